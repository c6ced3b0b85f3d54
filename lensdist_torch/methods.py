"""The beyond-the-paper methods on a generated test set, reported like the eigen-space one.

* ``regression``: :class:`DeltaRegressor` (ridge on PCA coefficients of the quality map),
  trained on all training pairs at once; classes come from the predicted Delta (it has no
  reject class: class-R pairs count as errors unless predicted below ``NO_DISTORTION_PX``).
* ``selfcal``: :func:`estimate_distortion` on the test pairs' images, re-rendered from their
  seeds (a pair is a pure function of its index, so nothing but the maps is stored); classes
  from the estimated Delta, R where the estimated Delta_avg is below ``NO_DISTORTION_PX``.

Both report their "cannot tell" share and the accuracy among confident pairs.
"""

from __future__ import annotations

import torch
from tqdm.auto import tqdm

from .config import LensdistConfig
from .dataset import CLASS_KEYS
from .distortion import REJECT, delta_avg as _delta_avg, delta_max as _delta_max, delta_top, distortion_class
from .evaluation import evaluate_predictions
from .regression import DeltaRegressor
from .selfcal import estimate_distortion
from .synthesis import draw_pairs, render_pairs

__all__ = ["NO_DISTORTION_PX", "TY_BINS", "motion_groups", "fit_regressor", "evaluate_regressor", "evaluate_selfcal"]

#: An estimated Delta_avg below this (px at 320 x 424) means "no visible distortion" (class R).
#: Class 1 spans ]0, 3.6] px; a true Delta_avg below 0.25 px occurs in well under 1 % of pairs.
NO_DISTORTION_PX = 0.25
TY_BINS = (0.0, 5.0, 10.0, 20.0, 40.0001)


def motion_groups(test: dict) -> dict:
    """Masks of test pairs by vertical motion t_y (the distortion hides when t_y is small)."""
    ty = test["motion"][:, 0]
    return {f"t_y {lo:.0f}-{min(hi, 40):.0f} px": (ty >= lo) & (ty < hi) for lo, hi in zip(TY_BINS[:-1], TY_BINS[1:])}


def _with_confidence(fig: dict, pred: torch.Tensor, truth: torch.Tensor, confident: torch.Tensor) -> dict:
    fig["confident_share"] = 100.0 * float(confident.double().mean())
    fig["confident_rate"] = 100.0 * float((pred[confident] == truth[confident]).double().mean()) if bool(confident.any()) else float("nan")
    return fig


def fit_regressor(train: dict, config: LensdistConfig, features: torch.Tensor) -> DeltaRegressor:
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
        label = torch.where(res.delta_avg < NO_DISTORTION_PX, torch.full_like(label, REJECT), label)
        top = delta_top(metric, cfg.image.height, cfg.image.width, cfg.distortion)
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
        k2, k4, _, info = estimate_distortion(img1, img2)
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
        top = delta_top(metric, h, w, config.distortion)
        label = distortion_class(pred_delta, top)
        label = torch.where((d_avg < NO_DISTORTION_PX) | ~converged, torch.full_like(label, REJECT), label)
        truth = test[CLASS_KEYS[metric]]
        fig = evaluate_predictions(label, pred_delta, truth, test[metric], top, converged, motion_groups(test))
        fig.update(method="selfcal", metric=metric, diverged=int((~converged).sum()))
        out[metric] = _with_confidence(fig, label, truth, confident)
    return out
