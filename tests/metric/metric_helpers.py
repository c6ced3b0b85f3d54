"""Shared helpers of the metric tests: textures, ramps, and docs/method.md sections 2-4 written
literally (kornia Sobel, double-angle vectors) as the reference the library must match."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.filters import spatial_gradient

from lensdist_torch import QualityConfig, metric
from lensdist_torch.metric import block_pool, error_images, local_criteria

CFG = QualityConfig()
HALF_PI = math.pi / 2

#: Every public entry point of the metric (lensdist_torch.metric) that takes a pair, by name, as
#: ``call(img1, img2, valid, **settings)`` (``local_criteria`` takes no mask: it ignores ``valid``).
ENTRY_POINTS = {
    "quality_map": lambda a, b, v, **k: metric.quality_map(a, b, v, **k),
    "registration_error_counts": lambda a, b, v, **k: metric.registration_error_counts(a, b, v, **k),
    "registration_quality": lambda a, b, v, **k: metric.registration_quality(a, b, v, **k),
    "registration_quality smooth": lambda a, b, v, **k: metric.registration_quality(a, b, v, smooth=True, **k),
    "registration_quality pixels": lambda a, b, v, **k: metric.registration_quality(a, b, v, return_pixels=True, **k),
    "RegistrationQuality": lambda a, b, v, **k: metric.RegistrationQuality(**k)(a, b, v),
    "registration_quality_loss": lambda a, b, v, **k: metric.registration_quality_loss(a, b, v, **k),
    "RegistrationQualityLoss": lambda a, b, v, **k: metric.RegistrationQualityLoss(**k)(a, b, v),
    "RegistrationQualityMetric": lambda a, b, v, **k: metric.RegistrationQualityMetric(**k).update(a, b, v),
    "local_criteria": lambda a, b, v, **k: metric.local_criteria(a, b, **k),
}


def textured(b: int, h: int, w: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """Smooth blobs + fine noise + a flat patch: strong, weak and zero gradients all occur."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(b, 1, h // 4 + 2, w // 4 + 2, generator=g, dtype=torch.float64)
    x = F.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=True)
    x = 0.75 * x + 0.25 * torch.rand(b, 1, h, w, generator=g, dtype=torch.float64) * (x > 0.5)
    x[..., h // 4 : h // 2, w // 4 : w // 2] = 0.5  # weak-gradient region (risk map)
    return x.clamp(0, 1).to(dtype)


def textured_pair(b: int, h: int, w: int, seed: int, dtype=torch.float64):
    """img2 = img1 shifted by one pixel and mixed with another texture: a mix of agreeing and
    disagreeing orientations, weak and strong gradients, small and large differences."""
    img1 = textured(b, h, w, seed, torch.float64)
    other = textured(b, h, w, seed + 1000, torch.float64)
    img2 = 0.7 * torch.roll(img1, shifts=(1, 1), dims=(-2, -1)) + 0.3 * other
    return img1.to(dtype), img2.to(dtype)


def x_ramp(h: int, w: int, slope: float, dtype=torch.float64) -> torch.Tensor:
    """0.5 + slope * (x - centre): constant along y, so s_y = 0 exactly and s_x = slope
    (slope / 2 on the two border columns, replicate padding)."""
    x = torch.arange(w, dtype=dtype) - (w - 1) / 2
    return (0.5 + slope * x).expand(1, 1, h, w).clone()


def angle_ramp(h: int, w: int, slope: float, degrees: float, dtype=torch.float64) -> torch.Tensor:
    """A linear ramp whose gradient has direction ``degrees``: interior Sobel = slope (cos, sin)."""
    phi = math.radians(degrees)
    y = (torch.arange(h, dtype=dtype) - (h - 1) / 2)[:, None]
    x = (torch.arange(w, dtype=dtype) - (w - 1) / 2)[None, :]
    return (0.5 + slope * (math.cos(phi) * x + math.sin(phi) * y))[None, None]


def blocks(x: torch.Tensor, b: int) -> torch.Tensor:
    """Sum over non-overlapping b x b blocks, written independently of the library."""
    n, c, h, w = x.shape
    return x.reshape(n, c, h // b, b, w // b, b).sum(dim=(3, 5))


def spec_reference(img1, img2, valid=None, cfg: QualityConfig = CFG):
    """docs/method.md, sections 2-4 transcribed literally (kornia Sobel, double-angle vectors, binary validity)."""
    s1 = spatial_gradient(img1, mode="sobel", order=1, normalized=True)
    s2 = spatial_gradient(img2, mode="sobel", order=1, normalized=True)
    sx1, sy1, sx2, sy2 = s1[:, :, 0], s1[:, :, 1], s2[:, :, 0], s2[:, :, 1]
    u1x, u1y = sx1**2 - sy1**2, 2 * sx1 * sy1
    u2x, u2y = sx2**2 - sy2**2, 2 * sx2 * sy2
    # "+ 0.0" turns a -0.0 dot product (a zero gradient times a negative component) into +0.0:
    # IEEE atan2(0, -0) = pi, which would give a zero vector the orientation difference pi / 2.
    # A zero vector has no orientation (docs/method.md, section 2): two of them agree (dalpha =
    # 0, atan2(0, 0)), one against a non-zero vector agrees with nothing (dalpha = pi / 2).
    dalpha = 0.5 * torch.atan2((u1x * u2y - u1y * u2x).abs(), u1x * u2x + u1y * u2y + 0.0)
    zero1, zero2 = (sx1 == 0) & (sy1 == 0), (sx2 == 0) & (sy2 == 0)
    dalpha = torch.where(zero1 != zero2, torch.full_like(dalpha, HALF_PI), dalpha)
    a = 1 - dalpha / HALF_PI
    e = cfg.gamma / (1 + torch.exp(cfg.k * (a - cfg.sigma)))
    g1, g2 = torch.sqrt(sx1**2 + sy1**2), torch.sqrt(sx2**2 + sy2**2)
    r0 = ((g1 <= cfg.theta_g) & (g2 <= cfg.theta_g)).to(img1.dtype)
    r = F.max_pool2d(r0, kernel_size=3, stride=1, padding=1)
    d = (img1 - img2).abs()
    v = torch.ones_like(d) if valid is None else valid.to(d.dtype)
    # 3 x 3 erosion; outside the image counts as valid
    v = -F.max_pool2d(-F.pad(v, (1, 1, 1, 1), value=1.0), kernel_size=3, stride=1)
    e_reg = v * (1 - r) * (e < cfg.theta_e).to(d.dtype)
    e_vis = v * r * (d > cfg.theta_d).to(d.dtype)
    bs = cfg.block_size
    reg = blocks(e_reg, bs) / bs**2
    vis = blocks(e_vis, bs) / bs**2
    reg = torch.where(reg < cfg.min_block_ratio, 0.0, reg)
    vis = torch.where(vis < cfg.min_block_ratio, 0.0, vis)
    return dict(d=d, a=a, e=e, g1=g1, g2=g2, r=r, e_reg=e_reg, e_vis=e_vis, reg=reg, vis=vis)


def hard_from_pieces(img1, img2, valid=None, cfg: QualityConfig = CFG):
    crit = local_criteria(img1, img2, config=cfg)
    errs = error_images(crit, valid, config=cfg)
    return block_pool(errs.e_reg, cfg), block_pool(errs.e_vis, cfg), errs


def assert_in_floor_range(m: torch.Tensor, floor: float = 0.1) -> None:
    assert bool(((m == 0) | ((m >= floor) & (m <= 1))).all()), m


