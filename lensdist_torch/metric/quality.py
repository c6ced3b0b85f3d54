"""The registration-quality metric (paper section 3; docs/method.md, sections 2-5).

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

Orientation difference. docs/method.md defines it through the double-angle vectors
``u = (s_x^2 - s_y^2, 2 s_x s_y)`` as ``0.5 * atan2(|u1 x u2|, u1 . u2)``. With
``a = g1 . g2`` and ``b = g1 x g2`` (g the Sobel gradients) one has ``u1 . u2 = a^2 - b^2`` and
``|u1 x u2| = 2|ab|``, so the same angle is ``atan2(|b|, |a|)``: second order in the gradients
instead of fourth, which keeps float32 far from underflow. The tests check both forms agree.
The fast hard map goes one step further: ``E < theta_E`` is, E being monotone in the angle,
exactly ``dalpha > dalpha*``, i.e. ``|b| > tan(dalpha*) |a|``; no atan, no exp on the hot path.

Inputs (all entry points): images of any size, padded to whole blocks (replicate padding, the
padding invalid; ``pad=False`` requires multiples of the block size); float images in
[0, data_range], uint8 in [0, 255]; a validity mask binarised at 0.5 and detached; dense
tensors, ``img2`` and ``valid`` on ``img1``'s device, none on the meta device (one-line errors
naming the argument, always checked: they read no data); ``validate=False`` (or
``torch.compile``) skips the value checks and their host sync. A pair with nothing to measure
(no pixel valid after the mask's 3 x 3 erosion, or every valid pixel in the risk map: flat
images, no edge to compare) has no quality index: ``registration_quality`` raises naming
``valid`` or the images (NaN with ``validate=False``), the stateful metrics skip and count it.
A vanishing gradient has no orientation: against a non-vanishing one it agrees with nothing
(A = 0); two vanishing gradients agree (A = 1, and they lie in the risk map anyway).
The loss lives in :mod:`lensdist_torch.metric.loss` and is re-exported here.

References:
    B. Möller, S. Posch, "Automatic Analysis of Lens Distortions in Image Registration", Institute
    of Computer Science, Martin Luther University Halle-Wittenberg (venue and year not in the text
    the project worked from; docs/method.md): the metric, section 3.
    C. S. Xydeas, V. Petrović, "Objective image fusion performance measure", Electronics Letters
    36(4), 308-309, 2000 (the orientation agreement).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from lensdist_torch.config import QualityConfig
from lensdist_torch.core.images import should_validate
from lensdist_torch.metric._hard import criteria_codes, hard_counts
from lensdist_torch.metric._inputs import (
    check_pair_values,
    get_config,
    measured,
    prepare_pair,
    prepare_unchecked,
)
from lensdist_torch.metric.criteria import (
    ErrorImages,
    LocalCriteria,
    criteria_from_grey,
    erode_valid,
    error_images,
    error_images_unchecked,
    local_criteria,
)
from lensdist_torch.metric.loss import RegistrationQualityLoss, registration_quality_loss
from lensdist_torch.metric.pooling import block_counts, block_pool, floor_ratio

__all__ = [
    "LocalCriteria",
    "ErrorImages",
    "QualityResult",
    "local_criteria",
    "error_images",
    "erode_valid",
    "block_counts",
    "block_pool",
    "floor_ratio",
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

    Attributes:
        registration_map: (B, 1, ceil(H/b), ceil(W/b)) block error ratios, 0 or in [0.1, 1].
        visual_map: (B, 1, ceil(H/b), ceil(W/b)) the same for visual errors.
        quality_index: (B,) 1 - mean of the registration map; 1 means no registration error.
            Invalid blocks count as error-free. A sample with nothing to measure (no pixel
            valid after the 3 x 3 erosion of the mask, or every valid pixel in the risk map:
            flat images) has no index: a ValueError naming ``valid`` or the images with
            ``validate=True``, NaN with ``validate=False`` (never 1).
        criteria: per-pixel (B, 1, H, W) maps, only with ``return_pixels`` (else None).
        errors: per-pixel (B, 1, H, W) error images, only with ``return_pixels`` (else None).

    Example:
        >>> x = torch.rand(2, 1, 32, 32)
        >>> res = registration_quality(x, x)
        >>> res.quality_index.tolist(), res.criteria is None
        ([1.0, 1.0], True)
    """

    registration_map: torch.Tensor
    visual_map: torch.Tensor
    quality_index: torch.Tensor
    criteria: LocalCriteria | None = None
    errors: ErrorImages | None = None


def counts_to_map(counts: torch.Tensor, config: QualityConfig | None = None) -> torch.Tensor:
    """Stored per-block error counts -> the quality map (floor applied).

    Args:
        counts: (B, 1, h, w) uint8 counts from :func:`registration_error_counts`.
        config: block size and floor; the defaults when None.

    Returns:
        (B, 1, h, w) float32 map; ``counts_to_map(c).flatten(1)`` is the feature vector.

    Example:
        >>> counts_to_map(torch.tensor([[[[0, 6, 7, 64]]]], dtype=torch.uint8)).tolist()
        [[[[0.0, 0.0, 0.109375, 1.0]]]]
    """
    cfg = get_config(config)
    return _floor(counts.float(), cfg)


