"""A sequence's pairs fitted one by one (step 3 of :mod:`~lensdist_torch.calibration.direct`).

:func:`fit_pairs` self-calibrates every chosen pair from the phase correlation's translation
(:func:`~lensdist_torch.selfcal.fit.estimate_distortion` with the sequence's plane + parallax
model); :func:`refit_from_registration` gives the pairs the pooling would not count a second start,
their own registration (direct, then features + RANSAC: views far apart, turned or seen obliquely
hold a translation start in a wrong minimum, docs/method.md section 10), only where that
registration lies more than one pixel of the fit's coarsest level from the translation; and
:func:`reject_residuals` drops the pairs whose residual is far above the lower quartile (a broken
or foreign frame).

Example:
    >>> import torch
    >>> reject_residuals(torch.ones(5), torch.tensor([0.02, 0.02, 0.03, 0.02, 0.2])).tolist()
    [1.0, 1.0, 1.0, 1.0, inf]
"""

from __future__ import annotations

import dataclasses

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.homography import corner_error
from lensdist_torch.registration.wide_baseline import SiftMemo, estimate_homography_robust
from lensdist_torch.selfcal.fit import LEVELS, estimate_distortion

__all__ = [
    "sequence_selfcal",
    "fit_pairs",
    "pair_misfit",
    "unregistered",
    "refit_from_registration",
    "reject_residuals",
    "BATCH_SIZE",
    "MAX_RESIDUAL_RATIO",
    "MAX_MISFIT",
    "PARALLAX_PX",
    "REGISTERED_START",
]

#: Step 3: a pair whose photometric residual exceeds this multiple of the pairs' lower quartile does not count (a
#: broken or foreign frame).
MAX_RESIDUAL_RATIO = 3.0
#: Step 3: a pair counts only where its residual RMS is at most this share of sqrt(var_1 + var_2), its frames'
#: contrast (0: a perfect fit; about 0.7 for unrelated frames): else its registration did not explain its frames.
MAX_MISFIT = 0.4
#: Step 3: the pairs the pooling doubts are fitted again from their own registration (False: the translation alone).
REGISTERED_START = True
#: The prior std (px) of each relief bump's height in the sequence's pairs (``selfcal.parallax_px`` for one pair):
#: the setting its relief figures and ``direct.RELIEF_REL`` were measured with (docs/method.md, section 10).
PARALLAX_PX = 1.0
#: Pairs self-calibrated together, and the progress callback's step: the answers do not depend on it.
BATCH_SIZE = 16


def pair_misfit(a: torch.Tensor, b: torch.Tensor, residual: torch.Tensor) -> torch.Tensor:
    """How much of a pair its registration leaves unexplained: residual / sqrt(var(a) + var(b)), (n,) float64.

    ``residual`` is each pair's RMS photometrically corrected residual (``SelfCalInfo.residual``)
    and var the intensity variance over each whole frame: 0 for a perfect fit, about 0.7 for two
    unrelated frames of that contrast (the photometric gain then fits nothing and the residual is
    the second frame's own spread), inf for two flat frames.

    Args:
        a: (n, 1, h, w) the pairs' first frames.
        b: (n, 1, h, w) their second frames.
        residual: (n,) their residuals.

    Example:
        >>> a = torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(0))  # var 1/12
        >>> pair_misfit(a, a, torch.tensor([0.0, 0.2])).round(decimals=2).tolist()  # 0.2 / sqrt(2 / 12)
        [0.0, 0.49]
    """
    contrast = (a.double().var(dim=(1, 2, 3), correction=0) + b.double().var(dim=(1, 2, 3), correction=0)).sqrt().cpu()
    return torch.where(
        contrast > 0,
        residual.double().cpu() / contrast.clamp_min(1e-300),
        torch.tensor(float("inf"), dtype=torch.float64),
    )


def unregistered(misfit: torch.Tensor) -> torch.Tensor:
    """(P,) bool: the pairs whose :func:`pair_misfit` exceeds :data:`MAX_MISFIT` (or is NaN): not registered.

    Example:
        >>> unregistered(torch.tensor([0.1, 0.6, float("inf")])).tolist()
        [False, True, True]
    """
    return ~(misfit <= MAX_MISFIT)


def _translations(shifts: torch.Tensor) -> torch.Tensor:
    """(n, 2) shifts -> (n, 3, 3) float64 translation homographies."""
    out = torch.eye(3, dtype=torch.float64).repeat(len(shifts), 1, 1)
    out[:, :2, 2] = shifts
    return out


def _fit_batch(a, b, init, selfcal) -> tuple[torch.Tensor, ...]:
    """One batch of pairs from the starts ``init``: (a, b), std, residual, planar and relief (a, b), misfit.

    On the CPU, NaN / inf where dropped.
    """
    info = estimate_distortion(a, b, init=init, config=selfcal, validate=False)[3]
    # the fit runs on the frames' device; its few numbers per pair come back to the CPU
    ab, std, res, planar, relief = (x.double().cpu() for x in (info.ab, info.delta_avg_std, info.residual,
                                                                info.planar_ab, info.relief_ab))
    misfit = pair_misfit(a, b, res)
    ok = info.converged.cpu() & torch.isfinite(std)
    nan, inf = torch.tensor(float("nan"), dtype=torch.float64), torch.tensor(float("inf"), dtype=torch.float64)
    relief = torch.where(torch.isfinite(relief), relief, ab)
    return (torch.where(ok[:, None], ab, nan), torch.where(ok, std, inf), torch.where(ok, res, inf),
            torch.where(ok[:, None], planar, nan), torch.where(ok[:, None], relief, nan), torch.where(ok, misfit, inf))


