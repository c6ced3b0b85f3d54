"""The decision fitted on a validation split: the R threshold, the confidence, the intervals.

``lensdist reproduce`` (through :func:`fit_confidence`) analyses the pairs of a validation split
(the protocol with another seed, :func:`validation_config`: never the test set) as ``analyze``
does, and fits the ``[analysis]`` values that turn the estimators' outputs into answers
(:func:`fit_decision`):

* ``no_distortion_px``: the R threshold with the most right self-calibration classes; of
  thresholds as right, the one whose confidence, fitted below, scores best (least log-loss),
  so the fit does not lean on the shipped value.
* ``selfcal_std_scale`` and ``flat_prior``: the factor on a pair's Delta_avg stds in the
  self-calibration's confidence and the weight of the planar model in it (its class's mass
  under both models of the scene, :func:`~lensdist_torch.workflows.class_mass.flat_or_relief`),
  the values of a grid whose confidences score best (least log-loss) as P(class right).
* ``min_confidence``: the least confidence of an answer, the value that answers most while the
  share of its answers that are right reaches :data:`TARGET_PRECISION` at the lower end of its 95 %
  interval, with at most :data:`MAX_CANNOT_TELL` of the pairs "cannot tell". ``relief_mass`` is not
  fitted: on rendered flat pairs naming relief only withholds right answers, on real frames it
  withheld a pair both models got wrong (docs/method.md, section 10).
* ``interval_std_scale``: the factor on the std in a pair's 95 % intervals, the least of the same
  grid whose intervals cover the true Delta_avg on ``class_mass.INTERVAL_CONFIDENCE`` of the pairs.
* the regression's Platt map, kept only where it lowers the split's ECE.

The fit's own covariance is what both scales correct: on the rendered planar conditions it is
about right for the intervals and a little wide for the classes; on a scene with relief both are
too narrow, since the relief biases the pair in a way its own residuals cannot show
(docs/method.md, section 10). Both are scored over the pairs whose answer the confidence decides
(:func:`scored_pairs`), the pairs the ECE is reported on.

The results are the analysis's :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`
records, or mappings of their JSON's keys (a synthetic split's few), each field read by
:func:`~lensdist_torch.workflows.class_mass.result_field`.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import estimated_class
from lensdist_torch.workflows.class_mass import INTERVAL_CONFIDENCE, delta_interval, rescored, result_field
from lensdist_torch.workflows.confidence import (
    expected_calibration_error,
    fit_platt,
    platt,
    precision_bound,
    reliability,
)
from lensdist_torch.workflows.decision import SELFCAL_CONFIDENCE_SCALE, SELFCAL_CONFIDENCE_SHIFT
from lensdist_torch.workflows.evaluate import analyze_test_set

__all__ = [
    "validation_config",
    "scored_pairs",
    "confidences",
    "outcomes",
    "answers",
    "fit_decision",
    "calibration_table",
    "interval_coverage",
    "coverage_row",
    "fit_confidence",
]

#: Per method, the ``[analysis]`` fields of its Platt map; None: the self-calibration's, a constant (the identity).
_PLATT = {"selfcal": None, "regression": ("regression_confidence_scale", "regression_confidence_shift")}
#: The validation split is the test set of the protocol seed plus this (never the test set itself).
VALIDATION_SEED_OFFSET = 1
#: Share right of the confident answers, at the lower end of its 95 % interval, that fitting min_confidence aims for.
TARGET_PRECISION = 0.97
#: The largest share of the split's pairs that may be "cannot tell" (any reason) at a fitted min_confidence.
MAX_CANNOT_TELL = 0.25

#: The candidate std scales (both): log-spaced from 0.5 to 4, and the config's own value.
_SCALES = tuple(torch.logspace(math.log10(0.5), math.log10(4.0), 25, dtype=torch.float64).tolist())
#: The candidate flat priors (with the std scale, where the pairs have a plane + parallax answer).
_PRIORS = tuple(i / 10 for i in range(1, 11))
#: The candidate least confidences of an answer.
_MIN_CONFIDENCES = (0.5, 0.6, 0.7, 0.8, 0.9)


def validation_config(config: LensdistConfig) -> LensdistConfig:
    """The protocol of the validation split: the seed moved by :data:`VALIDATION_SEED_OFFSET`.

    Its test set shares no pair with the test set of ``config`` (every pair's seed hashes the
    protocol seed, docs/method.md, section 7).

    Example:
        >>> validation_config(LensdistConfig()).protocol.seed - LensdistConfig().protocol.seed
        1
    """
    p = config.protocol
    return dataclasses.replace(config, protocol=dataclasses.replace(p, seed=p.seed + VALIDATION_SEED_OFFSET))


def _with(config: LensdistConfig, **analysis) -> LensdistConfig:
    return dataclasses.replace(config, analysis=dataclasses.replace(config.analysis, **analysis))


def scored_pairs(results: list, config: LensdistConfig) -> list[int]:
    """The pairs whose answer their confidence decides: the others are withheld for another reason.

    Registered, overlapping and in domain, with an estimate, moved by at least
    ``analysis.min_motion_px``, and no relief found under ``config``
    (:func:`~lensdist_torch.workflows.class_mass.rescored`: "cannot tell" whatever
    the confidence).

    Example:
        >>> ok = {"in_domain": True, "estimated_delta_avg": 5.0, "motion_px": 12.0, "relief_found": False}
        >>> scored_pairs([ok, ok | {"relief_found": True}, ok | {"motion_px": 0.4}], LensdistConfig())
        [0]
    """
    return _scored(results, config)[0]


def _scored(results: list, config: LensdistConfig) -> tuple[list[int], torch.Tensor]:
    """(:func:`scored_pairs`, every result's raw self-calibration confidence under ``config``): one rescoring."""
    a = config.analysis
    conf, relief = (
        rescored(results, config)
        if results
        else (torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.bool))
    )
    relief = relief.tolist()
    keep = [i for i, r in enumerate(results)
            if result_field(r, "in_domain") and result_field(r, "estimated_delta_avg") is not None and not relief[i]
            and not result_field(r, "motion_px", math.inf) < a.min_motion_px]
    return keep, conf


