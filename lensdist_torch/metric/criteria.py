"""The per-pixel criteria, error images and block pooling of the metric (SPEC 2-4).

The building blocks of :mod:`lensdist_torch.quality`: both paths (hard and smooth) and the
fast hard kernels. See :mod:`lensdist_torch.quality` for the formulas and the reasoning.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from lensdist_torch.config import QualityConfig
from lensdist_torch.core.images import check_image_pair, check_valid_mask, to_grey

__all__ = [
    "LocalCriteria",
    "ErrorImages",
    "local_criteria",
    "error_images",
    "erode_valid",
    "block_counts",
    "block_pool",
]

_HALF_PI = math.pi / 2


class LocalCriteria(NamedTuple):
    """Per-pixel criteria, each (B, 1, H, W).

    d: |I1 - I2| in [0, 1]. a: orientation agreement A in [0, 1]. e: edge preservation E in
    [0, gamma]. g1, g2: Sobel gradient magnitudes. r: dilated risk map (1 = both weak).
    """

    d: torch.Tensor
    a: torch.Tensor
    e: torch.Tensor
    g1: torch.Tensor
    g2: torch.Tensor
    r: torch.Tensor


class ErrorImages(NamedTuple):
    """Per-pixel error images, each (B, 1, H, W) in [0, 1] (exactly {0, 1} on the hard path)."""

    e_reg: torch.Tensor
    e_vis: torch.Tensor


def prepare_pair(img1, img2, valid, config, data_range, validate=True):
    cfg = config if config is not None else QualityConfig()
    if not isinstance(cfg, QualityConfig):
        raise TypeError(f"config must be a QualityConfig or None, got {type(cfg).__name__}")
    if not (isinstance(data_range, (int, float)) and data_range > 0):
        raise ValueError(f"data_range must be a positive number, got {data_range!r}")
    check_image_pair(img1, img2, cfg.block_size, finite=validate)
    g1, g2 = to_grey(img1), to_grey(img2)
    dtype = torch.promote_types(g1.dtype, g2.dtype)
    g1, g2 = g1.to(dtype), g2.to(dtype)
    if data_range != 1.0:  # the value of white in float inputs; uint8 is already / 255 (SPEC 1)
        if img1.is_floating_point():
            g1 = g1 / data_range
        if img2.is_floating_point():
            g2 = g2 / data_range
    if valid is not None:
        valid = check_valid_mask(valid, g1)
    return g1, g2, valid, cfg


def _sobel8(grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """8 x the normalised Sobel gradients: the raw [1, 2, 1] x [-1, 0, 1] responses."""
    p = F.pad(grey, (1, 1, 1, 1), mode="replicate")
    dx = p[..., :, 2:] - p[..., :, :-2]  # (B, 1, H + 2, W)
    dy = p[..., 2:, :] - p[..., :-2, :]  # (B, 1, H, W + 2)
    sx = torch.add(dx[..., :-2, :] + dx[..., 2:, :], dx[..., 1:-1, :], alpha=2)
    sy = torch.add(dy[..., :, :-2] + dy[..., :, 2:], dy[..., :, 1:-1], alpha=2)
    return sx, sy


def _gradients(grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised Sobel (SPEC 2): (B, 1, H, W) -> s_x, s_y, each (B, 1, H, W).

    The same numbers as ``kornia.filters.spatial_gradient(x, "sobel", 1, normalized=True)``
    (replicate border, kernels / 8; the tests check agreement to 1e-6), computed separably
    with slices: several times faster on the CPU than kornia's 2-channel convolution, which
    dominated the whole metric's time. The fast hard path uses the raw responses
    (:func:`_sobel8`) with thresholds scaled by the exact factor 8.
    """
    sx, sy = _sobel8(grey)
    return sx * 0.125, sy * 0.125


def _pair_gradients(g1: torch.Tensor, g2: torch.Tensor):
    sx1, sy1 = _gradients(g1)
    sx2, sy2 = _gradients(g2)
    return sx1, sy1, sx2, sy2


