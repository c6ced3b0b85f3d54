"""Fine-stage pairs: the residual a coarse stage leaves (0.5-3 px per corner) under strong
illumination changes, optionally with the same radial lens distortion on both patches.

Every pair is drawn from its own generator (:func:`split_seeds`), so a pair depends on neither
the arm, the batch it lands in, nor a resume. Three disjoint regions of the scenes:

* ``train``: all but the bottom ``data.held_out_rows`` rows;
* ``val``:   the bottom rows, columns < ``data.val_cols`` (lambda and lr are chosen here);
* ``test``:  the bottom rows, columns >= ``data.val_cols`` (only ever reported).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.geometry.transform import get_perspective_transform
from learnreg.data import load_scenes, patch_corners, photometric_jitter, source_points

__all__ = ["SPLITS", "load_scenes", "make_pairs", "split_seeds", "train_seeds", "vignette"]

SPLITS = ("train", "val", "test")


def _window(split: str, h: int, w: int, big: int, d: dict) -> tuple[int, int, int, int]:
    """Inclusive ranges (y_lo, y_hi, x_lo, x_hi) of a big crop's top-left corner in ``split``."""
    rows, cols = int(d["held_out_rows"]), int(d["val_cols"])
    if split == "train":
        out = (0, h - rows - big, 0, w - big)
    elif split == "val":
        out = (h - rows, h - big, 0, cols - big)
    elif split == "test":
        out = (h - rows, h - big, cols, w - big)
    else:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if out[1] < out[0] or out[3] < out[2]:
        raise ValueError(f"scene too small for the {split} region (data.patch, held_out_rows, val_cols)")
    return out


def _draw(scenes: list[torch.Tensor], seed: int, d: dict, big: int, split: str) -> dict:
    """One pair's choices, in a fixed order from its own generator: scene, crop, residual
    corner offsets (length uniform in [r_min, r_max], direction uniform), distortion. The
    generator goes on to draw the photometric changes."""
    gen = torch.Generator().manual_seed(int(seed))
    scene = scenes[int(torch.randint(len(scenes), (1,), generator=gen))]
    y_lo, y_hi, x_lo, x_hi = _window(split, *scene.shape[-2:], big, d)
    y0 = int(torch.randint(y_lo, y_hi + 1, (1,), generator=gen))
    x0 = int(torch.randint(x_lo, x_hi + 1, (1,), generator=gen))
    u = torch.rand(4, 2, generator=gen, dtype=torch.float64)
    r = float(d["r_min"]) + (float(d["r_max"]) - float(d["r_min"])) * u[:, 0]
    phi = 2 * math.pi * u[:, 1]
    delta = torch.stack([r * torch.cos(phi), r * torch.sin(phi)], dim=-1).float()
    k = torch.rand(2, generator=gen)  # 1 - k in ]0, 1]: coefficients in ]0, max]
    return {
        "crop": scene[0, :, y0 : y0 + big, x0 : x0 + big],
        "delta": delta,
        "k2": float(d["k2_max"]) * (1 - k[0]),
        "k4": float(d["k4_max"]) * (1 - k[1]),
        "gen": gen,
    }


def vignette(img: torch.Tensor, gen: torch.Generator, d: dict) -> torch.Tensor:
    """An off-centre radial fall-off 1 - v (r / r_far)^2, v uniform in [0, vignette]. (1,P,P)."""
    s = float(d["photometric"]) * float(d["vignette"])
    if s <= 0:
        return img
    u = torch.rand(3, generator=gen, dtype=torch.float64).tolist()
    v, cx, cy = s * u[0], 0.5 * u[1] - 0.25, 0.5 * u[2] - 0.25
    lin = torch.linspace(-0.5, 0.5, img.shape[-1], dtype=img.dtype)
    r2 = (lin.view(1, -1) - cx) ** 2 + (lin.view(-1, 1) - cy) ** 2
    far = (0.5 + abs(cx)) ** 2 + (0.5 + abs(cy)) ** 2  # the farthest corner
    return (img * (1.0 - v * r2 / far)).clamp(0.0, 1.0)


def _illuminate(img: torch.Tensor, gen: torch.Generator, d: dict) -> torch.Tensor:
    """learnreg's moving light (gain, offset, gamma, ramp, noise), then a vignetting."""
    return vignette(photometric_jitter(img, gen, d), gen, d)


def make_pairs(scenes: list[torch.Tensor], seeds: list[int], d: dict, distorted: bool, split: str) -> dict:
    """Pairs (A, B) with their residual corner offsets delta (N, 4, 2), px.

    As in learnreg: B's corner i shows the scene point at A's corner i + delta_i, so the
    homography from B's to A's pixels maps B's corners onto corners + delta. Distorted: both
    patches are rendered through the same radial distortion (eq. 4) about their centres.
    """
    patch = int(d["patch"])
    m = math.ceil(float(d["r_max"])) + 1
    big = patch + 2 * m
    draws = [_draw(scenes, s, d, big, split) for s in seeds]
    n = len(draws)
    crops = torch.stack([r["crop"] for r in draws])
    delta = torch.stack([r["delta"] for r in draws])
    corners = patch_corners(patch).expand(n, 4, 2)
    h_b = get_perspective_transform(corners, corners + m + delta)
    k2, k4 = (
        torch.stack([torch.as_tensor(r["k2"]) for r in draws]),
        torch.stack([torch.as_tensor(r["k4"]) for r in draws]),
    )
    q = source_points(patch, k2, k4, distorted)
    qh = torch.cat([q, torch.ones_like(q[..., :1])], dim=-1).reshape(n, -1, 3)
    src_b = qh @ h_b.transpose(1, 2)
    src_b = (src_b[..., :2] / src_b[..., 2:]).reshape(n, patch, patch, 2)
    grid = torch.cat([q + m, src_b]) / (big - 1) * 2 - 1
    imgs = F.grid_sample(torch.cat([crops, crops]), grid, mode="bilinear", padding_mode="border", align_corners=True)
    a = torch.stack([_illuminate(imgs[i], r["gen"], d) for i, r in enumerate(draws)])
    b = torch.stack([_illuminate(imgs[n + i], r["gen"], d) for i, r in enumerate(draws)])
    return {"a": a, "b": b, "delta": delta}


def train_seeds(seed: int, step: int, batch_size: int) -> list[int]:
    """Pair seeds of one training step: unique per (training seed, step, index), arm-independent."""
    return [int(seed) * 1_000_003 + 7919 + step * batch_size + i for i in range(batch_size)]


def split_seeds(base: int, n: int) -> list[int]:
    """Pair seeds of a validation or test set drawn from ``base``."""
    return [int(base) * 1_000_003 + 104_729 + i for i in range(int(n))]
