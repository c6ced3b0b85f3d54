"""Image gradients by central differences, pyramids of 2 x 2 means, binomial smoothing.

Shared by registration and self-calibration (docs/method.md, sections 6 and 7). They work on
the last two dimensions; a level-l pixel x_l of the pyramid lies at full-resolution
x = 2^l x_l + (2^l - 1) / 2 (see :mod:`lensdist_torch.geometry.frame`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["binomial_blur", "central_differences", "mean_pool_2x2", "mean_pyramid"]


def central_differences(img: torch.Tensor, stride: int = 1, out: torch.Tensor | None = None) -> torch.Tensor:
    """Image gradients (d/dx, d/dy) in pixels at every ``stride``-th row and column.

    (I(x + 1) - I(x - 1)) / 2 with a replicated border (so (I(1) - I(0)) / 2 at the first pixel):
    (B, h, w) -> (B, h', 2, w'), h' = ceil(h / stride), w' = ceil(w / stride); written into
    ``out`` when given (a work buffer of that shape), img's dtype.
    """
    p = F.pad(img[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    h, w = len(range(0, img.shape[1], stride)), len(range(0, img.shape[2], stride))
    out = img.new_empty(img.shape[0], h, 2, w) if out is None else out
    c = p[:, 1:-1:stride]
    torch.sub(c[:, :, 2::stride][..., :w], c[:, :, 0:-2:stride][..., :w], out=out[:, :, 0])
    torch.sub(p[:, 2::stride, 1:-1:stride][:, :h], p[:, 0:-2:stride, 1:-1:stride][:, :h], out=out[:, :, 1])
    return out.mul_(0.5)


def mean_pool_2x2(img: torch.Tensor) -> torch.Tensor:
    """2 x 2 means of the last two dimensions (an odd last row or column is dropped)."""
    p = img[..., : img.shape[-2] // 2 * 2, : img.shape[-1] // 2 * 2]
    return (p[..., ::2, ::2] + p[..., 1::2, ::2]).add_(p[..., ::2, 1::2]).add_(p[..., 1::2, 1::2]).mul_(0.25)


def mean_pyramid(img: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """[img, mean_pool_2x2(img), mean_pool_2x2(mean_pool_2x2(img)), ...], ``levels`` images in all, finest first."""
    pyr = [img]
    for _ in range(levels - 1):
        pyr.append(mean_pool_2x2(pyr[-1]))
    return pyr


def binomial_blur(img: torch.Tensor, out: torch.Tensor, work: torch.Tensor | None = None) -> torch.Tensor:
    """Separable [1, 4, 6, 4, 1] / 16 smoothing (sigma = 1 px), replicated border.

    (b, h, w) -> out (b, h, w), h and w >= 5; ``work`` is an optional (b, h, w + 4) buffer
    (a fresh one otherwise). Returns ``out``.
    """
    b, h, w = img.shape
    p = img.new_empty(b, h, w + 4) if work is None else work
    v = p[..., 2:-2]
    torch.add(img[:, :-4], img[:, 4:], out=v[:, 2:-2]).add_(img[:, 1:-3], alpha=4).add_(img[:, 3:-1], alpha=4)
    v[:, 2:-2].add_(img[:, 2:-2], alpha=6)
    for r in (0, 1, h - 2, h - 1):  # border rows, replicated
        t = [img[:, min(max(r + k, 0), h - 1)] for k in (-2, -1, 0, 1, 2)]
        v[:, r] = t[0] + t[4] + 4 * (t[1] + t[3]) + 6 * t[2]
    p[..., :2], p[..., -2:] = v[..., :1], v[..., -1:]
    torch.add(p[..., :-4], p[..., 4:], out=out).add_(p[..., 1:-3], alpha=4).add_(p[..., 3:-1], alpha=4)
    return out.add_(p[..., 2:-2], alpha=6).mul_(1 / 256)