def _safe_sqrt(x: torch.Tensor) -> torch.Tensor:
    # sqrt has an infinite derivative at 0; mask before, not after, so no NaN leaks back.
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, torch.ones_like(x))), torch.zeros_like(x))


def _direction(sx: torch.Tensor, sy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(s_x, s_y) / max(|s_x|, |s_y|), the scale detached; (near-)zero vectors become 0.

    Smooth path only. The orientation difference does not depend on the gradients' lengths, so
    the scaling moves no value and its gradient is exact (the angle's derivative along the
    vector is 0). Unscaled, dot and cross are products of two gradients and 1 / (dot^2 +
    cross^2) in atan2's backward overflows for float32 gradients below about 1e-10 (NaN
    gradients on nearly flat images, SPEC 5). Gradients below sqrt(tiny) (1e-19 in float32)
    count as zero vectors, which keeps 1 / max finite.
    """
    m = torch.maximum(sx.abs(), sy.abs()).detach()
    ok = m > math.sqrt(torch.finfo(m.dtype).tiny)
    inv = torch.where(ok, 1.0 / torch.where(ok, m, torch.ones_like(m)), torch.zeros_like(m))
    return sx * inv, sy * inv


def _orientation_difference(dot: torch.Tensor, cross: torch.Tensor, smooth: bool) -> torch.Tensor:
    """dalpha = atan2(|cross|, |dot|) in [0, pi/2]; 0 where both gradients vanish."""
    x, y = dot.abs(), cross.abs()
    if not smooth:
        return torch.atan2(y, x)  # atan2(0, 0) = 0: the exact formula, no guard needed
    # atan2's gradient is 0/0 at the origin; mask zero vectors before it (SPEC 5).
    zero = (x * x + y * y) == 0
    return torch.where(zero, torch.zeros_like(x), torch.atan2(y, torch.where(zero, torch.ones_like(x), x)))


def _edge_preservation(a: torch.Tensor, cfg: QualityConfig, smooth: bool) -> torch.Tensor:
    if smooth:  # the same value, written in the overflow-free form
        return cfg.gamma * torch.sigmoid(-cfg.k * (a - cfg.sigma))
    return cfg.gamma / (1.0 + torch.exp(cfg.k * (a - cfg.sigma)))


def _step_below(x: torch.Tensor, theta: float, tau: float, smooth: bool) -> torch.Tensor:
    """[x <= theta] on the hard path, sigmoid((theta - x) / tau) on the smooth path."""
    if smooth:
        return torch.sigmoid((theta - x) / tau)
    return (x <= theta).to(x.dtype)


def _dilate3(x: torch.Tensor) -> torch.Tensor:
    return F.max_pool2d(x, kernel_size=3, stride=1, padding=1)


def erode_valid(valid: torch.Tensor) -> torch.Tensor:
    """3 x 3 erosion of a (B, 1, H, W) validity mask; the image border counts as valid.

    max_pool2d pads with -inf, so pixels outside the image never invalidate their neighbours.
    """
    return -F.max_pool2d(-valid, kernel_size=3, stride=1, padding=1)


# ----------------------------------------------------------------------------- the pieces


def local_criteria(
    img1: torch.Tensor,
    img2: torch.Tensor,
    config: QualityConfig | None = None,
    smooth: bool = False,
    data_range: float = 1.0,
) -> LocalCriteria:
    """The per-pixel criteria D, A, E, G1, G2 and the dilated risk map R (SPEC 2).

    Args:
        img1, img2: registered images (B, C, H, W), C in {1, 3}, float in [0, data_range] or uint8.
        config: thresholds and temperatures; SPEC defaults when None.
        smooth: sigmoid risk map (differentiable) instead of the hard one.
        data_range: the value of white in float inputs.

    Returns:
        LocalCriteria of (B, 1, H, W) tensors.

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> c = local_criteria(x, x)
        >>> bool((c.a == 1).all()), bool((c.d == 0).all())
        (True, True)
    """
    g1, g2, _, cfg = prepare_pair(img1, img2, None, config, data_range)
    return _criteria(g1, g2, cfg, smooth)


def _criteria(g1, g2, cfg: QualityConfig, smooth: bool) -> LocalCriteria:
    sx1, sy1, sx2, sy2 = _pair_gradients(g1, g2)
    if smooth:
        ux1, uy1 = _direction(sx1, sy1)
        ux2, uy2 = _direction(sx2, sy2)
    else:
        ux1, uy1, ux2, uy2 = sx1, sy1, sx2, sy2
    dot = ux1 * ux2 + uy1 * uy2
    cross = ux1 * uy2 - uy1 * ux2
    a = 1.0 - _orientation_difference(dot, cross, smooth) / _HALF_PI
    e = _edge_preservation(a, cfg, smooth)
    if smooth:
        m1, m2 = _safe_sqrt(sx1 * sx1 + sy1 * sy1), _safe_sqrt(sx2 * sx2 + sy2 * sy2)
    else:
        m1, m2 = torch.sqrt(sx1 * sx1 + sy1 * sy1), torch.sqrt(sx2 * sx2 + sy2 * sy2)
    r0 = _step_below(m1, cfg.theta_g, cfg.tau_g, smooth) * _step_below(m2, cfg.theta_g, cfg.tau_g, smooth)
    return LocalCriteria(d=(g1 - g2).abs(), a=a, e=e, g1=m1, g2=m2, r=_dilate3(r0))


def error_images(
    criteria: LocalCriteria,
    valid: torch.Tensor | None = None,
    config: QualityConfig | None = None,
    smooth: bool = False,
) -> ErrorImages:
    """Registration and visual error images (SPEC 3).

    e_reg = V (1 - R) [E < theta_E] and e_vis = V R [D > theta_D], V the 3 x 3-eroded validity.

    Args:
        criteria: from :func:`local_criteria` (with the same ``smooth``).
        valid: (B, 1, H, W) validity of the registered pair (1 = real content), or None.
        config: thresholds and temperatures; SPEC defaults when None.
        smooth: sigmoids instead of thresholds.
    """
    cfg = config if config is not None else QualityConfig()
    r = criteria.r
    if smooth:
        mis = torch.sigmoid((cfg.theta_e - criteria.e) / cfg.tau_e)
        vis = torch.sigmoid((criteria.d - cfg.theta_d) / cfg.tau_d)
    else:
        mis = (criteria.e < cfg.theta_e).to(r.dtype)
        vis = (criteria.d > cfg.theta_d).to(r.dtype)
    e_reg, e_vis = (1.0 - r) * mis, r * vis
    if valid is not None:
        v = check_valid_mask(valid, r)
        if not smooth:  # as the fast path: a pixel is valid where valid >= 0.5
            v = (v >= 0.5).to(r.dtype)
        v = erode_valid(v)
        e_reg, e_vis = v * e_reg, v * e_vis
    return ErrorImages(e_reg=e_reg, e_vis=e_vis)


def block_counts(error: torch.Tensor, block_size: int = 8) -> torch.Tensor:
    """Sum of a (B, 1, H, W) error image over non-overlapping blocks -> (B, 1, H/b, W/b)."""
    if error.dim() != 4 or error.shape[-2] % block_size or error.shape[-1] % block_size:
        raise ValueError(
            f"error must be (B, 1, H, W) with H, W multiples of block_size={block_size}, "
            f"got {tuple(error.shape)}"
        )
    return F.avg_pool2d(error, kernel_size=block_size, stride=block_size, divisor_override=1)


def block_pool(
    error: torch.Tensor,
    config: QualityConfig | None = None,
    smooth: bool = False,
) -> torch.Tensor:
    """Block error ratios with the floor of SPEC 4: ratios below min_block_ratio become 0.

    Smooth: ratio * sigmoid((ratio - min_block_ratio) / tau_b).

    Args:
        error: (B, 1, H, W) error image in [0, 1].
    Returns:
        (B, 1, H/b, W/b) values 0 or in [min_block_ratio, 1] (hard path).
    """
    cfg = config if config is not None else QualityConfig()
    area = cfg.block_size * cfg.block_size
    ratio = block_counts(error, cfg.block_size) / area
    if smooth:
        return ratio * torch.sigmoid((ratio - cfg.min_block_ratio) / cfg.tau_b)
    return floor_ratio(ratio, cfg)


def floor_ratio(ratio: torch.Tensor, cfg: QualityConfig) -> torch.Tensor:
    """SPEC 4's block floor: ratios below ``min_block_ratio`` become 0."""
    return torch.where(ratio < cfg.min_block_ratio, torch.zeros_like(ratio), ratio)


