"""Several reconstructions of one sequence: the engine's run-to-run variation in the interval.

COLMAP's incremental mapping is a chain of random choices (the initial pair, RANSAC for every new
view's pose, the triangulation); on hard footage another seed registers other views and ends in
another camera. By default one mapping answers and its models' jackknife checks their posteriors
(:mod:`~lensdist_torch.calibration.multiview_evidence`); with ``multiview.reconstructions`` above one
the mapping runs that many times on the same features and matches (seeds ``seed``, ``seed`` + 1,
...; :func:`~lensdist_torch.calibration.multiview.reconstruct`), each reconstruction is
self-calibrated, and :func:`combine_reconstructions` measures the engine's variation. A mapping
that registers too few frames is no answer but a failed start (a wrong initial pair: the focal
length runs off and the mapping ends in about a second), so up to ``multiview.EXTRA_MAPPINGS``
further seeds are tried until ``reconstructions`` succeed; the failures are listed. :func:`combine_reconstructions`

* answers with the median reconstruction by Delta_avg (of two in the middle, the one with more
  registered frames, then the lower reprojection RMS);
* adds the largest |Delta_avg - the answer's| over the reconstructions (``reconstruction_spread``)
  to the interval in quadrature with each side's own half-width h (the models' posteriors mixed by
  their evidence, :mod:`~lensdist_torch.calibration.multiview_evidence`): sqrt(h^2 + (z spread)^2), z
  the normal quantile of ``calibration.confidence``;
* withholds the class ("cannot tell", the reason naming the spread) when fewer than
  ``reconstructions`` reconstructions succeeded, when two of them disagree beyond their own
  intervals, when the widened interval is too wide, or when it spans a sequence's R threshold
  at the paper's frame (:func:`~lensdist_torch.calibration.sequence_class.sequence_class`).
"""

from __future__ import annotations

import dataclasses
import math
from statistics import NormalDist

from lensdist_torch.calibration.multiview import MultiViewCalibration
from lensdist_torch.calibration.sequence_class import interval_class
from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.config.checks import or_defaults

__all__ = ["reconstruction_spread", "widened_interval", "combine_reconstructions"]


def reconstruction_spread(values: list[float], answer: float) -> float:
    """The largest |value - answer| (px) over the reconstructions' ``values`` (0 for one)."""
    return max((abs(v - answer) for v in values), default=0.0)


def widened_interval(value: float, interval: tuple[float, float], spread: float, t: float) -> tuple[float, float]:
    """``interval`` about ``value`` with ``spread`` added in quadrature under ``t`` on each side, the lower end >= 0.

    Each side's half-width h (the models' mixture may be lopsided) becomes sqrt(h^2 + (t spread)^2).

    Example:
        >>> [round(v, 3) for v in widened_interval(10.0, (9.0, 14.0), 1.0, 2.0)]  # sqrt(1 + 4), sqrt(16 + 4)
        [7.764, 14.472]
    """
    lo, hi = interval
    ts = t * spread
    return max(0.0, value - math.hypot(value - lo, ts)), value + math.hypot(hi - value, ts)


def _summary(seed: int, run) -> dict:
    if isinstance(run, str):
        return {"seed": seed, "failed": run}
    return {"seed": seed, "registered": run.registered, "points3D": run.points3D, "model": run.model,
            "reprojection_px": run.reprojection_px, "delta_avg_user_px": run.delta_avg_user_px,
            "delta_avg_user_interval": list(run.delta_avg_user_interval), "class": run.class_label,
            "reason": run.reason or None}


def _median(ok: list[MultiViewCalibration]) -> MultiViewCalibration:
    ranked = sorted(ok, key=lambda r: r.delta_avg_user_px)
    middle = ranked[(len(ranked) - 1) // 2: len(ranked) // 2 + 1]
    return max(middle, key=lambda r: (r.registered, -r.reprojection_px))


def _disagreement(runs: list[tuple[int, MultiViewCalibration]]) -> str:
    """'' when every two reconstructions' Delta_avg intervals overlap, else the reconstructions named."""
    ivs = [r.delta_avg_user_interval for _, r in runs]
    # intervals overlap pairwise exactly when the largest lower end is at most the smallest upper end
    if max(lo for lo, _ in ivs) <= min(hi for _, hi in ivs):
        return ""
    return ", ".join(f"seed {s} {r.delta_avg_user_px:.2f} px [{r.delta_avg_user_interval[0]:.2f}, "
                     f"{r.delta_avg_user_interval[1]:.2f}]" for s, r in runs)


def combine_reconstructions(runs: list[tuple[int, MultiViewCalibration | str]],
                            config: MultiViewConfig | None = None,
                            settings: LensdistConfig | None = None) -> MultiViewCalibration:
    """One answer from several reconstructions' self-calibrations (module docstring).

    Args:
        runs: per mapping seed its :class:`~lensdist_torch.calibration.multiview.MultiViewCalibration`,
            or a string saying why that reconstruction failed; at least one must have succeeded.
        config: :class:`~lensdist_torch.config.MultiViewConfig` (``reconstructions``: the
            successes a class needs, the width limits).
        settings: the intervals' coverage (``calibration.confidence``), the classes and a sequence's R
            threshold (``calibration.no_distortion_px``;
            default: :class:`~lensdist_torch.config.LensdistConfig`'s).

    Returns:
        The median reconstruction's calibration with the widened intervals, the class (or None and
        the reason), ``reconstructions`` (one summary per seed) and ``reconstruction_spread_px``.
    """
    cfg, st = or_defaults(config, MultiViewConfig), or_defaults(settings, LensdistConfig, "settings")
    ok = [(s, r) for s, r in runs if not isinstance(r, str)]
    if not ok:
        raise ValueError(f"runs must hold at least one successful reconstruction, got {len(runs)} failed")
    best = _median([r for _, r in ok])
    t = NormalDist().inv_cdf(0.5 + st.calibration.confidence / 2)
    spread = reconstruction_spread([r.delta_avg_user_px for _, r in ok], best.delta_avg_user_px)
    spread_max = reconstruction_spread([r.delta_max_user_px for _, r in ok], best.delta_max_user_px)
    intervals = [widened_interval(best.delta_avg_user_px, best.delta_avg_user_interval, spread, t),
                 widened_interval(best.delta_max_user_px, best.delta_max_user_interval, spread_max, t)]
    need, label, reason = cfg.reconstructions, best.class_label, best.reason
    apart = _disagreement(ok)
    if len(ok) < need:
        failed = "; ".join(f"seed {s}: {r}" for s, r in runs if isinstance(r, str))
        label, reason = None, (f"only {len(ok)} of {len(runs)} reconstructions succeeded ({need} needed), so the "
                               f"engine's own variation is not known" + (f" ({failed})" if failed else ""))
    elif apart:
        label, reason = None, f"the reconstructions disagree beyond their intervals ({apart})"
    elif label is not None:  # the class of the widened interval, which may now span two
        label, reason = interval_class(best.paper_delta_avg_px, best.delta_avg_user_px, intervals[0], st)
        if label is None and len(ok) > 1:
            reason += f" (the {len(ok)} reconstructions differ by up to {spread:.2f} px)"
    return dataclasses.replace(
        best,
        delta_avg_user_interval=intervals[0],
        delta_max_user_interval=intervals[1],
        class_label=label,
        reason=reason,
        reconstructions=tuple(_summary(s, r) for s, r in runs),
        reconstruction_spread_px=spread,
    )
