"""The registration-quality metric (paper section 3, SPEC sections 2-5).

Two registered images give, per pixel, an intensity difference D, an edge-preservation value
E (agreement of the axial gradient orientations) and a risk map R (both gradients weak,
dilated 3 x 3). Structured pixels whose orientations disagree are registration errors;
homogeneous pixels whose intensities disagree are visual errors. Each error image is pooled
in non-overlapping blocks into a map of error ratios, with ratios below 0.1 set to 0.

Two paths compute the same formulas:

* the hard path (``quality_map``, ``local_criteria``/``error_images``/``block_pool`` with
  ``smooth=False``) uses the exact formulas, no eps anywhere;
* the smooth path (``smooth=True``, ``RegistrationQualityLoss``) replaces each step
  ``[x < theta]`` by ``sigmoid((theta - x) / tau)`` and is differentiable everywhere.

Orientation difference. SPEC defines it through the double-angle vectors
``u = (s_x^2 - s_y^2, 2 s_x s_y)`` as ``0.5 * atan2(|u1 x u2|, u1 . u2)``. With
``a = g1 . g2`` and ``b = g1 x g2`` (g the Sobel gradients) one has ``u1 . u2 = a^2 - b^2`` and
``|u1 x u2| = 2|ab|``, so the same angle is ``atan2(|b|, |a|)``: second order in the gradients
instead of fourth, which keeps float32 far from underflow. The tests check both forms agree.
The fast hard map goes one step further: ``E < theta_E`` is, E being monotone in the angle,
exactly ``dalpha > dalpha*``, i.e. ``|b| > tan(dalpha*) |a|``; no atan, no exp on the hot path.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric.criteria import (
    ErrorImages,
    LocalCriteria,
    _criteria,
    _hard_counts,
    block_counts,
    block_pool,
    erode_valid,
    error_images,
    floor_ratio,
    local_criteria,
    prepare_pair,
)

__all__ = [
    "LocalCriteria",
    "ErrorImages",
    "QualityResult",
    "local_criteria",
    "error_images",
    "erode_valid",
    "block_counts",
    "block_pool",
    "quality_map",
    "registration_error_counts",
    "counts_to_map",
    "registration_quality",
    "registration_quality_loss",
    "RegistrationQuality",
    "RegistrationQualityLoss",
]


class QualityResult(NamedTuple):
    """What :func:`registration_quality` returns.

    registration_map, visual_map: (B, 1, H/b, W/b) block error ratios, 0 or in [0.1, 1].
    quality_index: (B,) 1 - mean of the registration map; 1 means no registration error.
    criteria, errors: the per-pixel maps, only when asked for (else None).
    """

    registration_map: torch.Tensor
    visual_map: torch.Tensor
    quality_index: torch.Tensor
    criteria: LocalCriteria | None = None
    errors: ErrorImages | None = None


def counts_to_map(counts: torch.Tensor, config: QualityConfig | None = None) -> torch.Tensor:
    """Stored per-block error counts (uint8, from :func:`registration_error_counts`) -> the
    quality map (float32, floor applied). ``counts_to_map(c).flatten(1)`` is the feature vector."""
    cfg = config if config is not None else QualityConfig()
    return _floor(counts.float(), cfg)


def _floor(counts: torch.Tensor, cfg: QualityConfig) -> torch.Tensor:
    return floor_ratio(counts / (cfg.block_size * cfg.block_size), cfg)


def registration_error_counts(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    config: QualityConfig | None = None,
    data_range: float = 1.0,
    validate: bool = True,
) -> torch.Tensor:
    """Registration-error pixels per block, before the floor: (B, 1, H/b, W/b) uint8.

    This is the exact, compact form in which generated data sets store quality maps.
    """
    g1, g2, valid, cfg = prepare_pair(img1, img2, valid, config, data_range, validate)
    if cfg.block_size > 15:
        raise ValueError(f"uint8 counts need block_size <= 15, got {cfg.block_size}")
    with torch.no_grad():
        reg, _ = _hard_counts(g1, g2, valid, cfg, visual=False)
    return reg.to(torch.uint8)


def quality_map(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    config: QualityConfig | None = None,
    data_range: float = 1.0,
    validate: bool = True,
) -> torch.Tensor:
    """The hard registration-error quality map of SPEC section 4.

    Args:
        img1, img2: registered images (B, C, H, W), C in {1, 3}, float in [0, data_range] or
            uint8; H and W multiples of the block size (8).
        valid: (B, 1, H, W) validity of the registered pair (1 = real content), or None.
        config: thresholds and block size; SPEC defaults when None.
        data_range: the value of white in float inputs.
        validate: check inputs for NaN/Inf (one pass over the data); shapes are always checked.

    Returns:
        (B, 1, H/8, W/8) tensor of block error ratios, 0 or in [0.1, 1].

    Example:
        >>> x = torch.rand(2, 1, 32, 48)
        >>> quality_map(x, x).shape
        torch.Size([2, 1, 4, 6])
        >>> float(quality_map(x, x).sum())
        0.0
    """
    g1, g2, valid, cfg = prepare_pair(img1, img2, valid, config, data_range, validate)
    with torch.no_grad():
        reg, _ = _hard_counts(g1, g2, valid, cfg, visual=False)
    return _floor(reg, cfg)


# ----------------------------------------------------------------------------- everything at once


def registration_quality(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    config: QualityConfig | None = None,
    smooth: bool = False,
    return_pixels: bool = False,
    data_range: float = 1.0,
) -> QualityResult:
    """Registration and visual maps, a global index, and optionally the per-pixel maps.

    Args:
        img1, img2: registered images (B, C, H, W), float in [0, data_range] or uint8.
        valid: (B, 1, H, W) validity mask or None.
        config: thresholds, temperatures and block size; SPEC defaults when None.
        smooth: the differentiable sigmoid path (SPEC 5) instead of the hard one.
        return_pixels: also return the per-pixel criteria and error images.
    """
    g1, g2, valid, cfg = prepare_pair(img1, img2, valid, config, data_range)
    if not smooth and not return_pixels:
        with torch.no_grad():
            reg, vis = _hard_counts(g1, g2, valid, cfg, visual=True)
        reg_map, vis_map = _floor(reg, cfg), _floor(vis, cfg)
        return QualityResult(reg_map, vis_map, 1.0 - reg_map.mean(dim=(1, 2, 3)))
    crit = _criteria(g1, g2, cfg, smooth)
    errs = error_images(crit, valid, cfg, smooth)
    reg_map = block_pool(errs.e_reg, cfg, smooth)
    vis_map = block_pool(errs.e_vis, cfg, smooth)
    q = 1.0 - reg_map.mean(dim=(1, 2, 3))
    if return_pixels:
        return QualityResult(reg_map, vis_map, q, crit, errs)
    return QualityResult(reg_map, vis_map, q)


_REDUCTIONS = ("mean", "sum", "none")


def registration_quality_loss(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    config: QualityConfig | None = None,
    reduction: str = "mean",
    data_range: float = 1.0,
) -> torch.Tensor:
    """The smooth registration-error map reduced to a loss (SPEC 5); lower is better.

    Args:
        img1, img2: (B, C, H, W) float images in [0, data_range]; gradients flow to both.
        valid: (B, 1, H, W) validity (e.g. the warp's in-bounds mask) or None.
        config: temperatures and thresholds; SPEC defaults when None.
        reduction: 'mean' (over blocks and batch), 'sum', or 'none' for the (B, 1, H/b, W/b) map.

    Example:
        >>> x = torch.rand(1, 1, 32, 32, requires_grad=True)
        >>> y = torch.roll(x.detach(), 1, dims=-1)
        >>> registration_quality_loss(x, y).backward()
        >>> bool(torch.isfinite(x.grad).all())
        True
    """
    if reduction not in _REDUCTIONS:
        raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")
    g1, g2, valid, cfg = prepare_pair(img1, img2, valid, config, data_range)
    crit = _criteria(g1, g2, cfg, smooth=True)
    reg_map = block_pool(error_images(crit, valid, cfg, smooth=True).e_reg, cfg, smooth=True)
    if reduction == "mean":
        return reg_map.mean()
    if reduction == "sum":
        return reg_map.sum()
    return reg_map


class RegistrationQuality(nn.Module):
    """Module form of :func:`registration_quality`; it only stores the settings.

    Args:
        config: thresholds, temperatures and block size (SPEC defaults when None).
        smooth: use the differentiable path.
        return_pixels: also return the per-pixel maps.
        data_range: the value of white in float inputs.

    Example:
        >>> metric = RegistrationQuality()
        >>> x = torch.rand(2, 1, 32, 32)
        >>> metric(x, x).registration_map.shape
        torch.Size([2, 1, 4, 4])
    """

    def __init__(
        self,
        config: QualityConfig | None = None,
        smooth: bool = False,
        return_pixels: bool = False,
        data_range: float = 1.0,
    ) -> None:
        super().__init__()
        self.config = config if config is not None else QualityConfig()
        self.smooth = smooth
        self.return_pixels = return_pixels
        self.data_range = data_range

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> QualityResult:
        return registration_quality(
            img1, img2, valid, self.config, self.smooth, self.return_pixels, self.data_range
        )

    def extra_repr(self) -> str:
        return f"smooth={self.smooth}, block_size={self.config.block_size}"


class RegistrationQualityLoss(nn.Module):
    """Module form of :func:`registration_quality_loss`: an auxiliary loss for registration.

    Example:
        >>> loss_fn = RegistrationQualityLoss()
        >>> warped = torch.rand(4, 1, 64, 64, requires_grad=True)
        >>> target = torch.rand(4, 1, 64, 64)
        >>> loss = loss_fn(warped, target)
        >>> loss.backward()
    """

    def __init__(self, config: QualityConfig | None = None, reduction: str = "mean", data_range: float = 1.0) -> None:
        super().__init__()
        if reduction not in _REDUCTIONS:
            raise ValueError(f"reduction must be one of {_REDUCTIONS}, got {reduction!r}")
        self.config = config if config is not None else QualityConfig()
        self.reduction = reduction
        self.data_range = data_range

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        return registration_quality_loss(img1, img2, valid, self.config, self.reduction, self.data_range)

    def extra_repr(self) -> str:
        return f"reduction={self.reduction!r}"