# ----------------------------------------------------------------------------- fast hard map


def _tan_threshold(cfg: QualityConfig) -> float | None:
    """tan(dalpha*) with E < theta_E <=> dalpha > dalpha*; None if every pixel errs."""
    # E = gamma / (1 + exp(k (A - sigma))) < theta_E  <=>  A < sigma + ln(gamma / theta_E - 1) / k
    a_star = cfg.sigma + math.log(cfg.gamma / cfg.theta_e - 1.0) / cfg.k
    if a_star > 1.0:
        return None
    dalpha_star = (1.0 - a_star) * _HALF_PI
    return math.inf if dalpha_star >= _HALF_PI else math.tan(dalpha_star)


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


def _hard_counts_chunk(g1, g2, valid, cfg: QualityConfig, t: float | None, visual: bool):
    sx1, sy1 = _sobel8(g1)
    sx2, sy2 = _sobel8(g2)
    if t is None:
        mis = torch.ones_like(sx1)
    else:  # |b| > t |a|  <=>  E < theta_E  (see the module docstring)
        cross = torch.addcmul(sx1 * sy2, sy1, sx2, value=-1.0).abs_()
        dot = torch.addcmul(sx1 * sx2, sy1, sy2).abs_()
        mis = _positive(cross.sub_(dot.mul_(t)))
    theta2 = 64.0 * cfg.theta_g * cfg.theta_g  # G <= theta <=> (8G)^2 <= 64 theta^2; 64 is exact
    strong1 = _positive(torch.addcmul(sx1 * sx1, sy1, sy1).sub_(theta2))
    strong2 = _positive(torch.addcmul(sx2 * sx2, sy2, sy2).sub_(theta2))
    # no weak pixel in the 3 x 3 window  <=>  R = 0 (R the dilated weak-pixel map)
    not_r = _erode3(torch.maximum(strong1, strong2))
    err = mis.mul_(not_r)
    if valid is not None:
        # erosion of the valid mask = dilation of the invalid one; outside the image is valid
        v = _erode3(1.0 - _positive(0.5 - valid))
        err.mul_(v)
    reg = _block_sum(err, cfg.block_size)
    if not visual:
        return reg, None
    vis = _positive((g1 - g2).abs_().sub_(cfg.theta_d)).mul_(1.0 - not_r)
    if valid is not None:
        vis.mul_(v)
    return reg, _block_sum(vis, cfg.block_size)


def _hard_counts(g1, g2, valid, cfg: QualityConfig, visual: bool):
    t = _tan_threshold(cfg)
    n, step = g1.shape[0], cfg.chunk_size
    if n <= step:
        return _hard_counts_chunk(g1, g2, valid, cfg, t, visual)
    # Chunks keep the ~20 intermediates of a chunk in cache; the maps do not depend on it.
    parts = [
        _hard_counts_chunk(
            g1[i : i + step], g2[i : i + step], None if valid is None else valid[i : i + step], cfg, t, visual
        )
        for i in range(0, n, step)
    ]
    reg = torch.cat([p[0] for p in parts])
    return reg, (torch.cat([p[1] for p in parts]) if visual else None)
