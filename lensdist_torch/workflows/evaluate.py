"""The beyond-the-paper methods on a generated test set, reported like the eigen-space one.

* ``regression``: :class:`DeltaRegressor` (nearest neighbours in PCA coefficients of the
  quality map), trained on all training pairs at once; classes come from the predicted Delta
  (:func:`estimated_class`: R below ``config.analysis.no_distortion_px``).
* ``selfcal``: :func:`estimate_distortion` on the test pairs' images, re-rendered from their
  seeds (a pair is a pure function of its index, so nothing but the maps is stored); classes
  from the estimated Delta by the same rule.

Both report their "cannot tell" share and the accuracy among confident pairs.
"""

from __future__ import annotations

import dataclasses

import torch
from tqdm.auto import tqdm

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.shards import CLASS_KEYS
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.distortion import delta_avg as _delta_avg
from lensdist_torch.geometry.distortion import delta_max as _delta_max
from lensdist_torch.geometry.distortion import delta_top, estimated_class
from lensdist_torch.geometry.selfcal import estimate_distortion
from lensdist_torch.metric.quality import counts_to_map
from lensdist_torch.workflows.reports import evaluate_predictions

__all__ = [
    "TY_BINS",
    "motion_groups",
    "features_of",
    "fit_classifier",
    "evaluate_classifier",
    "fit_regressor",
    "evaluate_regressor",
    "evaluate_selfcal",
]

TY_BINS = (0.0, 5.0, 10.0, 20.0, 40.0001)


def motion_groups(test: dict) -> dict:
    """Masks of test pairs by vertical motion t_y (the distortion hides when t_y is small)."""
    ty = test["motion"][:, 0]
    return {f"t_y {lo:.0f}-{min(hi, 40):.0f} px": (ty >= lo) & (ty < hi) for lo, hi in zip(TY_BINS[:-1], TY_BINS[1:])}


def _with_confidence(fig: dict, pred: torch.Tensor, truth: torch.Tensor, confident: torch.Tensor) -> dict:
    fig["confident_share"] = 100.0 * float(confident.double().mean())
    fig["confident_rate"] = 100.0 * float((pred[confident] == truth[confident]).double().mean()) if bool(confident.any()) else float("nan")
    return fig


def features_of(data: dict, config: LensdistConfig) -> torch.Tensor:
    """Feature vectors (N, (H/8)(W/8)) of a loaded set: quality maps, rows concatenated."""
    return counts_to_map(data["counts"], config.quality).flatten(1)


def fit_classifier(train: dict, config: LensdistConfig, n_eigenvectors: int | None = None, metric: str | None = None) -> EigenSpaceClassifier:
    """Fit on a loaded training set. Pairs whose registration failed are left out of the fit."""
    c = config.classifier
    c = dataclasses.replace(
        c,
        n_eigenvectors=n_eigenvectors if n_eigenvectors is not None else c.n_eigenvectors,
        metric=metric if metric is not None else c.metric,
    )
    cfg = dataclasses.replace(config, classifier=c)
    ok = train["converged"]
    x = features_of(train, cfg)[ok]
    model = EigenSpaceClassifier(x.shape[1], cfg)
    model.fit(x, train[CLASS_KEYS[c.metric]][ok], train[c.metric][ok].float())
    return model


def evaluate_classifier(model: EigenSpaceClassifier, test: dict) -> dict:
    """Figures of a fitted classifier on a loaded test set (all pairs, failed ones counted)."""
    cfg = model.config
    metric = cfg.classifier.metric
    with torch.no_grad():
        res = model(features_of(test, cfg))
    top = delta_top(metric, cfg)
    out = evaluate_predictions(
        res.label, res.delta, test[CLASS_KEYS[metric]], test[metric], top, test["converged"], motion_groups(test)
    )
    out["n_eigenvectors"] = cfg.classifier.n_eigenvectors
    out["metric"] = metric
    out["reject_threshold"] = float(model.reject_threshold)
    out["explained_variance"] = model.explained.tolist()
    out["paper_key"] = f"{cfg.classifier.n_eigenvectors}ev_{metric}"
    return out


def fit_regressor(train: dict, config: LensdistConfig, features: torch.Tensor) -> DeltaRegressor:
    """Fit a :class:`DeltaRegressor` on the training pairs whose registration converged."""
    ok = train["converged"]
    model = DeltaRegressor(features.shape[1], config)
    return model.fit(features[ok], train["delta_avg"][ok].float(), train["delta_max"][ok].float())


def evaluate_regressor(model: DeltaRegressor, test: dict, features: torch.Tensor) -> dict:
    """{metric: figures} for both Delta metrics, from one prediction per test pair."""
    cfg = model.config
    with torch.no_grad():
        res = model(features)
    out = {}
    for metric, pred_delta, label in (("delta_avg", res.delta_avg, res.class_avg), ("delta_max", res.delta_max, res.class_max)):
        top = delta_top(metric, cfg)
        truth = test[CLASS_KEYS[metric]]
        fig = evaluate_predictions(label, pred_delta, truth, test[metric], top, test["converged"], motion_groups(test))
        fig.update(method="regression", metric=metric)
        out[metric] = _with_confidence(fig, label, truth, res.confident)
    return out


def evaluate_selfcal(test: dict, config: LensdistConfig, scenes: list, batch_size: int = 16, progress: bool = True) -> dict:
    """Self-calibrate every test pair (images re-rendered from the pairs' seeds).

    Returns {metric: figures} for both Delta metrics, from one estimation per pair.
    """
    h, w = config.image.height, config.image.width
    n = test["index"].numel()
    k2s, k4s, confident, converged = [], [], [], []
    for s in tqdm(range(0, n, batch_size), desc="self-calibration", disable=not progress):
        idx = test["index"][s : s + batch_size].tolist()
        params = draw_pairs(config, "test", idx, len(scenes))
        img1, img2 = render_pairs(scenes, params, config)
        k2, k4, _, info = estimate_distortion(img1, img2, config=config.selfcal)
        k2s.append(k2)
        k4s.append(k4)
        confident.append(info.confident & info.converged)
        converged.append(info.converged)
    converged, confident = torch.cat(converged), torch.cat(confident)
    # a diverged pair has NaN coefficients: it is predicted R with Delta 0, and counted
    k2, k4 = torch.nan_to_num(torch.cat(k2s)), torch.nan_to_num(torch.cat(k4s))
    d_avg = _delta_avg(k2, k4, h, w)
    out = {}
    for metric in ("delta_avg", "delta_max"):
        pred_delta = d_avg if metric == "delta_avg" else _delta_max(k2, k4, h, w)
        top = delta_top(metric, config)
        label = estimated_class(torch.where(converged, pred_delta, torch.nan), torch.where(converged, d_avg, torch.nan), metric, config)
        truth = test[CLASS_KEYS[metric]]
        fig = evaluate_predictions(label, pred_delta, truth, test[metric], top, converged, motion_groups(test))
        fig.update(method="selfcal", metric=metric, diverged=int((~converged).sum()))
        out[metric] = _with_confidence(fig, label, truth, confident)
    return out