def _right(results: list, data: dict, config: LensdistConfig, keep: list[int]) -> torch.Tensor:
    """Whether the class of each kept pair's estimated Delta_avg under ``config`` (its R threshold) is the true one."""
    d = torch.tensor([result_field(results[i], "estimated_delta_avg") for i in keep], dtype=torch.float64)
    return estimated_class(d, d, metric="delta_avg", config=config) == data["class_avg"][keep]


def confidences(
    results: list, keep: list[int], *, config: LensdistConfig, method: str, calibrated: bool
) -> torch.Tensor:
    """The pairs ``keep``'s confidences under ``config`` (``calibrated``: through its Platt map).

    The self-calibration's raw one recomputed under ``config`` (its std scale, its R threshold),
    the regression's its own.
    """
    if method == "selfcal":
        raw = rescored([results[i] for i in keep], config)[0] if keep else torch.zeros(0, dtype=torch.float64)
    else:
        raw = torch.tensor([result_field(results[i], "raw_confidence") for i in keep], dtype=torch.float64)
    return _calibrated(raw, config, method) if calibrated else raw


def _calibrated(raw: torch.Tensor, config: LensdistConfig, method: str) -> torch.Tensor:
    """Raw confidences through ``method``'s Platt map (the regression's: ``config``'s)."""
    fields = _PLATT[method]
    return platt(raw, *((SELFCAL_CONFIDENCE_SCALE, SELFCAL_CONFIDENCE_SHIFT) if fields is None
                        else (getattr(config.analysis, f) for f in fields)))


