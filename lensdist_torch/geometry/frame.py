"""Coordinate frames: pixel grids, grid_sample's [-1, 1] and the centred normalised frame.

Pixel centres lie at integer positions (x to the right, y down; ``align_corners=True``). The
normalised frame of registration and self-calibration is centred and in half-diagonals,

    u = (p - p0) / R,   p0 = ((W - 1) / 2, (H - 1) / 2),   R = sqrt((W - 1)^2 + (H - 1)^2) / 2,

so the corner pixels lie at (+-(W - 1) / 2R, +-(H - 1) / 2R), |u| = 1. It is the same at every
level of a pyramid of 2 x 2 means (:func:`~lensdist_torch.geometry.pyramid.mean_pyramid`):
level-l pixel x_l lies at full-resolution x = 2^l x_l + (2^l - 1) / 2.
"""

from __future__ import annotations

import math

import torch
from kornia.geometry import create_meshgrid
from kornia.geometry.conversions import normalize_pixel_coordinates

__all__ = [
    "grid_points",
    "grid_near",
    "half_diagonal",
    "normalizer",
    "level_coordinates",
    "normalized_grid",
    "level_to_grid",
    "pixel_grid",
    "to_normalized",
    "grid_sample_matrix",
]


def half_diagonal(height: int, width: int) -> float:
    """R, the unit of the normalised frame: half the distance between opposite corner pixels."""
    return 0.5 * math.hypot(width - 1, height - 1)


def normalizer(height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """(3, 3) N with u = N p: full-resolution pixels -> the normalised frame."""
    r = half_diagonal(height, width)
    n = [[1 / r, 0, -(width - 1) / 2 / r], [0, 1 / r, -(height - 1) / 2 / r], [0, 0, 1]]
    return torch.tensor(n, dtype=dtype, device=device)


def level_coordinates(
    level: int, height: int, width: int, *, full_height: int, full_width: int, stride: int = 1, device=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalised coordinates of the pixel columns and rows of a pyramid level, float64.

    ``height`` x ``width`` is the level's size, ``full_height`` x ``full_width`` the image's
    (level 0); every ``stride``-th column and row. Returns u (w',) and v (h',).
    """
    f, scale = 2.0**level, half_diagonal(full_height, full_width)
    off = (f - 1) / 2
    axes = []
    for n, c in ((width, (full_width - 1) / 2), (height, (full_height - 1) / 2)):
        axes.append((f * torch.arange(0, n, stride, dtype=torch.float64, device=device) + off - c) / scale)
    return axes[0], axes[1]


def normalized_grid(
    level: int, height: int, width: int, *, full_height: int, full_width: int, dtype=torch.float32, device=None
) -> torch.Tensor:
    """(h, w, 2) normalised coordinates (u, v) of every pixel of a pyramid level."""
    u, v = level_coordinates(level, height, width, full_height=full_height, full_width=full_width, device=device)
    gv, gu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([gu, gv], -1).to(dtype)


def level_to_grid(level: int, height: int, width: int, *, full_height: int, full_width: int) -> tuple[float, ...]:
    """(sx, ox, sy, oy): grid_sample coordinates on a level image, x = sx u + ox, y = sy v + oy."""
    f, scale = 2.0**level, half_diagonal(full_height, full_width)
    off = (f - 1) / 2
    ax, ay = 2 / (f * max(width - 1, 1)), 2 / (f * max(height - 1, 1))
    return ax * scale, ax * ((full_width - 1) / 2 - off) - 1, ay * scale, ay * ((full_height - 1) / 2 - off) - 1


def pixel_grid(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """(H, W, 2) pixel-centre coordinates (x, y) (``kornia.geometry.create_meshgrid``)."""
    return create_meshgrid(height, width, False, device=device, dtype=dtype)[0].contiguous()


def to_normalized(points: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Pixel coordinates (..., 2) -> grid_sample's [-1, 1] (``align_corners=True``).

    ``kornia.geometry.conversions.normalize_pixel_coordinates``: x 2 / (W - 1) - 1.
    """
    return normalize_pixel_coordinates(points, height, width)


def grid_sample_matrix(height: int, width: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """(3, 3) pixel coordinates -> grid_sample's [-1, 1] (``align_corners=True``).

    A matrix to compose with homographies; a one-pixel axis maps to -1.
    """
    m = [[2 / max(width - 1, 1), 0, -1], [0, 2 / max(height - 1, 1), -1], [0, 0, 1]]
    return torch.tensor(m, dtype=dtype, device=device)


def grid_points(height: int, width: int, step: int) -> torch.Tensor:
    """Every ``step``-th pixel of a (height, width) frame as (N, 2) float64 (x, y), x fastest."""
    xs = torch.arange(0, width, step, dtype=torch.float64)
    ys = torch.arange(0, height, step, dtype=torch.float64)
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)


def grid_near(points: torch.Tensor, height: int, width: int, *, step: int, radius: float) -> torch.Tensor:
    """(N,) bool over :func:`grid_points`: the grid's pixels within ``radius`` (px) of any of ``points`` (M, 2).

    Exact, and linear in M: each point marks the grid pixels of its (2 ceil(radius / step) + 1)^2
    neighbourhood that lie within the radius (a distance matrix would be N x M).

    Example:
        >>> grid_points(4, 6, 2).tolist()
        [[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [0.0, 2.0], [2.0, 2.0], [4.0, 2.0]]
        >>> near = grid_near(torch.tensor([[0.5, 0.5]], dtype=torch.float64), 4, 6, step=2, radius=2.0)
        >>> near.tolist()  # (2, 2) is 2.12 away
        [True, True, False, True, False, False]
    """
    nx, ny = len(range(0, width, step)), len(range(0, height, step))
    k = math.ceil(radius / step)
    off = torch.arange(-k, k + 1)
    mask = torch.zeros(nx * ny, dtype=torch.bool)
    for chunk in points.split(4096):  # (4096, 2k + 1, 2k + 1) candidates at a time
        x, y = chunk[:, 0, None, None], chunk[:, 1, None, None]
        i = torch.round(x / step).long() + off[None, :, None]
        j = torch.round(y / step).long() + off[None, None, :]
        ok = ((i * step - x) ** 2 + (j * step - y) ** 2 <= radius**2) & (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        mask[(j * nx + i)[ok]] = True
    return mask