def sequence_selfcal(settings: LensdistConfig):
    """The self-calibration settings of the sequence path: the user's, with the sequence's own relief model.

    Its relief prior is fixed (:data:`PARALLAX_PX`; the pairs' evidence-based one is
    not used here: the sequence path's tests and benchmarks hold it fixed).

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> s = sequence_selfcal(LensdistConfig())
        >>> s.parallax_px, s.parallax_evidence, LensdistConfig().selfcal.parallax_evidence
        (1.0, False, True)
    """
    return dataclasses.replace(settings.selfcal, parallax_px=PARALLAX_PX, parallax_evidence=False)


def fit_pairs(frames, pairs, shifts, *, settings: LensdistConfig, progress):
    """Step 3 per pair, from the phase correlation's translations.

    Returns:
        [(a, b) (P, 2), std (P,), residual (P,), planar, relief, misfit (P,)].
    """
    selfcal = sequence_selfcal(settings)
    parts = []
    if progress is not None and len(pairs):  # the pairs are chosen
        progress(0, len(pairs))
    for s in range(0, len(pairs), BATCH_SIZE):
        sl = slice(s, s + BATCH_SIZE)
        parts.append(_fit_batch(frames[pairs[sl, 0]], frames[pairs[sl, 1]], _translations(shifts[sl]).to(frames.device),
                                selfcal))
        if progress is not None:
            progress(min(s + BATCH_SIZE, len(pairs)), len(pairs))
    if not parts:
        return [
            torch.zeros(0, 2, dtype=torch.float64),
            torch.zeros(0, dtype=torch.float64),
            torch.zeros(0, dtype=torch.float64),
            torch.zeros(0, 2, dtype=torch.float64),
            torch.zeros(0, 2, dtype=torch.float64),
            torch.zeros(0, dtype=torch.float64),
        ]
    return [torch.cat(x) for x in zip(*parts)]


def refit_from_registration(
    frames, pairs, shifts, fits, *, retry, settings: LensdistConfig
) -> torch.Tensor:
    """Step 3's second start: the pairs ``retry`` (P,) bool refitted from their own registration, in place.

    A pair is refitted where the homography of ``estimate_homography_robust`` (converged or not:
    on real views far apart its direct run often stops short of its own checks yet near the
    answer) is finite and its corners lie more than one pixel of the fit's coarsest level from
    the translation start (that start could not reach the right minimum); the refit keeps the
    better of that start and the phase correlation's and replaces the first fit where its
    residual is lower. Each frame's features are computed once (:class:`SiftMemo`). Returns the
    refitted pairs (P,) bool.
    """
    selfcal, memo = sequence_selfcal(settings), SiftMemo()
    refitted = torch.zeros(len(pairs), dtype=torch.bool)
    idx = retry.nonzero()[:, 0]
    for s in range(0, len(idx), BATCH_SIZE):
        rows = idx[s : s + BATCH_SIZE]
        a, b = frames[pairs[rows, 0]], frames[pairs[rows, 1]]
        h = estimate_homography_robust(a, b, config=settings.registration, validate=False, memo=memo)[0].double().cpu()
        # a registration that did not pass its own checks is still a start: the refit keeps the better one
        # and the misfit gate judges the result (real views far apart: docs/method.md, section 10)
        finite = torch.isfinite(h).flatten(1).all(1)
        far = finite & (
            corner_error(torch.nan_to_num(h), _translations(shifts[rows]), *frames.shape[-2:])
            > 2 ** (LEVELS - 1)
        )
        if not bool(far.any()):
            continue
        sub = rows[far]
        got = _fit_batch(a[far.to(a.device)], b[far.to(b.device)], h[far].to(frames.device), selfcal)
        better = got[2] < fits[2][sub]
        for k, x in enumerate(got):
            fits[k][sub[better]] = x[better]
        refitted[sub[better]] = True
    return refitted


def reject_residuals(std, res, *, misfit: torch.Tensor | None = None) -> torch.Tensor:
    """Step 3: inf std for the pairs that fail a check.

    A pair fails where its residual exceeds :data:`MAX_RESIDUAL_RATIO` times the lower quartile, or where its
    ``misfit`` (:func:`pair_misfit`) exceeds :data:`MAX_MISFIT` (not registered).
    """
    if misfit is not None:
        std = torch.where(unregistered(misfit), float("inf"), std)
    if not bool(torch.isfinite(res).any()):  # against the lower quartile: broken pairs may be many
        return std
    return torch.where(res <= MAX_RESIDUAL_RATIO * res[torch.isfinite(res)].quantile(0.25), std, float("inf"))