def outcomes(results: list, data: dict, *, config: LensdistConfig, method: str, calibrated: bool):
    """(confidence, right) of the :func:`scored_pairs` under ``config``.

    The confidence raw, or through the config's Platt map where ``calibrated``; right: whether the
    pair's class is (``benchmarks/bench_relief_test.py`` scores candidate priors by it).
    """
    keep, raw = _scored(results, config)
    # the self-calibration's: from the rescoring that chose the pairs
    raw = (
        raw[keep] if method == "selfcal" else confidences(results, keep, config=config, method=method, calibrated=False)
    )
    return (_calibrated(raw, config, method) if calibrated else raw), _right(results, data, config, keep)


def _log_loss(p: torch.Tensor, right: torch.Tensor) -> float:
    p = p.clamp(1e-9, 1 - 1e-9)
    return float(-torch.where(right, p.log(), (-p).log1p()).mean())


def interval_coverage(results: list, data: dict, config: LensdistConfig) -> dict:
    """{"pairs", "coverage"}: the share of the :func:`scored_pairs` whose interval covers the true Delta_avg.

    The interval of the kept answer, as ``analyze`` gives it
    (:func:`~lensdist_torch.workflows.class_mass.delta_interval`).

    Example:
        >>> r = {"in_domain": True, "estimated_delta_avg": 5.0, "delta_avg_std": 0.5, "motion_px": 9.0}
        >>> interval_coverage([r, r | {"estimated_delta_avg": 7.0}], {"delta_avg": torch.tensor([5.5, 5.5])},
        ...                   LensdistConfig())
        {'pairs': 2, 'coverage': 0.5}
    """
    intervals = {
        i: delta_interval(
            result_field(results[i], "estimated_delta_avg"),
            result_field(results[i], "delta_avg_std", math.inf),
            config.analysis,
        )
        for i in scored_pairs(results, config)
    }
    intervals = {i: iv for i, iv in intervals.items() if iv is not None}
    if not intervals:
        return {"pairs": 0, "coverage": float("nan")}
    covered = [iv[0] <= float(data["delta_avg"][i]) <= iv[1] for i, iv in intervals.items()]
    return {"pairs": len(covered), "coverage": sum(covered) / len(covered)}


def fit_decision(results: dict, data: dict, config: LensdistConfig, trace: list | None = None) -> dict:
    """The [analysis] values fitted on a validation split's analysis results.

    ``no_distortion_px``: the R threshold with the most right self-calibration classes (of a
    log-spaced grid from 0.02 to 2 px; ties: the one whose confidence, the std scale and flat
    prior fitted at it, has the least log-loss, then the one nearest the current value; the
    classes alone left a plateau of 0.19-0.63 px on the default protocol, where the nearest to
    the shipped value decided). Then, on the
    :func:`scored_pairs` and of a log-spaced grid from 0.5 to 4 (ties: nearest the current
    value): ``selfcal_std_scale`` with ``flat_prior`` (0.1 to 1; only where the pairs have a
    plane + parallax answer), the least log-loss of the self-calibration's confidence as
    P(class right), kept at the config's where the pairs are all right or all wrong (nothing to
    score); then ``min_confidence`` of 0.5 to 0.9, the one with the most answers whose share
    right reaches :data:`TARGET_PRECISION` at the lower end of its 95 % interval, with at most
    :data:`MAX_CANNOT_TELL` of the pairs "cannot tell" (:func:`_fit_withholding`); then
    ``interval_std_scale``, the least
    whose intervals cover the true Delta_avg on ``class_mass.INTERVAL_CONFIDENCE`` of the scored pairs
    (the largest where none does). Then the Platt map of
    the regression's confidence, kept only where it lowers the split's ECE below the config's
    map. The self-calibration's Platt map is a constant, the identity: its
    confidence is a probability already, and its std scale is what is fitted. ``trace``, where
    given, receives the withholding's candidates with their answers on the split.
    """
    a0 = config.analysis
    grid = sorted(set(torch.logspace(math.log10(0.02), math.log10(2.0), 61, dtype=torch.float64).tolist())
                  | {a0.no_distortion_px})
    every = [i for i, r in enumerate(results["selfcal"])
             if result_field(r, "in_domain") and result_field(r, "estimated_delta_avg") is not None]
    counts = {t: int(_right(results["selfcal"], data, _with(config, no_distortion_px=t), every).sum()) for t in grid}
    most = max(counts.values())
    std_fits = {
        t: _std_fit(results["selfcal"], data, _with(config, no_distortion_px=t)) for t, n in counts.items() if n == most
    }
    best = min(std_fits, key=lambda t: (std_fits[t][0], abs(math.log(t / a0.no_distortion_px))))
    fitted = {"no_distortion_px": float(best)}
    cfg = _with(config, no_distortion_px=best)
    fitted |= _fit_withholding(results["selfcal"], data, cfg, std_fits[best][1:], trace)
    cfg = _with(cfg, **fitted)
    fitted["interval_std_scale"] = _fit_interval_scale(results["selfcal"], data, cfg)
    for method, fields in _PLATT.items():
        # a map fitted on the protocol, whose pairs mostly move by tens of pixels, made pairs that
        # moved by < 2 px claim 0.93 where 0.69 were right (docs/method.md, section 10): the
        # self-calibration's std scale keeps each pair's own std, and so its motion, in the confidence
        if method in results and fields is not None:
            f_scale, f_shift = fields
            raw, right = outcomes(results[method], data, config=cfg, method=method, calibrated=False)
            new, old = fit_platt(raw, right), (getattr(a0, f_scale), getattr(a0, f_shift))
            # a refit must earn its place: on a small split (--quick) it can fall back to the
            # identity and double the ECE of the map it replaces; then the config's map stays
            if expected_calibration_error(platt(raw, *new), right) >= expected_calibration_error(
                platt(raw, *old), right
            ):
                new = old
            fitted[f_scale], fitted[f_shift] = new
    return fitted


