"""The self-calibration's confidence: a class's probability mass under a pair's two models of its scene.

A pair's Delta_avg answer (planar, and plane + parallax where that model converged) is a normal
of the fit's std; a class's confidence is its mass under the folded normal (Delta_avg is the size
of a signed offset), the two models weighed by ``analysis.flat_prior`` (:func:`flat_or_relief`).
Where the two answers fall in different classes and the plane + parallax answer gives the planar
answer's class little probability (:func:`relief_agreement` below ``analysis.relief_mass``) the
pair is "cannot tell" for relief.
:func:`rescored` (batched; one result: :func:`rescored_confidence`, :func:`rescored_relief_found`)
recomputes both from saved results under another decision (the fit on a validation split, ``workflows.decision_fit``);
a result is a :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`, or a mapping of its
JSON's keys (a saved ``to_json()``, or the few a synthetic split gives), read by :func:`result_field`.
:func:`delta_interval` is the one interval of the self-calibration's answers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import CLASS_LABELS, class_bounds, estimated_class
from lensdist_torch.workflows.pair_analysis import JSON_KEYS

__all__ = [
    "SceneModels",
    "scene_models",
    "flat_or_relief",
    "relief_agreement",
    "rescored",
    "rescored_confidence",
    "rescored_relief_found",
    "delta_interval",
    "result_field",
]

#: Coverage of a pair's Delta_avg interval (the self-calibration's): a normal's two-sided probability.
INTERVAL_CONFIDENCE = 0.95


def result_field(result, key: str, default=None):
    """One field of an analysis result, ``default`` where it is absent or None (null in JSON).

    ``result`` is a :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis` (``key``
    read as its attribute; ``class`` as ``class_label``, ...) or a mapping of the JSON's keys:
    a saved ``to_json()``, or the few keys a synthetic validation split gives.

    Example:
        >>> (result_field({"delta_avg_std": None}, "delta_avg_std", math.inf),
        ...  result_field({"in_domain": True}, "in_domain"))
        (inf, True)
    """
    attribute = {json_key: name for name, json_key in JSON_KEYS.items()}.get(key, key)
    value = result.get(key) if isinstance(result, Mapping) else getattr(result, attribute, None)
    return default if value is None else value


def rescored(results: list, cfg: LensdistConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(confidence, relief_found) of saved self-calibration results again, under ``cfg``, batched.

    From the answers each result keeps (``estimated_delta_avg`` and ``delta_avg_std``; with the
    plane + parallax model, ``planar_delta_avg`` and ``relief_delta_avg`` with their stds), the
    class of ``estimated_delta_avg`` under ``cfg`` and :func:`flat_or_relief`'s rule: what
    ``analyze`` would have said with ``cfg``. Confidence NaN without an estimate; relief_found the
    result's own flag where it keeps no plane + parallax answer. Used to fit the decision on a
    validation split without analysing its pairs again.

    Returns:
        (N,) float64 confidences, (N,) bool.
    """
    nan = float("nan")
    get = result_field  # a field absent or null (JSON): the default
    d = [get(r, "estimated_delta_avg", nan) for r in results]
    # without a plane + parallax answer the kept one is the planar one
    p = torch.tensor([[get(r, "planar_delta_avg", x), get(r, "planar_delta_avg_std", get(r, "delta_avg_std", nan))]
                      for r, x in zip(results, d)], dtype=torch.float64).view(-1, 2)
    q = torch.tensor([[get(r, "relief_delta_avg", nan), get(r, "relief_delta_avg_std", math.inf)] for r in results],
                     dtype=torch.float64).view(-1, 2)
    d = torch.tensor(d, dtype=torch.float64)
    conf, found, _, _ = _scene_models(_classes(d, cfg), p[:, 0], p[:, 1], q[:, 0], q[:, 1], cfg)
    stored = torch.tensor([bool(get(r, "relief_found", False)) for r in results], dtype=torch.bool)
    kept = torch.isfinite(q[:, 0]) & torch.isfinite(d)
    return torch.where(torch.isfinite(d), conf, nan), torch.where(kept, found, stored)


def rescored_confidence(res, cfg: LensdistConfig) -> float:
    """One result's raw confidence again, under ``cfg`` (:func:`rescored`).

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> res = {"estimated_delta_avg": 7.0, "delta_avg_std": 0.2}  # class 2 ends at 7.18 px: Phi(0.92)
        >>> round(rescored_confidence(res, LensdistConfig()), 3)
        0.822
    """
    return float(rescored([res], cfg)[0][0])


def rescored_relief_found(res, cfg: LensdistConfig) -> bool:
    """Whether one result finds relief under ``cfg`` (:func:`rescored`).

    Example:
        >>> import dataclasses
        >>> from lensdist_torch.config import LensdistConfig
        >>> res = {"estimated_delta_avg": 7.0, "delta_avg_std": 0.2,
        ...        "planar_delta_avg": 7.0, "planar_delta_avg_std": 0.2,
        ...        "relief_delta_avg": 7.6, "relief_delta_avg_std": 0.4}  # class 2: mass 0.15 under 7.6 +- 0.4
        >>> strict = LensdistConfig(
        ...     analysis=dataclasses.replace(LensdistConfig().analysis, relief_mass=0.1))  # below 0.1 only
        >>> rescored_relief_found(res, LensdistConfig()), rescored_relief_found(res, strict)
        (True, False)
    """
    return bool(rescored([res], cfg)[1][0])


class SceneModels(NamedTuple):
    """A pair's class over both models of its scene (:func:`scene_models`): tensors, or one pair's values.

    confidence: the class's mass, weighed over the planar and the plane + parallax answers.
    relief_found: "cannot tell" for relief (:func:`flat_or_relief`'s rule).
    agreement: the probability the plane + parallax answer gives the planar answer's class
        (:func:`relief_agreement`); NaN without a plane + parallax answer.
    parted: the two answers fall in different classes (False without a plane + parallax answer).
    """

    confidence: torch.Tensor | float
    relief_found: torch.Tensor | bool
    agreement: torch.Tensor | float
    parted: torch.Tensor | bool


def scene_models(
    label: str, planar: tuple[float, float], relief: tuple[float, float], cfg: LensdistConfig
) -> SceneModels:
    """One pair's :class:`SceneModels`: what :func:`flat_or_relief` weighs, and what it finds, in one pass.

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> m = scene_models("2", (7.0, 0.2), (7.6, 0.4), LensdistConfig())  # class 2 ends near 7.18 px
        >>> m.relief_found, m.parted, round(m.agreement, 3)
        (True, True, 0.149)
    """
    t = [torch.tensor([v], dtype=torch.float64) for v in (*planar, *relief)]
    m = _scene_models(torch.tensor([CLASS_LABELS.index(label)]), *t, cfg)
    return SceneModels(
        confidence=float(m.confidence[0]), relief_found=bool(m.relief_found[0]), agreement=float(m.agreement[0]),
        parted=bool(m.parted[0]))


def flat_or_relief(
    label: str, planar: tuple[float, float], relief: tuple[float, float], cfg: LensdistConfig
) -> tuple[float, bool]:
    """The raw confidence of a pair's class over both models of its scene, and whether they part.

    A user does not say whether the scene is flat. With the planar answer (Delta_avg, std) and
    the plane + parallax one, the confidence of ``label`` is its mass under each (the folded
    normal, each std times ``analysis.selfcal_std_scale``), weighted ``analysis.flat_prior`` and
    1 - that: ``w P(label | planar) + (1 - w) P(label | relief)``. Where the two answers fall in
    different classes and the plane + parallax answer gives the planar answer's class less
    probability than ``analysis.relief_mass`` (:func:`relief_agreement`; 1, the default: in
    different classes is enough) the class depends on whether the scene is flat, which one pair
    cannot tell: the second value (``relief_found``) is True. Without a plane + parallax answer
    (the model off, or not converged: a non-finite Delta_avg or std; the planar answer is then
    the kept one) the planar mass alone, and no relief found.

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> cfg = LensdistConfig()  # flat_prior 0.5; class 2 spans Delta_avg 3.6 to 7.2 px at 320 x 424
        >>> conf, found = flat_or_relief("2", (5.0, 0.2), (5.3, 0.4), cfg)
        >>> round(conf, 3), found
        (1.0, False)
        >>> flat_or_relief("2", (7.0, 0.2), (7.6, 0.4), cfg)[1]  # class 2 has mass 0.15 under 7.6 +- 0.4
        True
        >>> flat_or_relief("2", (5.0, 0.2), (float("nan"), float("inf")), cfg)[1]  # no relief answer
        False
    """
    m = scene_models(label, planar, relief, cfg)
    return m.confidence, m.relief_found


def relief_agreement(planar_delta: float, relief: tuple[float, float], cfg: LensdistConfig) -> float:
    """The probability the plane + parallax answer (Delta_avg, std) gives the planar answer's class.

    The class of ``planar_delta`` under ``cfg`` and its mass under the folded normal of the
    plane + parallax answer, the std times ``analysis.selfcal_std_scale``: near 1 where both
    models of the scene agree, near 0 where the relief moves the class. NaN without a finite
    plane + parallax answer.

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> round(relief_agreement(7.0, (7.6, 0.4), LensdistConfig()), 3)  # class 2 ends near 7.18 px: Phi(-1.04)
        0.149
    """
    d0 = torch.tensor([planar_delta], dtype=torch.float64)
    # the planar answer's own std and class weigh in the confidence only, not in the agreement
    return scene_models(CLASS_LABELS[int(_classes(d0, cfg)[0])], (planar_delta, 1.0), relief, cfg).agreement


def _scene_models(label, d0, s0, d1, s1, cfg: LensdistConfig) -> SceneModels:
    """:class:`SceneModels` of (N,) tensors: label class indices, the two answers and their stds."""
    a = cfg.analysis
    k, w = a.selfcal_std_scale, a.flat_prior
    bounds = torch.tensor([class_bounds(c, "delta_avg", cfg) for c in CLASS_LABELS], dtype=torch.float64)
    two = torch.isfinite(d1) & torch.isfinite(s1)
    planar = _mass(d0, k * s0, bounds[label])
    conf = torch.where(two, w * planar + (1 - w) * _mass(d1, k * s1, bounds[label]), planar)
    c0 = _classes(d0, cfg)
    agreement = torch.where(two, _mass(d1, k * s1, bounds[c0]), float("nan"))
    parted = two & (c0 != _classes(d1, cfg))
    return SceneModels(
        confidence=conf, relief_found=parted & (agreement < a.relief_mass), agreement=agreement, parted=parted)


def _classes(d: torch.Tensor, cfg: LensdistConfig) -> torch.Tensor:
    """The class indices (:data:`CLASS_LABELS`) of Delta_avg values (analysis px) under ``cfg``."""
    return estimated_class(d, d, metric="delta_avg", config=cfg)


def _mass(d: torch.Tensor, std: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """P(|D| in ]lo, hi]) for D ~ N(d, std^2), ``bounds`` (N, 2) each pair's class bin: the raw confidence of a class.

    Delta_avg is the size of a signed offset (barrel or pincushion), so its distribution is the
    folded normal: an estimate near 0 with a std of 0.2 px is R (|D| below the threshold) on both sides.
    Near a class boundary the class is a coin toss however small the std. A std that is not
    finite gives 0, one of 0 gives 1.
    """
    lo, hi = bounds.unbind(-1)
    safe = torch.where(torch.isfinite(std) & (std > 0), std, 1.0)
    cdf = torch.special.ndtr(torch.stack([hi - d, lo - d, -lo - d, -hi - d]) / safe)
    m = (cdf[0] - cdf[1] + cdf[2] - cdf[3]).clamp(1e-9, 1 - 1e-9)
    return torch.where(torch.isfinite(std), torch.where(std > 0, m, 1.0), 0.0)


def delta_interval(d: float, std: float, a) -> list[float] | None:
    """A pair's Delta_avg interval: [max(0, d - z k std), d + z k std]; None if std is not finite.

    ``a`` is the [analysis] settings: z the normal quantile of :data:`INTERVAL_CONFIDENCE`, k
    ``a.interval_std_scale``. The one interval of the self-calibration's answers (and of
    :func:`~lensdist_torch.workflows.decision_fit.interval_coverage`).

    Example:
        >>> from lensdist_torch.config import AnalysisConfig
        >>> [round(v, 3) for v in delta_interval(5.0, 0.5, AnalysisConfig())]  # z = 1.96
        [4.02, 5.98]
        >>> delta_interval(0.3, 0.5, AnalysisConfig())[0]  # clipped at 0: Delta_avg is a size
        0.0
    """
    if not math.isfinite(std):
        return None
    z = float(torch.special.ndtri(torch.tensor(0.5 + INTERVAL_CONFIDENCE / 2, dtype=torch.float64)))
    half = z * a.interval_std_scale * std
    return [max(0.0, d - half), d + half]
