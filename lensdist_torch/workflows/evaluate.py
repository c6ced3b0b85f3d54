"""Every method on a generated test set, through the user's analysis path.

The test pairs are re-rendered from their seeds (a pair is a pure function of its index, so
nothing but the maps is stored) and analysed by
:func:`~lensdist_torch.workflows.analyze.analyze_batch`, exactly as ``lensdist analyze`` would
analyse them: the registration, the quality map, the method and the decision (class or "cannot
tell"). The class-R pairs are analysed with the protocol's perturbed registration
(docs/method.md, section 7), passed as ``homography``. The figures
(:func:`~lensdist_torch.workflows.reports.evaluate_predictions`) count "cannot tell" as its own
outcome.

* ``eigenspace``: the paper's classifiers, a Delta_avg and a Delta_max one together.
* ``regression``: :class:`DeltaRegressor` (nearest neighbours in PCA coefficients of the map).
* ``selfcal``: :func:`estimate_distortion`, started from the registration's H.

The learned methods' checkpoints carry the scenes they were fitted on and their texture
statistics (:func:`training_extra`) for the domain check of the analysis.
"""

from __future__ import annotations

import dataclasses

import torch
from tqdm.auto import tqdm

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.manifest import data_config_difference
from lensdist_torch.data.shards import CLASS_KEYS, load_scenes
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.distortion import CLASS_LABELS, delta_top
from lensdist_torch.metric.quality import counts_to_map
from lensdist_torch.workflows.analyze import analyze_batch, prepare_batch
from lensdist_torch.workflows.decision import REASONS
from lensdist_torch.workflows.pair_analysis import PairAnalysis
from lensdist_torch.workflows.reports import CANNOT_TELL, evaluate_predictions
from lensdist_torch.workflows.texture import texture_statistics

__all__ = [
    "TY_BINS",
    "motion_groups",
    "features_of",
    "training_extra",
    "fit_classifier",
    "fit_regressor",
    "analyze_test_set",
    "figures_of",
    "evaluate_classifier",
    "evaluate_regressor",
    "evaluate_selfcal",
    "evaluate_checkpoints",
]

TY_BINS = (0.0, 5.0, 10.0, 20.0, 40.0001)


def motion_groups(test: dict) -> dict:
    """Masks of test pairs by vertical motion t_y (the distortion hides when t_y is small)."""
    ty = test["motion"][:, 0]
    return {f"t_y {lo:.0f}-{min(hi, 40):.0f} px": (ty >= lo) & (ty < hi) for lo, hi in zip(TY_BINS[:-1], TY_BINS[1:])}


def features_of(data: dict, config: LensdistConfig) -> torch.Tensor:
    """Feature vectors (N, (H/8)(W/8)) of a loaded set: quality maps, rows concatenated."""
    return counts_to_map(data["counts"], config.quality).flatten(1)


def training_extra(config: LensdistConfig, scenes: list | None = None, names: list | None = None) -> dict:
    """A checkpoint's ``extra``: the scenes it is fitted on and their texture statistics.

    ``scenes`` / ``names`` default to the embedded scenes of ``config.protocol.scenes``.
    """
    if scenes is None:
        scenes, names = load_scenes(config)
    return {"scenes": list(names), "texture": texture_statistics(config, scenes, names)}


def fit_classifier(train: dict, config: LensdistConfig, *, n_eigenvectors: int | None = None, metric: str | None = None,
                   extra: dict | None = None) -> EigenSpaceClassifier:
    """Fit on a loaded training set. Pairs whose registration failed are left out of the fit.

    ``config`` must agree with the config the set was generated with (``train["config"]``) on
    every field that changes the pairs (the data fingerprint's: quality thresholds, image size,
    distortion, protocol, registration); ValueError naming the first that differs. So the
    checkpoint records the data's config there, and ``config``'s own classifier settings.
    ``extra`` (e.g. :func:`training_extra`) is kept as ``model.extra`` and saved with it.
    """
    if "config" in train:
        diff = data_config_difference(train["config"], config)
        if diff:
            raise ValueError(
                f"the config differs from the one the training data was generated with on {diff}: the maps were made "
                "with the data's; drop --config, change only its classifier settings, or generate data with it"
            )
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
    model.extra = dict(extra or {})
    return model


def fit_regressor(train: dict, config: LensdistConfig, features: torch.Tensor | None = None,
                  extra: dict | None = None) -> DeltaRegressor:
    """Fit a :class:`DeltaRegressor` on the training pairs whose registration converged."""
    features = features_of(train, config) if features is None else features
    ok = train["converged"]
    model = DeltaRegressor(features.shape[1], config)
    model = model.fit(features[ok], train["delta_avg"][ok].float(), train["delta_max"][ok].float())
    model.extra = dict(extra or {})
    return model