def _floor(counts: torch.Tensor, cfg: QualityConfig) -> torch.Tensor:
    return floor_ratio(counts / (cfg.block_size * cfg.block_size), cfg)


def registration_error_counts(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    *,
    config: QualityConfig | None = None,
    data_range: float = 1.0,
    validate: bool = True,
    pad: bool = True,
) -> torch.Tensor:
    """Registration-error pixels per block, before the floor.

    The exact, compact form in which generated data sets store quality maps.

    Args:
        img1: (B, C, H, W) registered image, C in {1, 3}, float in [0, data_range] or uint8.
        img2: (B, C, H, W) the other image.
        valid: (B, 1, H, W) validity mask (bool or in [0, 1], binarised at 0.5) or None.
        config: thresholds and block size (at most 15); the defaults when None.
        data_range: the value of white in float inputs.
        validate: check values (NaN/Inf, range, mask; one host sync); skipped while compiling.
        pad: pad to whole blocks (else H, W must be multiples of the block size).

    Returns:
        (B, 1, ceil(H/b), ceil(W/b)) uint8 counts.

    Example:
        >>> x = torch.rand(1, 1, 16, 16)
        >>> registration_error_counts(x, x).dtype
        torch.uint8
    """
    g1, g2, valid, cfg = prepare_pair(
        img1, img2, valid, config=config, data_range=data_range, validate=validate, pad=pad
    )
    if cfg.block_size > 15:
        raise ValueError(f"uint8 counts need block_size <= 15, got {cfg.block_size}")
    with torch.no_grad():
        reg, _ = hard_counts(g1, g2, valid, cfg=cfg, visual=False)
    return reg.to(torch.uint8)


def quality_map(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    *,
    config: QualityConfig | None = None,
    data_range: float = 1.0,
    validate: bool = True,
    pad: bool = True,
) -> torch.Tensor:
    """The hard registration-error quality map (docs/method.md, section 4).

    Args:
        img1: (B, C, H, W) registered image, C in {1, 3}, float in [0, data_range] or uint8.
        img2: (B, C, H, W) the other image, on img1's device.
        valid: (B, 1, H, W) validity of the registered pair (1 = real content; bool or in
            [0, 1], binarised at 0.5) on img1's device, or None.
        config: thresholds and block size; the defaults when None.
        data_range: the value of white in float inputs (they are divided by it).
        validate: check values (NaN/Inf, range, mask; one host sync); skipped while compiling.
            Types and shapes are always checked.
        pad: pad H and W to whole blocks (replicate the images, the padding invalid); with
            False they must be multiples of the block size.

    Returns:
        (B, 1, ceil(H/8), ceil(W/8)) block error ratios, 0 or in [0.1, 1]. Blocks with no
        valid pixel read 0 (no error counted), also when the whole mask is empty: the map
        records where errors were seen; :func:`registration_quality` refuses to summarise a
        pair with nothing to measure.

    Example:
        >>> x = torch.rand(2, 1, 32, 48)
        >>> quality_map(x, x).shape
        torch.Size([2, 1, 4, 6])
        >>> float(quality_map(x, x).sum())
        0.0
        >>> quality_map(torch.rand(1, 1, 37, 61), torch.rand(1, 1, 37, 61)).shape
        torch.Size([1, 1, 5, 8])
    """
    g1, g2, valid, cfg = prepare_pair(
        img1, img2, valid, config=config, data_range=data_range, validate=validate, pad=pad
    )
    with torch.no_grad():
        reg, _ = hard_counts(g1, g2, valid, cfg=cfg, visual=False)
    return _floor(reg, cfg)


def measured_map(img1, img2, valid, config, data_range, validate, pad):
    """quality_map and the (B,) codes of what each sample leaves to measure (``measure_codes``).

    Never raises for a sample with nothing to measure (the stateful metrics skip those).
    """
    g1, g2, v, cfg = prepare_unchecked(img1, img2, valid, config=config, data_range=data_range, pad=pad)
    with torch.no_grad():
        reg, _, flags = hard_counts(g1, g2, v, cfg=cfg, visual=False, measured=True)
    if should_validate(validate):
        check_pair_values(img1, img2, valid, data_range=data_range)
    return _floor(reg, cfg), flags


