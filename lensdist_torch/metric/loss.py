"""The smooth registration-error map as a loss (docs/method.md, section 5).

The default reduction, ``"masked_mean"``, averages the smooth map over *valid blocks* only: a
block counts when every one of its pixels is valid after the 3 x 3 erosion of the mask. The
plain ``"mean"`` counts invalid blocks as error-free, so it rewards a warp that pushes the
image out of the frame (a quarter of the frame valid: a quarter of the loss); the masked mean
does not fall when the mask shrinks over equally misregistered content. Partially covered
blocks are left out because their ratios are biased low (their invalid pixels cannot err);
image padding (any size is padded to whole blocks) is invalid, so partial edge blocks are left
out too. The mask is binarised at 0.5 and detached: no gradient reaches it.

Nothing to measure. A sample with nothing to measure (no valid block, or every valid pixel in
the risk map: flat, textureless images; the rule of
:func:`~lensdist_torch.metric.quality.registration_quality`, read with ``measured``) adds
nothing to the masked mean, neither error nor blocks: the mean is over the valid blocks of the
measurable samples of the batch, so a flat pair does not dilute the others (three flat pairs
beside a misregistered one used to divide its loss by 4), as the stateful metric skips such
pairs. A batch with nothing to measure gives 0 with a zero gradient, with or without
``validate``: unlike :func:`~lensdist_torch.metric.quality.registration_quality`, which
refuses to call such a pair perfect (NaN with ``validate=False``), a loss must keep training
going, and 0 with no gradient says "no signal" (a NaN would poison the weights). Keep a
photometric or overlap term beside it, since this loss alone cannot see a warp that leaves the
frame.

Reductions. ``"per_sample"`` gives (B,): each sample's own masked mean (what piq's losses call
``reduction="none"``), for weighting samples or logging them. ``"none"`` keeps the meaning it has
in ``torch.nn`` and kornia's losses: nothing reduced, the (B, 1, h, w) map of blocks.

References:
    B. Möller, S. Posch, "Automatic Analysis of Lens Distortions in Image Registration", Institute
    of Computer Science, Martin Luther University Halle-Wittenberg (venue and year not in the text
    the project worked from; docs/method.md): the metric this smooths, section 3.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric._hard import criteria_codes
from lensdist_torch.metric._inputs import get_config, measured, prepare_pair
from lensdist_torch.metric.criteria import criteria_from_grey, erode_valid, error_images_unchecked
from lensdist_torch.metric.pooling import block_pool

__all__ = ["REDUCTIONS", "OVERSHOOT", "registration_quality_loss", "RegistrationQualityLoss"]

#: The reductions of the loss; the first is the default.
REDUCTIONS = ("masked_mean", "mean", "sum", "per_sample", "none")
#: How far outside [0, data_range], in units of data_range, the loss takes an image as it is:
#: a bicubic warp (PyTorch's, a = -0.75) of an image in [0, 1] stays within [-0.4453, 1.4453] (the
#: sums of its 4 x 4 kernel's negative and positive weights at half-pixel shifts), and no more: a
#: mean-subtracted [0, 1] image (down to -0.5) is still refused.
OVERSHOOT = 0.45


def _check_reduction(reduction: str) -> None:
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction must be one of {REDUCTIONS}, got {reduction!r}")


def _reduce(reg_map: torch.Tensor, v: torch.Tensor | None, crit, block: int, reduction: str):
    if reduction == "none":
        return reg_map
    if reduction == "sum":
        return reg_map.sum()
    if reduction == "mean":
        return reg_map.mean()
    # 1 where the whole block is valid (every block without a mask), in a measurable sample: the
    # codes are read only here, the reductions above do not need them
    full = torch.ones_like(reg_map) if v is None else -F.max_pool2d(-v, kernel_size=block, stride=block)
    full = full * measured(criteria_codes(v, crit)).to(full.dtype).view(-1, 1, 1, 1)
    # clamp: nothing to measure gives 0 / 1 = 0 and a zero gradient (no NaN, no host sync)
    dims = (1, 2, 3) if reduction == "per_sample" else None
    return (reg_map * full).sum(dim=dims) / full.sum(dim=dims).clamp_min(1.0)


def registration_quality_loss(
    img1: torch.Tensor,
    img2: torch.Tensor,
    valid: torch.Tensor | None = None,
    *,
    config: QualityConfig | None = None,
    reduction: str = "masked_mean",
    data_range: float = 1.0,
    validate: bool = True,
    pad: bool = True,
) -> torch.Tensor:
    """The smooth registration-error map reduced to a loss; lower is better.

    See docs/method.md, section 5, and the module docstring for the masked mean.

    Args:
        img1: (B, C, H, W) float image in [0, data_range] (e.g. the warped one); gradients
            flow to it. What an interpolating warp puts outside the range (a bicubic warp's
            overshoot, up to ``OVERSHOOT`` times data_range beyond it) is measured as it is,
            gradients included; farther out is an error (0-255 images without ``data_range=255``).
        img2: (B, C, H, W) the other image, on img1's device; gradients flow to it too.
        valid: (B, 1, H, W) validity (e.g. the warp's in-bounds mask) on img1's device, bool or
            in [0, 1], binarised at 0.5 and detached; or None (everything valid).
        config: temperatures and thresholds; the defaults when None.
        reduction: ``"masked_mean"`` (default: mean over the valid blocks of the measurable
            samples of the batch), ``"mean"`` (over all blocks and the batch: invalid blocks
            count as 0, flat pairs dilute it), ``"sum"``, ``"per_sample"`` for (B,), each sample's
            mean over its own valid blocks (0 for a sample with nothing to measure; piq's
            ``"none"``), or ``"none"`` for the
            (B, 1, ceil(H/b), ceil(W/b)) map (torch's and kornia's ``"none"``).
        data_range: the value of white in float inputs (they are divided by it).
        validate: check values (NaN/Inf, range, mask; one host sync); skipped while compiling.
        pad: pad to whole blocks (else H, W must be multiples of the block size).

    Returns:
        A scalar tensor, (B,) for ``"per_sample"``, or the map for ``"none"``. With nothing
        to measure in the batch (no valid block, or flat images) the masked mean is 0 with a
        zero gradient (see the module docstring), and so is such a sample's ``"per_sample"``
        value; ``"mean"`` and ``"sum"`` count invalid blocks as 0, and ``"none"`` shows them
        as 0. The masked mean weights measurable samples by their valid blocks, so it equals
        the mean of their ``"per_sample"`` values when they have as many.

    Example:
        >>> x = torch.rand(1, 1, 32, 32, requires_grad=True)
        >>> y = torch.roll(x.detach(), 1, dims=-1)
        >>> registration_quality_loss(x, y).backward()
        >>> bool(torch.isfinite(x.grad).all())
        True
        >>> valid = torch.zeros(1, 1, 32, 32)
        >>> valid[..., :16, :16] = 1  # a quarter of the frame: the masked mean does not drop
        >>> full = registration_quality_loss(x, y)
        >>> bool(registration_quality_loss(x, y, valid) > 0.5 * full)
        True

        Per sample, as piq's ``reduction="none"``; the map, as torch's and kornia's:

        >>> x2, y2 = torch.cat([x.detach(), y]), torch.cat([y, y])  # misregistered, identical
        >>> per = registration_quality_loss(x2, y2, reduction="per_sample")
        >>> per.shape, bool(per[0] > 0.3), round(float(per[1]), 3)  # smooth: near 0, not 0
        (torch.Size([2]), True, 0.0)
        >>> registration_quality_loss(x2, y2, reduction="none").shape
        torch.Size([2, 1, 4, 4])
    """
    _check_reduction(reduction)
    g1, g2, valid, cfg = prepare_pair(
        img1, img2, valid, config=config, data_range=data_range, validate=validate, pad=pad, overshoot=OVERSHOOT
    )
    v = None if valid is None else erode_valid(valid)
    crit = criteria_from_grey(g1, g2, cfg, smooth=True)
    reg_map = block_pool(error_images_unchecked(crit, v, cfg, smooth=True).e_reg, cfg, smooth=True)
    return _reduce(reg_map, v, crit, cfg.block_size, reduction)


class RegistrationQualityLoss(nn.Module):
    """Module form of :func:`registration_quality_loss`: an auxiliary loss for registration.

    Args:
        config: temperatures and thresholds; the defaults when None.
        reduction: ``"masked_mean"`` (default), ``"mean"``, ``"sum"``, ``"per_sample"`` (B,)
            or ``"none"`` (the block map); see :func:`registration_quality_loss`.
        data_range: the value of white in float inputs.
        validate: check values (one host sync per call); skipped while compiling.
        pad: pad to whole blocks (else H, W must be multiples of the block size).

    Shape:
        - img1, img2: (B, C, H, W); valid: (B, 1, H, W) or None.
        - Output: scalar, (B,) for ``reduction="per_sample"``, or (B, 1, ceil(H/b),
          ceil(W/b)) for ``reduction="none"``.

    Example:
        >>> loss_fn = RegistrationQualityLoss()
        >>> warped = torch.rand(4, 1, 64, 64, requires_grad=True)
        >>> target = torch.rand(4, 1, 64, 64)
        >>> loss = loss_fn(warped, target, torch.ones(4, 1, 64, 64))
        >>> loss.backward()
        >>> loss.shape
        torch.Size([])
    """

    def __init__(
        self,
        config: QualityConfig | None = None,
        reduction: str = "masked_mean",
        data_range: float = 1.0,
        validate: bool = True,
        pad: bool = True,
    ) -> None:
        super().__init__()
        _check_reduction(reduction)
        self.config = get_config(config)
        self.reduction = reduction
        self.data_range = data_range
        self.validate = validate
        self.pad = pad

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """See :func:`registration_quality_loss`."""
        return registration_quality_loss(
            img1, img2, valid, config=self.config, reduction=self.reduction, data_range=self.data_range,
            validate=self.validate, pad=self.pad
        )

    def extra_repr(self) -> str:
        """The reduction, shown in the module's repr."""
        return f"reduction={self.reduction!r}"
