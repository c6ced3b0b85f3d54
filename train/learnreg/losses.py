"""The warp, the two losses and the corner error, all on corner offsets (B, 4, 2) in px.

Offsets delta describe the homography from B's to A's pixel coordinates that maps B's corners
(:func:`~learnreg.data.patch_corners`) onto the corners + delta.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.geometry.transform import get_perspective_transform, warp_perspective

from lensdist_torch import RegistrationQualityLoss
from lensdist_torch.geometry import homography

from .data import patch_corners

__all__ = ["offsets_to_homography", "warp_a_to_b", "corner_error", "l1_loss", "quality_loss"]


def offsets_to_homography(delta: torch.Tensor, patch: int) -> torch.Tensor:
    """(B, 4, 2) corner offsets -> (B, 3, 3) homography from B's to A's pixel coordinates."""
    corners = patch_corners(patch, device=delta.device, dtype=delta.dtype).expand(delta.shape[0], 4, 2)
    return get_perspective_transform(corners, corners + delta)


def warp_a_to_b(a: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp A into B's frame with the homography given by the corner offsets.

    Returns the warped A and its validity mask (1 where the warp sampled inside A).
    """
    n, _, h, w = a.shape
    corners = patch_corners(h, device=a.device, dtype=a.dtype).expand(n, 4, 2)
    m = get_perspective_transform(corners + delta, corners)  # A coords -> B coords
    warped = warp_perspective(a, m, (h, w), align_corners=True)
    valid = warp_perspective(torch.ones_like(a[:, :1]), m, (h, w), align_corners=True)
    return warped, (valid > 0.999).to(a.dtype)


def corner_error(pred: torch.Tensor, gt: torch.Tensor, patch: int) -> torch.Tensor:
    """Mean Euclidean corner error per pair, px: (N,) float64.

    ``lensdist_torch.geometry.homography.corner_error`` on the two homographies (solved in
    float64): the mean distance between the patch corners mapped by each, which for offsets is
    the mean of ||pred_i - gt_i|| over the four corners.
    """
    pred, gt = pred.detach().double(), gt.detach().double().to(pred.device)
    return homography.corner_error(offsets_to_homography(pred, patch), offsets_to_homography(gt, patch), patch, patch)


def l1_loss(warped: torch.Tensor, b: torch.Tensor, valid: torch.Tensor, levels: int = 1) -> torch.Tensor:
    """Masked photometric L1, averaged over ``levels`` levels of a 2x average-pooling pyramid.

    On a fine texture the full-resolution L1 is flat beyond a pixel or two of misalignment; the
    coarse levels widen its basin (``levels = 1``: the plain L1).
    """
    total = warped.new_zeros(())
    for level in range(levels):
        if level:
            warped, b = F.avg_pool2d(warped, 2), F.avg_pool2d(b, 2)
            valid = (F.avg_pool2d(valid, 2) > 0.999).to(valid.dtype)
        total = total + ((warped - b).abs() * valid).sum() / valid.sum().clamp_min(1.0)
    return total / levels


def quality_loss(loss_fn: RegistrationQualityLoss, warped, b, valid) -> torch.Tensor:
    """The smooth block-error map, averaged over the *valid* blocks.

    The metric masks invalid pixels out; averaging over all blocks would reward a warp that
    pushes A out of the frame, so the map is normalised by the valid share of each block.
    ``loss_fn`` must have ``reduction="none"``.
    """
    err = loss_fn(warped.clamp(0, 1), b, valid)  # (B, 1, H/8, W/8)
    bs = loss_fn.config.block_size
    vb = F.avg_pool2d(valid, bs, bs)
    return err.sum() / vb.sum().clamp_min(1.0)
