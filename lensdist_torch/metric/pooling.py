"""Block pooling of the error images and the block floor (docs/method.md, section 4).

Each error image is summed over non-overlapping b x b blocks (b = 8 by default); a block's
ratio is its count over b * b, and ratios below ``min_block_ratio`` (0.1) become 0. The entry
points of :mod:`lensdist_torch.metric.quality` pad images to whole blocks first; these pieces
take H and W multiples of the block size.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric._inputs import get_config

__all__ = ["block_counts", "block_pool", "floor_ratio"]


def block_counts(error: torch.Tensor, block_size: int = 8) -> torch.Tensor:
    """Sum of an error image over non-overlapping blocks.

    Args:
        error: (B, 1, H, W) error image, H and W multiples of ``block_size``.
        block_size: side of the square blocks in pixels.

    Returns:
        (B, 1, H / block_size, W / block_size) sums.

    Raises:
        ValueError: ``error`` is not 4-D or not divisible into blocks.

    Example:
        >>> block_counts(torch.ones(1, 1, 16, 24)).squeeze().tolist()
        [[64.0, 64.0, 64.0], [64.0, 64.0, 64.0]]
    """
    if error.dim() != 4 or error.shape[-2] % block_size or error.shape[-1] % block_size:
        raise ValueError(
            f"error must be (B, 1, H, W) with H, W multiples of block_size={block_size}, "
            f"got {tuple(error.shape)}"
        )
    return F.avg_pool2d(error, kernel_size=block_size, stride=block_size, divisor_override=1)


def floor_ratio(ratio: torch.Tensor, config: QualityConfig | None = None) -> torch.Tensor:
    """The block floor of docs/method.md, section 4: ratios below ``min_block_ratio`` become 0.

    Args:
        ratio: block error ratios in [0, 1], any shape.
        config: supplies ``min_block_ratio`` (0.1 by default).

    Returns:
        ``ratio`` with values below the floor set to 0 (same shape and dtype).

    Example:
        >>> floor_ratio(torch.tensor([0.05, 0.1, 0.5])).tolist()
        [0.0, 0.10000000149011612, 0.5]
    """
    cfg = get_config(config)
    return torch.where(ratio < cfg.min_block_ratio, torch.zeros_like(ratio), ratio)


def block_pool(
    error: torch.Tensor,
    config: QualityConfig | None = None,
    smooth: bool = False,
) -> torch.Tensor:
    """Block error ratios with the floor of docs/method.md, section 4.

    Hard: ratios below ``min_block_ratio`` become 0. Smooth: ratio * sigmoid((ratio -
    min_block_ratio) / tau_b), differentiable.

    Args:
        error: (B, 1, H, W) error image in [0, 1], H and W multiples of the block size.
        config: block size, floor and temperature; the defaults when None.
        smooth: the sigmoid floor instead of the hard one.

    Returns:
        (B, 1, H / b, W / b) block ratios: 0 or in [min_block_ratio, 1] on the hard path.

    Example:
        >>> e = torch.zeros(1, 1, 8, 16)
        >>> e[..., :4, :8] = 1  # 32 of 64 pixels in the first block, none in the second
        >>> block_pool(e).squeeze().tolist()
        [0.5, 0.0]
    """
    cfg = get_config(config)
    area = cfg.block_size * cfg.block_size
    ratio = block_counts(error, cfg.block_size) / area
    if smooth:
        return ratio * torch.sigmoid((ratio - cfg.min_block_ratio) / cfg.tau_b)
    return floor_ratio(ratio, cfg)