# ------------------------------------------------------------------ the analysis of a test set
def _scenes_of(test: dict, scenes):
    return scenes if scenes is not None else load_scenes(test["config"])[0]


def analyze_test_set(test: dict, runs: dict, scenes: list | None = None, *, config: LensdistConfig | None = None,
                     batch_size: int = 16, progress: bool = False, device=None, set_name: str = "test") -> dict:
    """Analyse every pair of a loaded test set with :func:`analyze_batch`, once per run.

    Args:
        test: a set from ``load_set``.
        runs: {name: keyword arguments of analyze_batch} (``method``, ``checkpoint``, ...); a run's
            ``decision``, where given, is its own ``[analysis]`` section, answered from the same
            fits (:meth:`~lensdist_torch.workflows.prepare.PreparedPairs.with_decision`).
        scenes: the scenes the set was rendered from (default: the embedded scenes of its config).
        config: the analysis settings (default: the set's config).
        batch_size: pairs rendered and registered together.
        progress: a progress bar on stderr.
        device: where the analysis runs.
        set_name: the protocol set the pairs belong to (``test``).

    Returns:
        {name: one :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis` per pair, in the
        set's order}. Every run of a batch shares one rendering, registration and self-calibration.
    """
    cfg = config if config is not None else test["config"]
    scenes = _scenes_of(test, scenes)
    n = test["index"].numel()
    out = {name: [] for name in runs}
    for s in tqdm(range(0, n, batch_size), desc="analysis", disable=not progress):
        idx = test["index"][s : s + batch_size]
        params = draw_pairs(test["config"], set_name, idx.tolist(), len(scenes))
        img1, img2 = render_pairs(scenes, params, test["config"])
        perturbed = test["perturbed"][s : s + batch_size].bool()
        parts = []  # distorted pairs: the analysis's own registration; class R: the protocol's
        for sel, hom in ((~perturbed, None), (perturbed, test["H"][s : s + batch_size][perturbed])):
            if bool(sel.any()):
                rows = sel.nonzero().flatten()
                prep = prepare_batch(img1[rows], img2[rows], config=cfg, homography=hom, device=device)
                parts.append((rows, {name: _run(prep, **kw) for name, kw in runs.items()}))
        for name in runs:
            batch = [None] * len(idx)
            for rows, res in parts:
                for r, one in zip(rows.tolist(), res[name]):
                    batch[r] = one
            out[name] += batch
    return out


def _run(prep, decision=None, **kw) -> list[PairAnalysis]:
    """One run of :func:`analyze_test_set` on a prepared batch, under its own decision where it has one."""
    prep = prep if decision is None else prep.with_decision(decision)
    return analyze_batch(None, None, config=prep.config, prepared=prep, **kw)


def figures_of(results: list[PairAnalysis], test: dict, metric: str, config: LensdistConfig) -> dict:
    """One metric's figures from analysis results of a test set's pairs (``cannot tell`` its own outcome)."""
    labels = [r.class_label if metric == "delta_avg" else r.class_max_label for r in results]
    pred = torch.tensor([CANNOT_TELL if lab is None else CLASS_LABELS.index(lab) for lab in labels])
    # the estimator's own number, also where the answer is "cannot tell"
    own = [r.estimated_delta_avg if metric == "delta_avg" else r.estimated_delta_max for r in results]
    delta = torch.tensor([float("nan") if d is None else d for d in own], dtype=torch.float64)
    truth = test[CLASS_KEYS[metric]]
    ok = torch.tensor([r.registration_ok for r in results])
    fig = evaluate_predictions(
        pred,
        delta,
        truth,
        test[metric],
        delta_range=delta_top(metric, config),
        registration_ok=ok,
        extra_groups=motion_groups(test),
    )
    fig["metric"] = metric
    reasons = [code for r in results for code in r.cannot_tell_reasons]
    fig["cannot_tell_reasons"] = {code: reasons.count(code) for code in REASONS if code in reasons}
    fig["per_pair"] = {
        "index": test["index"].tolist(),
        "class": labels,
        "delta": own,
        "confidence": [r.confidence for r in results],
        "cannot_tell_reasons": [r.cannot_tell_reasons for r in results],
    }
    return fig


def _run_or_use(results, test, scenes, run, config, progress, device, batch_size=16):
    if results is not None:
        return results
    return analyze_test_set(test, {"run": run}, scenes, config=config, batch_size=batch_size, progress=progress,
                            device=device)["run"]