def _std_fit(results: list, data: dict, config: LensdistConfig) -> tuple[float, float, float]:
    """(log-loss, selfcal_std_scale, flat_prior) of the least log-loss over the config's scored pairs.

    The log-loss is inf where nothing is scored.
    """
    a = config.analysis
    keep = scored_pairs(results, config)  # fixed: the scores compare one set of pairs
    right = _right(results, data, config, keep)
    if right.numel() == 0 or bool(right.all()) or not bool(right.any()):
        # all right (or all wrong): the sharpest (or widest) scale would always win
        return math.inf, a.selfcal_std_scale, a.flat_prior
    has_relief = any(result_field(results[i], "relief_delta_avg") is not None for i in keep)
    priors = sorted(set(_PRIORS) | {a.flat_prior}) if has_relief else [a.flat_prior]  # no second model: no weight
    scores = [(_log_loss(confidences(results, keep, config=_with(config, selfcal_std_scale=s, flat_prior=w),
                                     method="selfcal", calibrated=True), right),
               abs(math.log(s / a.selfcal_std_scale)) + abs(w - a.flat_prior), s, w)
              for s in sorted(set(_SCALES) | {a.selfcal_std_scale}) for w in priors]
    best = min(scores)
    return float(best[0]), float(best[2]), float(best[3])


