"""Training and held-out pairs, generated on the fly from the embedded scenes.

Every pair is drawn from its own seed (:func:`train_seeds`, :func:`eval_seeds`), so a pair does
not depend on the arm, on the batch it lands in, or on resumes. The held-out pairs use another
seed *and* another region of the scenes (the bottom ``data.eval_rows`` rows).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.geometry.transform import get_perspective_transform

from lensdist_torch import load_scene
from lensdist_torch.geometry.distortion import distortion_grid, pixel_grid

__all__ = ["load_scenes", "patch_corners", "source_points", "make_pairs", "train_seeds", "eval_seeds"]


def load_scenes(cfg: dict) -> list[torch.Tensor]:
    return [load_scene(s) for s in cfg["data"]["scenes"]]


def patch_corners(patch: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(4, 2) pixel-centre corners (x, y) of a patch, clockwise from the top left."""
    p = float(patch - 1)
    return torch.tensor([[0.0, 0.0], [p, 0.0], [p, p], [0.0, p]], device=device, dtype=dtype)


def source_points(patch: int, k2: torch.Tensor, k4: torch.Tensor, distorted: bool) -> torch.Tensor:
    """Where each pixel of the (N) patches samples the undistorted view: (N, P, P, 2), (x, y) px.

    Distorted: the ideal points of eq. 4 (SPEC 6) about the patch centre, so that the rendered
    patch is the backward warp I_d(p_d) = I(p(p_d)). Otherwise the pixel grid itself.
    """
    if distorted:
        return distortion_grid(k2, k4, patch, patch, dtype=k2.dtype)
    return pixel_grid(patch, patch).expand(k2.numel(), patch, patch, 2)


def photometric_jitter(img: torch.Tensor, gen: torch.Generator, d: dict) -> torch.Tensor:
    """A moving light: gain, offset, gamma, a brightness ramp across the patch, noise. (1,P,P)."""
    s = float(d["photometric"])
    if s <= 0:
        return img
    u = torch.rand(7, generator=gen, dtype=torch.float64).tolist()
    gain = 1.0 + s * d["gain"] * (2 * u[0] - 1)
    offset = s * d["offset"] * (2 * u[1] - 1)
    gamma = math.exp(s * math.log(d["gamma"]) * (2 * u[2] - 1))
    theta = 2 * math.pi * u[3]
    ramp = s * d["ramp"] * u[4]
    sigma = s * d["noise"] * u[5]
    p = img.shape[-1]
    lin = torch.linspace(-0.5, 0.5, p, dtype=img.dtype)
    ramp_map = 1.0 + ramp * (math.cos(theta) * lin.view(1, -1) + math.sin(theta) * lin.view(-1, 1))
    out = (gain * img.clamp_min(0).pow(gamma) + offset) * ramp_map
    noise = torch.randn(img.shape, generator=gen, dtype=img.dtype)
    return (out + sigma * noise).clamp(0.0, 1.0)


def _draw(scenes: list[torch.Tensor], seed: int, d: dict, big: int, held_out: bool) -> dict:
    """The random choices of one pair, in a fixed order from its own generator: the scene, the
    crop (big x big), the corner offsets, the distortion coefficients. The generator goes on
    to draw the photometric changes."""
    gen = torch.Generator().manual_seed(int(seed))
    scene = scenes[int(torch.randint(len(scenes), (1,), generator=gen))]
    h, w = scene.shape[-2:]
    rows = int(d["eval_rows"])
    y_lo, y_hi = (h - rows, h - big) if held_out else (0, h - rows - big)
    if y_hi < y_lo:
        raise ValueError("scene too small for data.patch, data.rho and data.eval_rows")
    y0 = int(torch.randint(y_lo, y_hi + 1, (1,), generator=gen))
    x0 = int(torch.randint(0, w - big + 1, (1,), generator=gen))
    delta = (torch.rand(4, 2, generator=gen) * 2 - 1) * float(d["rho"])
    u = torch.rand(2, generator=gen)  # 1 - u is in ]0, 1]: the coefficients are in ]0, max]
    return {
        "crop": scene[0, :, y0 : y0 + big, x0 : x0 + big],
        "delta": delta,
        "k2": float(d["k2_max"]) * (1 - u[0]),
        "k4": float(d["k4_max"]) * (1 - u[1]),
        "gen": gen,
    }


def make_pairs(
    scenes: list[torch.Tensor], seeds: list[int], d: dict, distorted: bool, held_out: bool
) -> dict[str, torch.Tensor]:
    """Pairs (A, B) with the ground-truth corner offsets; one generator per pair.

    B's corner i shows the scene point at A's corner i + delta_i (delta: (N, 4, 2), px), i.e. the
    homography from B's to A's pixel coordinates maps the corners onto corners + delta.
    """
    patch = int(d["patch"])
    m = math.ceil(float(d["rho"])) + 1  # margin around the crop: B stays inside the big crop
    big = patch + 2 * m
    draws = [_draw(scenes, seed, d, big, held_out) for seed in seeds]
    n = len(draws)
    crops = torch.stack([r["crop"] for r in draws])  # (N, 1, big, big)
    delta = torch.stack([r["delta"] for r in draws])  # (N, 4, 2)
    corners = patch_corners(patch).expand(n, 4, 2)
    h_b = get_perspective_transform(corners, corners + m + delta)  # B patch -> big crop coords
    q = source_points(patch, torch.stack([r["k2"] for r in draws]), torch.stack([r["k4"] for r in draws]), distorted)
    qh = torch.cat([q, torch.ones_like(q[..., :1])], dim=-1).reshape(n, -1, 3)
    src_b = qh @ h_b.transpose(1, 2)
    src_b = (src_b[..., :2] / src_b[..., 2:]).reshape(n, patch, patch, 2)
    grid = torch.cat([q + m, src_b]) / (big - 1) * 2 - 1
    imgs = F.grid_sample(torch.cat([crops, crops]), grid, mode="bilinear", padding_mode="border", align_corners=True)
    a = torch.stack([photometric_jitter(imgs[i], r["gen"], d) for i, r in enumerate(draws)])
    b = torch.stack([photometric_jitter(imgs[n + i], r["gen"], d) for i, r in enumerate(draws)])
    return {"a": a, "b": b, "delta": delta}


def train_seeds(cfg: dict, step: int) -> list[int]:
    """Seeds of the pairs of a training step: unique per (seed, step, index), arm-independent."""
    bs, base = int(cfg["train"]["batch_size"]), int(cfg["train"]["seed"])
    return [base * 1_000_003 + 7919 + step * bs + i for i in range(bs)]


def eval_seeds(cfg: dict) -> list[int]:
    """Seeds of the held-out pairs, from ``eval.seed``."""
    base = int(cfg["eval"]["seed"])
    return [base * 1_000_003 + 104_729 + i for i in range(int(cfg["eval"]["n_pairs"]))]
