"""One camera's distortion from a whole sequence of its frames, with an error bar.

One pair is noisy; the frames of one camera share one (k2, k4) of eq. 4 (docs/method.md,
section 6). :func:`calibrate_sequence` self-calibrates many pairs (section 10) and combines them:

1. **Analysis size**: frames longer than ``analysis_side`` are scaled down by s (user px per
   analysis px) about their centre, p_user - c_user = s (p - c). Eq. 4 times s has r_user = s r,
   so **k2_user = k2 / s^2 and k4_user = k4 / s^4**, exactly.
2. **Pairs**: each frame with the first later frames that moved by :data:`MOTION_STEPS` of the
   half diagonal R, at most :data:`MAX_MOTION` R (:mod:`~lensdist_torch.calibration.sequence_pairs`).
3. **Per pair**, :func:`~lensdist_torch.selfcal.fit.estimate_distortion` (batched, from the
   pair's phase correlation, with the plane + parallax model of ``selfcal.parallax`` bumps, kept
   where Hausman's test finds relief): a = k2 R^2, b = k4 R^4 and the std sigma_i of Delta_avg; pairs that
   diverged or whose residual exceeds ``MAX_RESIDUAL_RATIO`` times the lower quartile's drop, or
   that the fit did not register: residual RMS over ``MAX_MISFIT`` of sqrt(var_1 + var_2), the
   frames' contrast (real views far apart stop in a wrong minimum and say anything there).
   With ``REGISTERED_START``, the pairs step 4 would not count, or that lie more than 3 of their
   own sigma_i from its value, are fitted again from their own registration where it lies far
   from the translation (:mod:`~lensdist_torch.calibration.direct_fits`).
4. **Combination: the inverse-variance mean** of (a_i, b_i) (weights 1 / sigma_i^2) of the pairs
   that count: those whose signed Delta_avg R (a m3 + b m5) (m_k: the frame's mean |u|^k) lies
   within ``OUTLIER_MADS`` robust deviations (1.4826 MAD, at least the median sigma_i) of the
   median and that the good-and-bad mixture finds more likely good than failed (failures spread
   over +-``OUTLIER_RANGE`` class ranges: :func:`~lensdist_torch.calibration.pooling.good_and_bad`).
5. **Intervals**: pairs sharing frames have correlated errors, so the variance is a
   delete-a-block jackknife (``JACKKNIFE_BLOCKS`` contiguous blocks), or the Birge-scaled
   max(1, chi^2 / (n - 1)) / sum(1 / sigma_i^2) where larger, plus :data:`SYSTEMATIC_REL` D in
   quadrature (what all pairs share), plus :data:`RELIEF_REL` times the relief's effect: the pairs'
   plane + parallax minus planar answers combined as the answers are, where it exceeds
   :data:`RELIEF_TEST` of its jackknife stds (relief parts the models alike in every pair, noise
   does not), else the effect that test cannot exclude, ``RELIEF_TEST`` of those stds (a relief can bias
   both models alike; no jackknife sees it: docs/method.md, 7). t on blocks - 1 dof; [max(0, D - t sd), D + t sd].
6. **Class** (``estimated_class``) of Delta_avg at the paper's 320 x 424 frame where the whole
   interval, carried there, lies in that class (:func:`~lensdist_torch.calibration.sequence_class.interval_class`,
   the rule every path shares), or None with a reason: under ``MIN_PAIRS`` usable pairs, or the
   classes the interval spans (R against 1 where it spans ``NO_DISTORTION_PX``, a sequence's R threshold).

Why this combination: docs/method.md, section 10.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F

from lensdist_torch.calibration import direct_fits
from lensdist_torch.calibration.direct_fits import fit_pairs, refit_from_registration, reject_residuals, unregistered
from lensdist_torch.calibration.lens_answer import LensAnswer
from lensdist_torch.calibration.pooling import OUTLIER_RANGE, pair_weights, pool_pairs, within_mads
from lensdist_torch.calibration.sequence_class import MIN_PAIRS, interval_class
from lensdist_torch.calibration.sequence_pairs import (
    FLAT_TEXTURE,
    MAX_MOTION,
    MOTION_STEPS,
    NO_TEXTURE,
    TOO_LITTLE_MOTION,
    choose_pairs,
    no_pairs_reason,
)
from lensdist_torch.config import CalibrationConfig, LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.images import check_image, to_grey
from lensdist_torch.geometry.distortion import delta_avg, delta_max, delta_top
from lensdist_torch.geometry.frame import half_diagonal, pixel_grid
from lensdist_torch.selfcal.fit import LEVELS

__all__ = ["CalibrationConfig", "SequenceCalibration", "analysis_scale", "analysis_size", "to_analysis",
           "user_coefficients", "choose_pairs", "no_pairs_reason", "calibrate_sequence", "TOO_LITTLE_MOTION",
           "NO_TEXTURE", "FLAT_TEXTURE", "MAX_MOTION", "MOTION_STEPS", "SYSTEMATIC_REL", "RELIEF_REL", "RELIEF_TEST"]

#: Step 5: a std of this fraction of each Delta, in quadrature: the error all pairs share (docs/method.md, 10).
SYSTEMATIC_REL = 1e-3
#: Step 5: a std of this multiple of the relief's effect on each Delta, in quadrature (what plane + parallax leaves).
RELIEF_REL = 0.8
#: Step 5: the relief's effect counts at this many of its jackknife stds or more; below, this many of those stds count.
RELIEF_TEST = 2.0


@dataclass(frozen=True, kw_only=True)
class SequenceCalibration(LensAnswer):
    """The result of :func:`calibrate_sequence`: the lens answer and the direct path's diagnostics.

    The core fields are :class:`~lensdist_torch.calibration.lens_answer.LensAnswer`'s (user px,
    intervals at ``confidence``, NaN below 2 usable pairs; the class or None with the reason).

    Attributes:
        pairs_used: pairs that count in the combination.
        pairs_rejected: pairs that diverged, failed the residual test or the registration, or were outliers.
        frames: frames in the sequence.
        image_size: the frames' (H, W) in the user's pixels.
        analysis_size: the analysis frames' (H, W).
        scale: user px per analysis px.
        ab: the combined normalised (a, b) = (k2 R^2, k4 R^4) at the analysis size.
        pairs: (P, 2) frame indices of the pairs fitted.
        pair_delta_avg: (P,) each pair's signed Delta_avg (analysis px).
        pair_delta_avg_std: (P,) its std.
        pair_used: (P,) bool, the pair counts.
        relief_effect_px: |Delta_avg of the pairs' plane + parallax answers - that of their planar
            answers| (user px), combined as the answers are, where significant, else 0.
        relief_z: that effect over its jackknife std (significant at :data:`RELIEF_TEST` or more).
        pair_refitted: (P,) bool, the pair was fitted again from its own registration
            (``direct_fits.REGISTERED_START``) and that fit replaced the first; None where none ran.
        pair_misfit: (P,) what each pair's registration leaves unexplained
            (:func:`~lensdist_torch.calibration.direct_fits.pair_misfit`; over ``direct_fits.MAX_MISFIT``:
            not registered, not used); None where none ran.

    Example:
        >>> x = torch.rand(1, 1, 64, 64, generator=torch.Generator().manual_seed(0))
        >>> cal = calibrate_sequence(torch.cat([x, x]))  # a still camera: no pair to use
        >>> cal.class_label, cal.reason, cal.pairs_used, math.isnan(cal.k2_user), cal.image_size
        (None, 'too little motion: no two frames moved enough apart', 0, True, (64, 64))
    """

    pairs_used: int
    pairs_rejected: int
    frames: int
    image_size: tuple[int, int]
    analysis_size: tuple[int, int]
    scale: float
    ab: tuple[float, float]
    pairs: torch.Tensor
    pair_delta_avg: torch.Tensor
    pair_delta_avg_std: torch.Tensor
    pair_used: torch.Tensor
    relief_effect_px: float = 0.0
    relief_z: float = 0.0
    pair_refitted: torch.Tensor | None = None
    pair_misfit: torch.Tensor | None = None


# ------------------------------------------------------------------ analysis size
def analysis_scale(height: int, width: int, config: CalibrationConfig | None = None) -> float:
    """The scale s, user px per analysis px: max(1, longest side / ``config.analysis_side``)."""
    cfg = or_defaults(config, CalibrationConfig)
    return max(1.0, max(height, width) / cfg.analysis_side)


def analysis_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(h, w) of the analysis frames of (height, width) frames at ``scale``."""
    return max(1, round(height / scale)), max(1, round(width / scale))