def _fit_withholding(results: list, data: dict, config: LensdistConfig, scale_prior: tuple[float, float],
                     trace: list | None = None) -> dict:
    """The confidence, and the least confidence of an answer, fitted on a split.

    ``scale_prior``: the std scale and the flat prior fitted at the config's threshold
    (:func:`_std_fit`); then, for each ``min_confidence``
    of :data:`_MIN_CONFIDENCES` (and the config's), the split's self-calibration answers as
    ``analyze`` would give them (:func:`answers`). Of the candidates with at most
    :data:`MAX_CANNOT_TELL` of the pairs "cannot tell", the one with the most answers whose share
    right is at least :data:`TARGET_PRECISION` at the lower end of its 95 % interval
    (:func:`~lensdist_torch.workflows.confidence.precision_bound`: the split's own chance allowed
    for); where none is, the one with the highest such bound; where none is within the limit,
    the config's. ``relief_mass`` stays the config's: a rendered split cannot price what naming
    relief guards against on real frames (docs/method.md, section 10).

    Returns:
        {"min_confidence", "selfcal_std_scale", "flat_prior"}; every candidate with its
        :func:`answers` appended to ``trace`` where given.
    """
    a = config.analysis
    k, w = scale_prior
    rows = []
    for m in sorted(set(_MIN_CONFIDENCES) | {a.min_confidence}):
        fit = {"min_confidence": float(m), "selfcal_std_scale": k, "flat_prior": w}
        got = answers(results, data, _with(config, **fit))
        if trace is not None:  # JSON: no NaN (no answer, no precision)
            trace.append(
                {key: v if not (isinstance(v, float) and math.isnan(v)) else None for key, v in (fit | got).items()}
            )
        if got["cannot_tell"] <= MAX_CANNOT_TELL and math.isfinite(got["precision_bound"]):
            rows.append(
                (got["precision_bound"] >= TARGET_PRECISION, got["answered"], got["precision_bound"], -m, fit)
            )
    if not rows:
        return {"min_confidence": a.min_confidence, "selfcal_std_scale": k, "flat_prior": w}
    reached = [r for r in rows if r[0]]
    best = max(reached, key=lambda r: r[1:4]) if reached else max(rows, key=lambda r: (r[2], -r[1], r[3]))
    return best[4]


def answers(results: list, data: dict, config: LensdistConfig) -> dict:
    """{"pairs", "answered", "cannot_tell", "precision", "precision_bound"} of the self-calibration's answers.

    Under ``config``, a pair is answered where it is scored (:func:`scored_pairs`) and its calibrated confidence
    reaches ``analysis.min_confidence``; "cannot tell" is the share of all pairs not answered (every reason),
    precision the share of the answers whose class is right (NaN without one), precision_bound the lower end of
    its 95 % interval (:func:`~lensdist_torch.workflows.confidence.precision_bound`).

    Example:
        >>> r = {"in_domain": True, "estimated_delta_avg": 5.0, "delta_avg_std": 0.2, "motion_px": 9.0}
        >>> got = answers([r, r | {"estimated_delta_avg": 8.0}, r | {"in_domain": False}],
        ...               {"class_avg": torch.tensor([1, 1, 1])}, LensdistConfig())  # 5 and 8 px: classes 2 and 3
        >>> got["answered"], round(got["cannot_tell"], 3), got["precision"]
        (2, 0.333, 0.5)
    """
    conf, right = outcomes(results, data, config=config, method="selfcal", calibrated=True)
    right = right[conf >= config.analysis.min_confidence]
    n = len(results)
    return {"pairs": n, "answered": int(right.numel()), "cannot_tell": (n - right.numel()) / n if n else float("nan"),
            "precision": float(right.double().mean()) if right.numel() else float("nan"),
            "precision_bound": precision_bound(int(right.sum()), int(right.numel()))}


def _fit_interval_scale(results: list, data: dict, config: LensdistConfig) -> float:
    want = INTERVAL_CONFIDENCE
    for s in sorted(set(_SCALES) | {config.analysis.interval_std_scale}):
        cov = interval_coverage(results, data, _with(config, interval_std_scale=s))
        if cov["pairs"] == 0:
            return float(config.analysis.interval_std_scale)
        if cov["coverage"] >= want:
            return float(s)
    return float(max(_SCALES))


def calibration_table(
    results: dict, data: dict, *, before: LensdistConfig, after: LensdistConfig, split: str
) -> tuple[list, dict]:
    """ECE rows (method, split, pairs, before, after) and reliability curves, per method in ``results``."""
    rows, curves = [], {}
    for method in _PLATT:
        if method not in results:
            continue
        b = reliability(*outcomes(results[method], data, config=before, method=method, calibrated=True))
        a = reliability(*outcomes(results[method], data, config=after, method=method, calibrated=True))
        rows.append({"method": method, "split": split, "pairs": a["pairs"], "before": b["ece"], "after": a["ece"]})
        curves[f"{method}, before"], curves[f"{method}, after"] = b, a
    return rows, curves