def _index(reg_map: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """1 - mean of each sample's map; NaN where the sample has nothing to measure (``measured``)."""
    q = 1.0 - reg_map.mean(dim=(1, 2, 3))
    return torch.where(measured(codes), q, torch.full_like(q, float("nan")))


def registration_quality(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    *,
    config: QualityConfig | None = None,
    smooth: bool = False,
    return_pixels: bool = False,
    data_range: float = 1.0,
    validate: bool = True,
    pad: bool = True,
) -> QualityResult:
    """Registration and visual maps, a global index, and optionally the per-pixel maps.

    Args:
        img1: (B, C, H, W) registered image, float in [0, data_range] or uint8.
        img2: (B, C, H, W) the other image, on img1's device.
        valid: (B, 1, H, W) validity mask (bool or in [0, 1], binarised at 0.5) on img1's
            device, or None.
        config: thresholds, temperatures and block size; the defaults when None.
        smooth: the differentiable sigmoid path (docs/method.md, section 5).
        return_pixels: also return the per-pixel criteria and error images (B, 1, H, W).
        data_range: the value of white in float inputs.
        validate: check values (one host sync); skipped while compiling.
        pad: pad to whole blocks (else H, W must be multiples of the block size).

    Returns:
        QualityResult: maps (B, 1, ceil(H/b), ceil(W/b)), the (B,) index, per-pixel maps. The
        index of a sample with nothing to measure (see Raises) is NaN with ``validate=False``.

    Raises:
        ValueError: with ``validate=True``, a sample has nothing to measure: no pixel of its
            mask is valid after the 3 x 3 erosion (an all-zero mask, a stripe one or two pixels
            wide, or an image of one row or column), or every valid pixel is in the risk map
            (both images flat: no edge to compare); its index would otherwise read 1.0,
            perfect. Checked in the same host sync as the values.

    Example:
        >>> x = torch.rand(1, 1, 32, 32)
        >>> res = registration_quality(x, torch.roll(x, 1, dims=-1), return_pixels=True)
        >>> res.registration_map.shape, res.criteria.e.shape
        (torch.Size([1, 1, 4, 4]), torch.Size([1, 1, 32, 32]))
        >>> bool(res.quality_index < 1)
        True
    """
    g1, g2, v, cfg = prepare_unchecked(img1, img2, valid, config=config, data_range=data_range, pad=pad)
    h, w = img1.shape[-2:]
    if not smooth and not return_pixels:
        with torch.no_grad():
            reg, vis, flags = hard_counts(g1, g2, v, cfg=cfg, visual=True, measured=True)
        if should_validate(validate):  # the value checks and the flags: one host sync
            check_pair_values(img1, img2, valid, data_range=data_range, measurable=flags)
        reg_map, vis_map = _floor(reg, cfg), _floor(vis, cfg)
        return QualityResult(
            registration_map=reg_map, visual_map=vis_map, quality_index=_index(reg_map, flags))
    eroded = None if v is None else erode_valid(v)
    crit = criteria_from_grey(g1, g2, cfg, smooth)
    flags = criteria_codes(eroded, crit)
    if should_validate(validate):
        check_pair_values(img1, img2, valid, data_range=data_range, measurable=flags)
    errs = error_images_unchecked(crit, eroded, cfg, smooth)
    reg_map = block_pool(errs.e_reg, cfg, smooth)
    vis_map = block_pool(errs.e_vis, cfg, smooth)
    q = _index(reg_map, flags)
    if not return_pixels:
        return QualityResult(registration_map=reg_map, visual_map=vis_map, quality_index=q)
    if g1.shape[-2:] != (h, w):  # padded: per-pixel maps at the input size
        crit = LocalCriteria(*(t[..., :h, :w] for t in crit))
        errs = ErrorImages(*(t[..., :h, :w] for t in errs))
    return QualityResult(
        registration_map=reg_map, visual_map=vis_map, quality_index=q, criteria=crit, errors=errs)


class RegistrationQuality(nn.Module):
    """Module form of :func:`registration_quality`; it only stores the settings.

    Args:
        config: thresholds, temperatures and block size (the defaults when None).
        smooth: use the differentiable path.
        return_pixels: also return the per-pixel maps.
        data_range: the value of white in float inputs.
        validate: check values (one host sync per call); skipped while compiling.
        pad: pad to whole blocks (else H, W must be multiples of the block size).

    Shape:
        - img1, img2: (B, C, H, W); valid: (B, 1, H, W) or None.
        - Output: QualityResult with (B, 1, ceil(H/b), ceil(W/b)) maps and a (B,) index.

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
        validate: bool = True,
        pad: bool = True,
    ) -> None:
        super().__init__()
        self.config = get_config(config)
        self.smooth = smooth
        self.return_pixels = return_pixels
        self.data_range = data_range
        self.validate = validate
        self.pad = pad

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> QualityResult:
        """See :func:`registration_quality`."""
        return registration_quality(
            img1, img2, valid, config=self.config, smooth=self.smooth, return_pixels=self.return_pixels,
            data_range=self.data_range, validate=self.validate, pad=self.pad
        )

    def extra_repr(self) -> str:
        """The path and block size, shown in the module's repr."""
        return f"smooth={self.smooth}, block_size={self.config.block_size}"