def to_analysis(frames: torch.Tensor, scale: float) -> torch.Tensor:
    """(N, C, H, W) float or uint8 frames -> (N, 1, h, w) float32 grey at the analysis size.

    The map is exactly centred, p_user - c_user = scale (p - c) (module docstring): a box
    prefilter of floor(scale) px, then bilinear ``grid_sample`` (border padding).

    Example:
        >>> to_analysis(torch.rand(2, 3, 96, 128), 2.0).shape
        torch.Size([2, 1, 48, 64])
    """
    g = to_grey(frames).float()
    if scale == 1.0:
        return g
    (n, _, hh, ww), k = g.shape, max(1, int(math.floor(scale)))
    h, w = analysis_size(hh, ww, scale)
    g = F.avg_pool2d(g, k, stride=1)  # pixel i averages [i, i + k - 1]: centred at i + (k - 1) / 2
    axes = [((m - 1) / 2 + scale * (torch.arange(n_a, dtype=torch.float64) - (n_a - 1) / 2) - (k - 1) / 2)
            * 2 / max(m_b - 1, 1) - 1 for m, n_a, m_b in ((ww, w, g.shape[-1]), (hh, h, g.shape[-2]))]
    grid = torch.stack(torch.meshgrid(axes[1].float(), axes[0].float(), indexing="ij")[::-1], -1).expand(n, h, w, 2)
    return F.grid_sample(g, grid, mode="bilinear", padding_mode="border", align_corners=True)