def evaluate_classifier(model: EigenSpaceClassifier, test: dict, scenes: list | None = None, *,
                        partner: EigenSpaceClassifier | None = None, results: list | None = None,
                        config: LensdistConfig | None = None, progress: bool = False, device=None) -> dict:
    """Figures of a fitted eigen-space classifier on a loaded test set, through the analysis.

    ``partner`` is the classifier of the other Delta metric analysed with it (none by default);
    ``results`` are analysis results of the set's pairs already computed with them.
    """
    cfg = config if config is not None else test["config"]
    metric = model.config.classifier.metric
    pair = (model, partner) if metric == "delta_avg" else (partner, model)
    run = {"method": "eigenspace", "checkpoint": pair[0] or False, "checkpoint_max": pair[1] or False}
    out = figures_of(_run_or_use(results, test, scenes, run, cfg, progress, device), test, metric, cfg)
    out["method"] = "eigenspace"
    out["n_eigenvectors"] = model.config.classifier.n_eigenvectors
    out["reject_threshold"] = float(model.reject_threshold)
    out["explained_variance"] = model.explained.tolist()
    out["paper_key"] = f"{model.config.classifier.n_eigenvectors}ev_{metric}"
    return out


def evaluate_regressor(model: DeltaRegressor, test: dict, scenes: list | None = None, *, results: list | None = None,
                       config: LensdistConfig | None = None, progress: bool = False, device=None) -> dict:
    """{metric: figures} for both Delta metrics, from one analysis per test pair."""
    cfg = config if config is not None else test["config"]
    res = _run_or_use(results, test, scenes, {"method": "regression", "checkpoint": model}, cfg, progress, device)
    return {m: {**figures_of(res, test, m, cfg), "method": "regression"} for m in ("delta_avg", "delta_max")}


def evaluate_selfcal(
    test: dict,
    *,
    config: LensdistConfig | None = None,
    scenes: list | None = None,
    batch_size: int = 16,
    progress: bool = True,
    results: list | None = None,
    device=None,
) -> dict:
    """{metric: figures} of the self-calibration of every test pair (re-rendered, analysed)."""
    cfg = config if config is not None else test["config"]
    res = _run_or_use(results, test, scenes, {"method": "selfcal"}, cfg, progress, device, batch_size)
    out = {}
    for m in ("delta_avg", "delta_max"):
        out[m] = {**figures_of(res, test, m, cfg), "method": "selfcal",
                  "diverged": sum(bool(r.registration_ok) and r.estimated_delta_avg is None for r in res)}
    return out


def evaluate_checkpoints(test: dict, checkpoints=(), *, regression=None, selfcal: bool = False, progress: bool = False,
                         device=None, config: LensdistConfig | None = None) -> dict:
    """``lensdist evaluate``: {setting: figures} of checkpoints (paths) on a loaded test set.

    Eigen-space classifiers with the same number of eigenvectors, one per Delta metric, are
    analysed together (as ``analyze`` does); a lone one alone. The test set must be of the
    embedded scenes (its pairs are re-rendered). ``config`` holds the analysis settings (e.g. a
    calibrated one; default: the set's own), of the set's image size and quality thresholds.
    """
    from lensdist_torch.core.storage import check_compatible

    cfg = test["config"] if config is None else config
    check_compatible(cfg, test["config"], "(--config)")
    groups: list[dict] = []
    for path in checkpoints:
        model = EigenSpaceClassifier.load(path, expected=cfg)
        c = model.config.classifier
        group = next((g for g in groups if g["n"] == c.n_eigenvectors and c.metric not in g), None)
        if group is None:
            group = {"n": c.n_eigenvectors}
            groups.append(group)
        group[c.metric] = model
    runs = {f"eigenspace {i}": {"method": "eigenspace", "checkpoint": g.get("delta_avg", False),
                                "checkpoint_max": g.get("delta_max", False)} for i, g in enumerate(groups)}
    reg = DeltaRegressor.load(regression, expected=cfg) if regression else None
    if reg is not None:
        runs["regression"] = {"method": "regression", "checkpoint": reg}
    if selfcal:
        runs["selfcal"] = {"method": "selfcal"}
    results = analyze_test_set(test, runs, None, config=cfg, progress=progress, device=device)
    settings = {}
    for i, g in enumerate(groups):
        for metric in ("delta_max", "delta_avg"):
            if metric in g:
                other = g.get("delta_avg" if metric == "delta_max" else "delta_max")
                name = f"{g['n']} EV, {metric}" + ("" if f"{g['n']} EV, {metric}" not in settings else f" ({i + 1})")
                settings[name] = evaluate_classifier(
                    g[metric], test, partner=other, results=results[f"eigenspace {i}"], config=cfg
                )
    if reg is not None:
        settings.update(
            {
                f"regression, {m}": f
                for m, f in evaluate_regressor(reg, test, results=results["regression"], config=cfg).items()
            }
        )
    if selfcal:
        settings.update(
            {f"selfcal, {m}": f for m, f in evaluate_selfcal(test, config=cfg, results=results["selfcal"]).items()}
        )
    return settings
