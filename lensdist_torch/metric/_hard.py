"""The fast hard map: registration (and visual) error counts per block, no autograd.

The same numbers as :func:`~lensdist_torch.metric.criteria.local_criteria` +
:func:`~lensdist_torch.metric.criteria.error_images` + :func:`~lensdist_torch.metric.pooling.block_counts`
(the tests check it to the pixel), written for speed: ``E < theta_E`` is, E being monotone in
the orientation difference, exactly ``|g1 x g2| > tan(dalpha*) |g1 . g2|`` (no atan, no exp);
thresholds compare squared raw Sobel responses; {0, 1} masks stay in float (sign + clamp) and
the 3 x 3 dilation of the risk map is a separable product of shifted slices. See
docs/method.md, sections 2-4, for the formulas.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from lensdist_torch.config import QualityConfig
from lensdist_torch.core.chunks import chunk_slices
from lensdist_torch.metric._inputs import ONLY_AT_RISK
from lensdist_torch.metric.criteria import HALF_PI, sobel8


def tan_threshold(cfg: QualityConfig) -> float | None:
    """tan(dalpha*) with E < theta_E <=> dalpha > dalpha*; None if every pixel errs."""
    # E = gamma / (1 + exp(k (A - sigma))) < theta_E  <=>  A < sigma + ln(gamma / theta_E - 1) / k
    a_star = cfg.sigma + math.log(cfg.gamma / cfg.theta_e - 1.0) / cfg.k
    if a_star > 1.0:
        return None
    dalpha_star = (1.0 - a_star) * HALF_PI
    return math.inf if dalpha_star >= HALF_PI else math.tan(dalpha_star)


def _erode3(x: torch.Tensor) -> torch.Tensor:
    """3 x 3 erosion of a (B, 1, H, W) {0, 1} float mask; outside the image counts as 1.

    For {0, 1} values the minimum over a window is its product: separable products of shifted
    slices, several times cheaper than max-pooling. ``1 - _erode3(1 - m)`` is the max-pool
    dilation of m (kernel 3, stride 1, padding 1), which is how the risk map is dilated.
    """
    p = F.pad(x, (1, 1, 1, 1), value=1.0)
    rows = p[..., :, :-2] * p[..., :, 1:-1] * p[..., :, 2:]
    return rows[..., :-2, :] * rows[..., 1:-1, :] * rows[..., 2:, :]


def _positive(x: torch.Tensor) -> torch.Tensor:
    """[x > 0] as a {0, 1} float tensor, in place.

    IEEE subtraction never rounds a non-zero difference to zero, so ``[a - b > 0]`` is exactly
    ``[a > b]``; sign + clamp stay in float, where comparisons producing bool tensors (and
    converting them back) cost several times more on the CPU.
    """
    return x.sign_().clamp_(min=0.0)


def _block_sum(x: torch.Tensor, block: int) -> torch.Tensor:
    b, _, h, w = x.shape
    x = x.contiguous().view(b, h // block, block, w).sum(2)
    return x.view(b, h // block, w // block, block).sum(-1).view(b, 1, h // block, w // block)


def measure_codes(v: torch.Tensor | None, not_r: torch.Tensor) -> torch.Tensor:
    """(B,) codes of what each sample leaves to measure.

    ``MEASURABLE`` (1): a valid pixel outside the risk map; ``ONLY_AT_RISK`` (0.5): valid pixels,
    but every one at risk (both images flat there: no edge to compare); ``NOTHING_VALID`` (0).

    Args:
        v: (B, 1, H, W) the eroded {0, 1} validity, or None (everything valid).
        not_r: (B, 1, H, W) {0, 1}, 1 where the dilated risk map is 0.
    """
    if v is None:
        return not_r.amax(dim=(1, 2, 3)).clamp(min=ONLY_AT_RISK)
    return torch.maximum(ONLY_AT_RISK * v.amax(dim=(1, 2, 3)), (v * not_r).amax(dim=(1, 2, 3)))


def criteria_codes(v: torch.Tensor | None, crit) -> torch.Tensor:
    """:func:`measure_codes` from the per-pixel criteria (either path): the risk map read at 0.5.

    Args:
        v: (B, 1, H, W) the eroded {0, 1} validity, or None.
        crit: the :class:`~lensdist_torch.metric.criteria.LocalCriteria` of the pair.
    """
    return measure_codes(v, (crit.r < 0.5).to(crit.r.dtype).detach())


def _hard_counts_chunk(g1, g2, valid, cfg: QualityConfig, t: float | None, visual: bool, measured: bool = False):
    sx1, sy1 = sobel8(g1)
    sx2, sy2 = sobel8(g2)
    if t is None:
        mis = torch.ones_like(sx1)
    else:  # |b| > t |a|  <=>  E < theta_E  (see the module docstring)
        cross = torch.addcmul(sx1 * sy2, sy1, sx2, value=-1.0).abs_()
        dot = torch.addcmul(sx1 * sx2, sy1, sy2).abs_()
        # A vanishing gradient has no orientation: against a non-vanishing one it is an error
        # (A = 0). For 2-D vectors a = b = 0 exactly when one of them vanishes, so "+ tiny"
        # (the smallest normal number) turns |b| > t |a| into |b| >= t |a| there, and only
        # there: a non-zero |b| - t |a| is never within tiny of 0 unless the gradients are
        # below ~1e-19 (float32), which count as vanishing (as on the smooth path). Two
        # vanishing gradients also count, but such a pixel is in the risk map anyway.
        mis = _positive(cross.sub_(dot.mul_(t)).add_(torch.finfo(cross.dtype).tiny))
    theta2 = 64.0 * cfg.theta_g * cfg.theta_g  # G <= theta <=> (8G)^2 <= 64 theta^2; 64 is exact
    strong1 = _positive(torch.addcmul(sx1 * sx1, sy1, sy1).sub_(theta2))
    strong2 = _positive(torch.addcmul(sx2 * sx2, sy2, sy2).sub_(theta2))
    # no weak pixel in the 3 x 3 window  <=>  R = 0 (R the dilated weak-pixel map)
    not_r = _erode3(torch.maximum(strong1, strong2))
    err = mis.mul_(not_r)
    flags = None
    if valid is not None:
        # valid is {0, 1} already (binarised when the inputs were prepared); its erosion is the
        # dilation of the invalid pixels; outside the image counts as valid
        v = _erode3(valid)
        err.mul_(v)
        if measured:
            flags = measure_codes(v, not_r)
    elif measured:
        flags = measure_codes(None, not_r)
    reg = _block_sum(err, cfg.block_size)
    if not visual:
        return reg, None, flags
    vis = _positive((g1 - g2).abs_().sub_(cfg.theta_d)).mul_(1.0 - not_r)
    if valid is not None:
        vis.mul_(v)
    return reg, _block_sum(vis, cfg.block_size), flags


def hard_counts(g1, g2, valid, *, cfg: QualityConfig, visual: bool, measured: bool = False):
    """Error pixels per block of the hard path.

    Args:
        g1: (B, 1, H, W) grey image in [0, 1], H and W multiples of the block size.
        g2: (B, 1, H, W) the other grey image.
        valid: (B, 1, H, W) {0, 1} mask (already binarised) or None.
        cfg: the metric's settings.
        visual: also count the visual errors.
        measured: also return what each sample leaves to measure (:func:`measure_codes`), from
            the erosion and the risk map the counts use anyway.

    Returns:
        (registration counts, visual counts or None), each (B, 1, H/b, W/b) in the images' dtype;
        with ``measured``, a third element: the (B,) codes of :func:`measure_codes`.
    """
    t = tan_threshold(cfg)
    spans = chunk_slices(g1.shape[0], cfg.chunk_size, g1.device, g1.shape[-2] * g1.shape[-1])
    if len(spans) == 1:
        out = _hard_counts_chunk(g1, g2, valid, cfg, t, visual, measured)
        return out if measured else out[:2]
    # Chunks keep the ~20 intermediates of a chunk in cache; the maps do not depend on it.
    parts = [
        _hard_counts_chunk(g1[sl], g2[sl], None if valid is None else valid[sl], cfg, t, visual, measured)
        for sl in spans
    ]
    reg = torch.cat([p[0] for p in parts])
    vis = torch.cat([p[1] for p in parts]) if visual else None
    if not measured:
        return reg, vis
    return reg, vis, torch.cat([p[2] for p in parts])