def user_coefficients(k2: float, k4: float, scale: float) -> tuple[float, float]:
    """Analysis-pixel (k2, k4) -> the user's: (k2 / s^2, k4 / s^4) (module docstring).

    Example:
        >>> user_coefficients(4e-6, 1.6e-11, 2.0)
        (1e-06, 1e-12)
    """
    return k2 / scale**2, k4 / scale**4


# ------------------------------------------------------------------ combination
def _failure_width(size, st: LensdistConfig) -> float:
    """The span (px of the analysis frame ``size``) over which a failed pair's signed Delta_avg may fall."""
    return 2 * OUTLIER_RANGE * delta_top("delta_avg", st) * half_diagonal(*size) / half_diagonal(*st.image.size)


def _signed_mean(height: int, width: int, rn: float) -> torch.Tensor:
    """(2,) g: g . (a, b) is the mean signed offset (px) for k2 = a / rn^2, k4 = b / rn^4."""
    grid = pixel_grid(height, width, torch.float64) - torch.tensor(
        [(width - 1) / 2, (height - 1) / 2], dtype=torch.float64
    )
    r = grid.norm(dim=-1)
    return torch.stack([(r**3).mean() / rn**2, (r**5).mean() / rn**4])


# ------------------------------------------------------------------ the estimator
def _stack(frames) -> torch.Tensor:
    """A (N, C, H, W) tensor or a list of (1, C, H, W) tensors -> (N, 1, H, W) float grey."""
    if isinstance(frames, (list, tuple)):
        if len(frames) == 0:
            raise ValueError("frames is empty: a sequence of at least 2 frames of one camera is needed")
        for i, f in enumerate(frames):
            check_image(f, f"frames[{i}]")
            if f.shape[0] != 1 or f.shape[-2:] != frames[0].shape[-2:]:
                raise ValueError(
                    f"frames must be (1, C, H, W) frames of one size: frames[0] is {tuple(frames[0].shape)}, "
                    f"frames[{i}] is {tuple(f.shape)}"
                )
        return torch.cat([to_grey(f).float() for f in frames])
    if not isinstance(frames, torch.Tensor):
        raise TypeError(
            f"frames must be a (N, C, H, W) tensor or a list of (1, C, H, W) tensors, got {type(frames).__name__}"
        )
    return to_grey(check_image(frames, "frames")).float()


def _prepare(frames, cfg: CalibrationConfig, frame_size) -> tuple[torch.Tensor, tuple[int, int], float]:
    """Analysis frames (N, 1, h, w), the user's frame size and the scale."""
    x = _stack(frames)
    if x.shape[0] < 2:
        raise ValueError(f"frames must hold at least 2 frames of one camera, got {x.shape[0]}")
    h, w = x.shape[-2:]
    if frame_size is None:
        scale = analysis_scale(h, w, cfg)
        return torch.cat([to_analysis(x[i : i + 8], scale) for i in range(0, len(x), 8)]), (h, w), scale
    ok = (
        isinstance(frame_size, (tuple, list))
        and len(frame_size) == 2
        and all(type(v) is int and v > 0 for v in frame_size)
    )
    scale = analysis_scale(*frame_size, cfg) if ok else 1.0
    if not ok or analysis_size(*frame_size, scale) != (h, w):
        raise ValueError(
            f"frame_size must be the (height, width) whose analysis size is the frames' {h} x {w}, got {frame_size!r}"
        )
    return x, tuple(frame_size), scale


