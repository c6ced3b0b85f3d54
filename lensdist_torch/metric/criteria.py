"""The per-pixel criteria and error images of the metric (docs/method.md, sections 2-3).

The building blocks of :mod:`lensdist_torch.metric.quality`, on both paths (hard and smooth):
Sobel gradients, the orientation agreement A, the edge preservation E, the gradient magnitudes
and the dilated risk map R, then the registration and visual error images. Block pooling is in
:mod:`lensdist_torch.metric.pooling`; the fast hard kernels in ``_hard``. See
:mod:`lensdist_torch.metric.quality` for the formulas and the reasoning.

References:
    B. Möller, S. Posch, "Automatic Analysis of Lens Distortions in Image Registration", Institute
    of Computer Science, Martin Luther University Halle-Wittenberg (venue and year not in the text
    the project worked from; docs/method.md): eq. 1-3.
    C. S. Xydeas, V. Petrović, "Objective image fusion performance measure", Electronics Letters
    36(4), 308-309, 2000 (the orientation agreement).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from lensdist_torch.config import QualityConfig
from lensdist_torch.core.images import should_validate
from lensdist_torch.metric._inputs import (
    binarise_valid,
    check_mask_shape,
    check_placement,
    check_values,
    erode_valid,
    get_config,
    prepare_pair,
)

__all__ = [
    "LocalCriteria",
    "ErrorImages",
    "local_criteria",
    "error_images",
    "erode_valid",
]

HALF_PI = math.pi / 2


class LocalCriteria(NamedTuple):
    """Per-pixel criteria of a pair of images (docs/method.md, section 2).

    Attributes:
        d: (B, 1, H, W) intensity difference |I1 - I2| in [0, 1].
        a: (B, 1, H, W) orientation agreement A in [0, 1] (1 = same axial orientation).
        e: (B, 1, H, W) edge preservation E in [0, gamma].
        g1: (B, 1, H, W) normalised Sobel gradient magnitude of img1.
        g2: (B, 1, H, W) the same for img2.
        r: (B, 1, H, W) risk map, 3 x 3-dilated (1 = both gradients weak).

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> c = local_criteria(x, x)
        >>> c.a.shape, bool((c.a == 1).all())
        (torch.Size([1, 1, 16, 16]), True)
    """

    d: torch.Tensor
    a: torch.Tensor
    e: torch.Tensor
    g1: torch.Tensor
    g2: torch.Tensor
    r: torch.Tensor


class ErrorImages(NamedTuple):
    """Per-pixel error images (docs/method.md, section 3).

    Attributes:
        e_reg: (B, 1, H, W) registration errors in [0, 1] (exactly {0, 1} on the hard path).
        e_vis: (B, 1, H, W) visual errors, likewise.

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> errs = error_images(local_criteria(x, x))
        >>> float(errs.e_reg.sum()), float(errs.e_vis.sum())
        (0.0, 0.0)
    """

    e_reg: torch.Tensor
    e_vis: torch.Tensor


def sobel8(grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """8 x the normalised Sobel gradients: the raw [1, 2, 1] x [-1, 0, 1] responses."""
    p = F.pad(grey, (1, 1, 1, 1), mode="replicate")
    dx = p[..., :, 2:] - p[..., :, :-2]  # (B, 1, H + 2, W)
    dy = p[..., 2:, :] - p[..., :-2, :]  # (B, 1, H, W + 2)
    sx = torch.add(dx[..., :-2, :] + dx[..., 2:, :], dx[..., 1:-1, :], alpha=2)
    sy = torch.add(dy[..., :, :-2] + dy[..., :, 2:], dy[..., :, 1:-1], alpha=2)
    return sx, sy


def _gradients(grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised Sobel (docs/method.md, section 2): (B, 1, H, W) -> s_x, s_y, each (B, 1, H, W).

    The same numbers as ``kornia.filters.spatial_gradient(x, "sobel", 1, normalized=True)``
    (replicate border, kernels / 8; the tests check agreement to 1e-6), computed separably
    with slices: several times faster on the CPU than kornia's 2-channel convolution, which
    dominated the whole metric's time. The fast hard path uses the raw responses
    (:func:`sobel8`) with thresholds scaled by the exact factor 8.
    """
    sx, sy = sobel8(grey)
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
    gradients on nearly flat images, docs/method.md, section 5). Gradients below sqrt(tiny) (1e-19 in float32)
    count as zero vectors, which keeps 1 / max finite.
    """
    m = torch.maximum(sx.abs(), sy.abs()).detach()
    ok = m > math.sqrt(torch.finfo(m.dtype).tiny)
    inv = torch.where(ok, 1.0 / torch.where(ok, m, torch.ones_like(m)), torch.zeros_like(m))
    return sx * inv, sy * inv


def _orientation_difference(dot: torch.Tensor, cross: torch.Tensor, smooth: bool) -> torch.Tensor:
    """The orientation difference atan2(|cross|, |dot|) in [0, pi/2]; 0 where a gradient vanishes.

    The caller sets pi / 2 where exactly one gradient vanishes (docs/method.md, section 2).
    """
    x, y = dot.abs(), cross.abs()
    if not smooth:
        return torch.atan2(y, x)  # atan2(0, 0) = 0: the exact formula, no guard needed
    # atan2's gradient is 0/0 at the origin; mask zero vectors before it (docs/method.md, section 5).
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


# ----------------------------------------------------------------------------- the pieces


def local_criteria(
    img1: torch.Tensor,
    img2: torch.Tensor,
    *,
    config: QualityConfig | None = None,
    smooth: bool = False,
    data_range: float = 1.0,
    validate: bool = True,
) -> LocalCriteria:
    """The per-pixel criteria D, A, E, G1, G2 and the dilated risk map R.

    See docs/method.md, section 2. Per pixel, so any image size works (no blocks here).

    Args:
        img1: (B, C, H, W) registered image, C in {1, 3}, float in [0, data_range] or uint8.
        img2: (B, C, H, W) the other image, same shape.
        config: thresholds and temperatures; the defaults of docs/method.md when None.
        smooth: sigmoid risk map (differentiable) instead of the hard one.
        data_range: the value of white in float inputs (they are divided by it).
        validate: check for NaN/Inf and the value range (one host sync); skipped while
            compiling.

    Returns:
        LocalCriteria of (B, 1, H, W) tensors.

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> c = local_criteria(x, x)
        >>> bool((c.a == 1).all()), bool((c.d == 0).all())
        (True, True)
    """
    g1, g2, _, cfg = prepare_pair(img1, img2, None, config=config, data_range=data_range, validate=validate, pad=None)
    return criteria_from_grey(g1, g2, cfg, smooth)


def criteria_from_grey(g1, g2, cfg: QualityConfig, smooth: bool) -> LocalCriteria:
    sx1, sy1, sx2, sy2 = _pair_gradients(g1, g2)
    if smooth:
        ux1, uy1 = _direction(sx1, sy1)
        ux2, uy2 = _direction(sx2, sy2)
    else:
        ux1, uy1, ux2, uy2 = sx1, sy1, sx2, sy2
    dot = ux1 * ux2 + uy1 * uy2
    cross = ux1 * uy2 - uy1 * ux2
    dalpha = _orientation_difference(dot, cross, smooth)
    # a vanishing gradient has no orientation: against a non-vanishing one nothing agrees (A = 0)
    lone = ((ux1 == 0) & (uy1 == 0)) != ((ux2 == 0) & (uy2 == 0))
    a = 1.0 - torch.where(lone, torch.full_like(dalpha, HALF_PI), dalpha) / HALF_PI
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
    *,
    config: QualityConfig | None = None,
    smooth: bool = False,
    validate: bool = True,
) -> ErrorImages:
    """Registration and visual error images (docs/method.md, section 3).

    e_reg = V (1 - R) [E < theta_E] and e_vis = V R [D > theta_D], V the 3 x 3-eroded validity.

    Args:
        criteria: from :func:`local_criteria` (with the same ``smooth``).
        valid: (B, 1, H, W) validity of the registered pair (1 = real content), bool or in
            [0, 1], on the criteria's device, or None. Binarised at 0.5 and detached on both
            paths.
        config: thresholds and temperatures; the defaults of docs/method.md when None.
        smooth: sigmoids instead of thresholds.
        validate: check the mask for NaN and values outside [0, 1] (one host sync).

    Returns:
        ErrorImages of (B, 1, H, W) tensors.

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> y = torch.roll(x, 1, dims=-1)
        >>> valid = torch.zeros(1, 1, 16, 16)
        >>> float(error_images(local_criteria(x, y), valid).e_reg.sum())
        0.0
    """
    cfg = get_config(config)
    v = None
    if valid is not None:
        check_mask_shape(valid, criteria.r)
        check_placement([("valid", valid)], criteria.r.device)
        if should_validate(validate):
            check_values([], valid, data_range=1.0)
        v = erode_valid(binarise_valid(valid, criteria.r))
    return error_images_unchecked(criteria, v, cfg, smooth)


def error_images_unchecked(
    criteria: LocalCriteria, v: torch.Tensor | None, cfg: QualityConfig, smooth: bool
) -> ErrorImages:
    """error_images with ``v`` the eroded {0, 1} validity (or None)."""
    r = criteria.r
    if smooth:
        mis = torch.sigmoid((cfg.theta_e - criteria.e) / cfg.tau_e)
        vis = torch.sigmoid((criteria.d - cfg.theta_d) / cfg.tau_d)
    else:
        mis = (criteria.e < cfg.theta_e).to(r.dtype)
        vis = (criteria.d > cfg.theta_d).to(r.dtype)
    e_reg, e_vis = (1.0 - r) * mis, r * vis
    if v is not None:
        e_reg, e_vis = v * e_reg, v * e_vis
    return ErrorImages(e_reg=e_reg, e_vis=e_vis)