def coverage_row(results: list, data: dict, *, before: LensdistConfig, after: LensdistConfig, split: str) -> dict:
    """The self-calibration's interval coverage before and after the fitted decision, on one split."""
    b, a = interval_coverage(results, data, before), interval_coverage(results, data, after)
    return {"split": split, "pairs": a["pairs"], "before": b["coverage"], "after": a["coverage"],
            "nominal": INTERVAL_CONFIDENCE}


def _toml(config: LensdistConfig) -> str:
    """The whole config as TOML (JSON's numbers, strings, booleans and lists are TOML's too)."""
    import json

    from lensdist_torch.config import config_to_dict

    lines = ["# written by fit_confidence: load with --config (lensdist analyze / evaluate)"]
    for section, values in config_to_dict(config).items():
        lines += ["", f"[{section}]"] + [f"{k} = {json.dumps(v, allow_nan=False)}" for k, v in values.items()]
    return "\n".join(lines) + "\n"


def fit_confidence(config: LensdistConfig, out, *, regression=None, scenes: list | None = None, workers: int = 1,
                   batch_size: int = 16, progress: bool = True, device=None, figures: bool = True) -> dict:
    """Fit the R threshold, the confidence and the intervals on a validation split, and write them.

    The validation split is the test set of :func:`validation_config` (another protocol seed:
    never the test set), generated under ``out/validation`` (reused when there). Its pairs are
    analysed with the self-calibration (and ``regression``, a model or checkpoint path, when
    given) and :func:`fit_decision` fits the [analysis] values.

    Writes ``out/calibration.json`` (the fitted values, the withholding's candidates with their
    answers on the split (``withholding``), the ECE and the interval coverage before
    and after, the reliability bins), ``out/calibration.toml`` (the calibrated config, for
    ``--config``) and ``out/reliability_validation.png`` (with matplotlib).

    Returns:
        {"config": the calibrated config, "analysis": the fitted values, "ece": rows,
        "intervals": a row, "reliability": curves, "json": path}.
    """
    from pathlib import Path

    from lensdist_torch.core.storage import atomic_write_text
    from lensdist_torch.data.shards import generate, load_set
    from lensdist_torch.workflows.reports import dumps_strict

    out = Path(out)
    generate(
        validation_config(config),
        out / "validation",
        sets=["test"],
        workers=workers,
        batch_size=batch_size,
        progress=progress,
    )
    data = load_set(out / "validation", "test")
    runs = {"selfcal": {"method": "selfcal"}}
    if regression is not None:
        runs["regression"] = {"method": "regression", "checkpoint": regression}
    results = analyze_test_set(
        data, runs, scenes, config=config, batch_size=batch_size, progress=progress, device=device
    )
    candidates: list = []
    fitted = fit_decision(results, data, config, candidates)
    calibrated = _with(config, **fitted)
    rows, curves = calibration_table(results, data, before=config, after=calibrated, split="validation")
    intervals = [coverage_row(results["selfcal"], data, before=config, after=calibrated, split="validation")]
    summary = {"analysis": fitted, "withholding": candidates, "ece": rows, "intervals": intervals,
               "reliability": curves, "validation_pairs": int(data["index"].numel()),
               "validation_seed": validation_config(config).protocol.seed}
    path = out / "calibration.json"
    atomic_write_text(path, dumps_strict(summary, indent=2) + "\n")
    atomic_write_text(out / "calibration.toml", _toml(calibrated))
    if figures:
        from lensdist_torch.workflows.figures import have_matplotlib, save_reliability

        if have_matplotlib():
            save_reliability(curves, out / "reliability_validation.png", "reliability on the validation split")
    return {**summary, "config": calibrated, "json": str(path)}