def calibrate_sequence(
    frames,
    config: CalibrationConfig | None = None,
    settings: LensdistConfig | None = None,
    *,
    frame_size: tuple[int, int] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SequenceCalibration:
    """One camera's (k2, k4) from a sequence of its frames, with 95 % intervals (module docstring).

    Args:
        frames: (N, C, H, W) float in [0, 1] or uint8, or a list of (1, C, H, W) tensors, N >= 2,
            one camera and one size, C in {1, 3}, in recording order.
        config: :class:`CalibrationConfig`; defaults when None.
        settings: the library's :class:`~lensdist_torch.config.LensdistConfig` (self-calibration
            settings, the class rule and the paper's frame); defaults when None.
        frame_size: when ``frames`` were already brought to the analysis size with
            :func:`to_analysis` (to keep a long video small), the original (H, W).
        progress: called as progress(pairs_done, pairs_total) once the pairs are chosen (0 done) and after
            every batch.

    Returns:
        :class:`SequenceCalibration`, offsets and coefficients in the frames' own pixels.

    Example:
        >>> from lensdist_torch.core.images import load_scene
        >>> from lensdist_torch.geometry.distortion import distortion_grid, sample_at_pixels
        >>> grid = distortion_grid([6e-6], [0.0], 160, 200)  # the ideal point of every pixel
        >>> scene = load_scene("gravel")  # a camera panning down 8 px a frame
        >>> frames = torch.cat([sample_at_pixels(scene, grid + torch.tensor([150.0, 100.0 + 8 * i]))
        ...                     for i in range(10)])
        >>> cal = calibrate_sequence(frames)
        >>> round(cal.k2_user * 1e6, 1), cal.class_label, cal.frames, cal.image_size
        (6.1, '2', 10, (160, 200))
    """
    cfg, st = or_defaults(config, CalibrationConfig), or_defaults(settings, LensdistConfig, "settings")
    xa, size, scale = _prepare(frames, cfg, frame_size)
    least = max(16, 2**LEVELS)
    if min(xa.shape[-2:]) < least:
        raise ValueError(f"frames must be at least {least} px on each side, got {tuple(xa.shape[-2:])}")
    pairs, shifts = choose_pairs(xa, cfg)
    fits = fit_pairs(xa, pairs, shifts, settings=st, progress=progress)
    refitted = torch.zeros(len(pairs), dtype=torch.bool)
    if direct_fits.REGISTERED_START and len(pairs):
        refitted = refit_from_registration(
            xa, pairs, shifts, fits, retry=_doubtful(fits, xa, st), settings=st
        )
    ab, std, res, planar, relief, misfit = fits
    std = reject_residuals(std, res, misfit=misfit)
    return _result(ab, std, pairs, xa, size, scale, cfg, st, (planar, relief), misfit, refitted)


def _doubtful(fits, xa, st: LensdistConfig) -> torch.Tensor:
    """(P,) bool: the pairs step 4 would not count, or that lie more than 3 of their own sigma from its value."""
    h, w = xa.shape[-2:]
    lin, std = fits[0] @ _signed_mean(h, w, half_diagonal(h, w)), reject_residuals(fits[1], fits[2], misfit=fits[5])
    weights, keep = pair_weights(lin, std, _failure_width((h, w), st))
    if not bool(keep.any()):
        return ~keep
    mu = (weights * torch.nan_to_num(lin)).sum() / weights.sum()
    return ~keep | ((lin - mu).abs() > 3 * std)


def _relief_term(models, std, pairs, fun, cfg: CalibrationConfig) -> tuple[tuple[float, ...], float, float]:
    """Step 5's relief terms of the user's Delta_avg and Delta_max stds, z (|effect| / its std), the effect found.

    The models' differences are pooled by inverse variance (1 / sigma_i^2) over those within
    ``OUTLIER_MADS`` of their median: they part by noise or by relief, not by failures.
    Below :data:`RELIEF_TEST`, that many stds count (the effect the test cannot exclude), none is found.
    """
    diff = None if models is None else models[1] - models[0]
    if diff is None or not bool((diff[torch.isfinite(diff)] != 0).any()):
        return (0.0, 0.0, 0.0), 0.0, 0.0
    keep = within_mads(diff @ fun[0], std)
    w = torch.where(keep, 1.0 / std.clamp_min(1e-12) ** 2, torch.zeros_like(std))
    theta_d, sd_d, _ = pool_pairs(diff, w, keep, pairs[:, 0], fun=fun, cfg=cfg)
    effect, z = (theta_d @ fun.T).abs(), 0.0
    if float(effect[1]) > 0 and bool(torch.isfinite(sd_d[1])):
        z = float(effect[1] / sd_d[1]) if float(sd_d[1]) > 0 else math.inf
    if z >= RELIEF_TEST:  # the models part consistently over the sequence: relief
        return tuple(float(e) for e in effect[1:]), z, float(effect[1])
    bound = tuple(RELIEF_TEST * float(v) for v in sd_d[1:]) if bool(torch.isfinite(sd_d[1:]).all()) else (0.0,) * 2
    return bound, z, 0.0


def _result(ab, std, pairs, xa, size, scale, cfg: CalibrationConfig, st: LensdistConfig,
            models: tuple[torch.Tensor, torch.Tensor] | None = None, misfit: torch.Tensor | None = None,
            refitted: torch.Tensor | None = None) -> SequenceCalibration:
    """Combine the pairs, convert to the user's pixels, intervals and class."""
    (h, w), (hh, ww), (hc, wc) = xa.shape[-2:], size, st.image.size
    ra, rc = half_diagonal(h, w), half_diagonal(hc, wc)
    corner = half_diagonal(hh, ww)
    ru = scale * ra  # the analysis half diagonal in user px
    fun = torch.stack(
        [
            _signed_mean(h, w, ra),
            _signed_mean(hh, ww, ru),
            torch.tensor([corner**3 / ru**2, corner**5 / ru**4], dtype=torch.float64),
        ]
    )
    weights, keep = pair_weights(ab @ fun[0], std, _failure_width((h, w), st))
    theta, sd, t = pool_pairs(ab, weights, keep, pairs[:, 0], fun=fun, cfg=cfg)
    a, b = float(theta[0]), float(theta[1])
    k2u, k4u = user_coefficients(a / ra**2, b / ra**4, scale)
    n_used, nan = int(keep.sum()), float("nan")
    d_avg, d_max = (float(f([k2u], [k4u], hh, ww)[0]) if n_used else nan for f in (delta_avg, delta_max))
    dc = float(delta_avg([a / rc**2], [b / rc**4], hc, wc)[0]) if n_used else nan
    relief, relief_z, found = _relief_term(models, std, pairs, fun, cfg) if n_used > 1 else ((0.0, 0.0), 0.0, 0.0)
    half = [t * math.sqrt(float(e) ** 2 + (SYSTEMATIC_REL * d) ** 2 + (RELIEF_REL * r) ** 2)
            for e, d, r in zip(sd[1:], (d_avg, d_max), relief)]
    iv_avg, iv_max = ((max(0.0, d - e) if n_used > 1 else nan, d + e) for d, e in ((d_avg, half[0]), (d_max, half[1])))
    label, reason = None, ""
    if len(pairs) == 0:
        reason = no_pairs_reason(xa)
    elif n_used < MIN_PAIRS:
        failed = 0 if misfit is None else int(unregistered(misfit).sum())
        reason = f"too few usable pairs: {n_used} of at least {MIN_PAIRS}" + (
            f" ({failed} of {len(pairs)} pairs not registered: their residual is over {direct_fits.MAX_MISFIT} of "
            "their frames' contrast, views too far apart or too different)" if failed else "")
    else:
        label, reason = interval_class(dc, d_avg, iv_avg, st)
    return SequenceCalibration(
        k2_user=k2u, k4_user=k4u, delta_avg_user_px=d_avg, delta_avg_user_interval=iv_avg, delta_max_user_px=d_max,
        delta_max_user_interval=iv_max, class_label=label, reason=reason, pairs_used=n_used,
        pairs_rejected=len(pairs) - n_used, frames=xa.shape[0], image_size=(hh, ww), analysis_size=(h, w),
        scale=scale, ab=(a, b), pairs=pairs, pair_delta_avg=(ab @ fun[0]).abs(), pair_delta_avg_std=std,
        pair_used=keep, relief_effect_px=found, relief_z=min(relief_z, 1e6), pair_refitted=refitted,
        pair_misfit=misfit)
