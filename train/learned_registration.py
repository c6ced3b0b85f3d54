"""The registration-quality metric as an auxiliary loss in learned registration, end to end.

A small HomographyNet-style network (two stacked grey patches in, four corner offsets out) is
trained *unsupervised*: the predicted homography warps patch A onto patch B with
``kornia.geometry.warp_perspective`` and a loss compares the two. Arms, same seed, same data,
same number of steps:

* ``l1``                    photometric L1 alone;
* ``l1_quality``            L1 + lambda * ``RegistrationQualityLoss`` (after an L1-only warm-up);
* ``l1_quality_distorted``  the same on pairs whose two patches carry the same radial lens
                            distortion (SPEC 6), which no homography can explain.

Training pairs are drawn on the fly from the embedded scenes (random 128 x 128 crops, corner
perturbations up to rho = 8 px, photometric changes such as a moving underwater light: gain,
offset, gamma, a brightness ramp across the patch, noise). Every pair is generated from its
own seed, so the data do not depend on the arm, on the batch a pair lands in, or on resumes.
The held-out pairs come from another seed *and* another region of the scenes (the bottom rows).

Usage (one command, from the repository root)::

    python train/learned_registration.py --config configs/learned_registration.toml \\
        --out results/learned_registration [--device cpu|cuda] [--arms l1,l1_quality] \\
        [--steps N] [--resume] [--set train.batch_size=8 ...]

Writes ``results.json`` (arm -> mean/median corner error, share under 1 px), ``results.md``,
``curves.png`` (when matplotlib is present) and ``checkpoints/<arm>.pt`` under ``--out``.
Checkpoints are written atomically every ``train.checkpoint_every`` steps and load with
``torch.load(..., weights_only=True)``; ``--resume`` continues each arm from its checkpoint and
reaches the same parameters as an uninterrupted run.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import tomllib
import torch
import torch.nn.functional as F
from kornia.geometry.transform import get_perspective_transform, warp_perspective
from torch import nn

try:  # tqdm is a dependency of the package, but keep the script usable without it
    from tqdm.auto import tqdm
except ImportError:  # pragma: no cover
    tqdm = None

from lensdist_torch import QualityConfig, RegistrationQualityLoss, load_scene

try:  # the package's SPEC 6 grid, when this version of the package has it
    from lensdist_torch.geometry.distortion import distortion_grid as _package_distortion_grid
except ImportError:  # pragma: no cover
    _package_distortion_grid = None

ARM_NAMES = ("l1", "l1_quality", "l1_quality_distorted")

# ----------------------------------------------------------------------------- configuration

DEFAULTS: dict[str, dict[str, Any]] = {
    "data": {
        "scenes": ["gravel", "grass"],
        "patch": 128,  # side of the patches (a multiple of the metric's block size, 8)
        "rho": 8.0,  # corner perturbation: each coordinate uniform in [-rho, rho] px
        "eval_rows": 160,  # the bottom eval_rows rows of every scene are held out for evaluation
        "photometric": 1.0,  # strength of the photometric changes (0 = none)
        "gain": 0.35,  # contrast gain in [1 - gain, 1 + gain]
        "offset": 0.12,  # brightness offset in [-offset, offset]
        "gamma": 1.6,  # gamma log-uniform in [1 / gamma, gamma]
        "ramp": 0.6,  # brightness ramp across the patch (moving light): factor 1 +- ramp / 2
        "noise": 0.03,  # Gaussian noise sigma in [0, noise]
        "k2_max": 3.0e-6,  # radial distortion of the distorted arm, in patch pixels (SPEC 6):
        "k4_max": 3.0e-10,  # k2 in ]0, k2_max], k4 in ]0, k4_max]: up to ~4 px at the corners
    },
    "model": {"kind": "correlation", "width": 16, "hidden": 256, "batch_norm": True},
    "train": {
        "seed": 0,
        "steps": 800,
        "batch_size": 16,
        "lr": 2e-3,
        "lr_final": 1e-4,  # cosine decay from lr to lr_final
        "weight_decay": 0.0,
        "checkpoint_every": 100,
        "threads": 2,
        "log_every": 10,
        "l1_levels": 4,  # pyramid levels of the photometric L1 (1 = full resolution only)
    },
    "eval": {"seed": 12345, "n_pairs": 256, "batch_size": 64},
    "arms": {
        "l1": {"lambda_quality": 0.0},
        "l1_quality": {"lambda_quality": 0.2, "quality_start": 0.25, "quality_ramp": 0.1},
        "l1_quality_distorted": {
            "lambda_quality": 0.2,
            "quality_start": 0.25,
            "quality_ramp": 0.1,
            "distorted": True,
        },
    },
}

ARM_DEFAULTS: dict[str, Any] = {
    "lambda_quality": 0.0,  # weight of the quality loss
    "quality_start": 0.0,  # fraction of the steps trained on L1 alone before the quality loss
    "quality_ramp": 0.0,  # fraction of the steps over which lambda ramps linearly from 0
    "tau_scale_start": 1.0,  # temperature scale of the metric when the quality loss starts ...
    "tau_scale_end": 1.0,  # ... annealed geometrically to this at the last step
    "l1_weight": 1.0,  # weight of the L1 loss
    "distorted": False,  # both patches carry the same radial lens distortion
}


def _merge(base: dict, over: dict, path: str = "") -> dict:
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value, f"{path}{key}.")
        else:
            out[key] = copy.deepcopy(value)
    return out


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def load_train_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> dict:
    """The training configuration: DEFAULTS <- the TOML file <- ``overrides``.

    ``overrides`` maps dotted keys (``"train.steps"``, ``"arms.l1_quality.lambda_quality"``) to
    values. Unknown sections or keys are an error, as in the package's configs.
    """
    cfg = copy.deepcopy(DEFAULTS)
    if path is not None:
        with open(path, "rb") as f:
            data = tomllib.load(f)
        if "arms" in data:  # the file's arms replace the default arms
            cfg["arms"] = {}
        cfg = _merge(cfg, data)
    for dotted, value in (overrides or {}).items():
        node = cfg
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    unknown = set(cfg) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"unknown config section(s) {sorted(unknown)}")
    for section in ("data", "model", "train", "eval"):
        bad = set(cfg[section]) - set(DEFAULTS[section])
        if bad:
            raise ValueError(f"unknown key(s) {sorted(bad)} in [{section}]")
    for name, arm in cfg["arms"].items():
        bad = set(arm) - set(ARM_DEFAULTS)
        if bad:
            raise ValueError(f"unknown key(s) {sorted(bad)} in [arms.{name}]")
        cfg["arms"][name] = {**ARM_DEFAULTS, **arm}
    if cfg["data"]["patch"] % 8:
        raise ValueError("data.patch must be a multiple of 8 (the metric's block size)")
    return cfg


# ----------------------------------------------------------------------------- data


def patch_corners(patch: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(4, 2) pixel-centre corners (x, y) of a patch, clockwise from the top left."""
    p = float(patch - 1)
    return torch.tensor([[0.0, 0.0], [p, 0.0], [p, p], [0.0, p]], device=device, dtype=dtype)


def radial_distortion_grid(patch: int, k2: torch.Tensor, k4: torch.Tensor) -> torch.Tensor:
    """Ideal points p(p_d) for every pixel p_d of a distorted patch (SPEC 6): (B, P, P, 2).

    p = p0 + (1 + k2 r^2 + k4 r^4) (p_d - p0), r = ||p_d - p0||, p0 the patch centre; the
    distorted patch is the backward warp I_d(p_d) = I(p(p_d)) (one grid_sample). Uses
    ``lensdist_torch.distortion.distortion_grid`` when present (the same formula).
    """
    if _package_distortion_grid is not None:
        return _package_distortion_grid(k2, k4, patch, patch, dtype=k2.dtype)
    ys, xs = torch.meshgrid(torch.arange(patch, dtype=k2.dtype), torch.arange(patch, dtype=k2.dtype), indexing="ij")
    c = (patch - 1) / 2.0
    dx, dy = xs - c, ys - c
    r2 = dx * dx + dy * dy
    f = 1.0 + k2.view(-1, 1, 1) * r2 + k4.view(-1, 1, 1) * r2 * r2
    return torch.stack([c + f * dx, c + f * dy], dim=-1)


def max_distortion_offset(patch: int, k2: float, k4: float) -> float:
    """Delta_max = k2 r^3 + k4 r^5 at the patch corners (SPEC 6)."""
    r = (patch - 1) / 2.0 * math.sqrt(2.0)
    return k2 * r**3 + k4 * r**5


def _photometric(img: torch.Tensor, gen: torch.Generator, d: dict) -> torch.Tensor:
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


def make_pairs(
    scenes: list[torch.Tensor], seeds: list[int], d: dict, distorted: bool, held_out: bool
) -> dict[str, torch.Tensor]:
    """Pairs (A, B) with the ground-truth corner offsets; one generator per pair.

    B's corner i shows the scene point at A's corner i + delta_i (delta: (N, 4, 2), px), i.e. the
    homography from B's to A's pixel coordinates maps the corners onto corners + delta.
    """
    patch, rho = int(d["patch"]), float(d["rho"])
    m = math.ceil(rho) + 1  # margin around the crop: B stays inside the big crop
    big = patch + 2 * m
    crops, deltas, k2s, k4s = [], [], [], []
    gens = []
    for seed in seeds:
        gen = torch.Generator().manual_seed(int(seed))
        scene = scenes[int(torch.randint(len(scenes), (1,), generator=gen))]
        h, w = scene.shape[-2:]
        y_lo, y_hi = (h - int(d["eval_rows"]), h - big) if held_out else (0, h - int(d["eval_rows"]) - big)
        if y_hi < y_lo:
            raise ValueError("scene too small for data.patch, data.rho and data.eval_rows")
        y0 = int(torch.randint(y_lo, y_hi + 1, (1,), generator=gen))
        x0 = int(torch.randint(0, w - big + 1, (1,), generator=gen))
        crops.append(scene[0, :, y0 : y0 + big, x0 : x0 + big])
        deltas.append((torch.rand(4, 2, generator=gen) * 2 - 1) * rho)
        u = torch.rand(2, generator=gen)
        # ]0, max]: 1 - u is in ]0, 1]
        k2s.append(float(d["k2_max"]) * (1 - u[0]))
        k4s.append(float(d["k4_max"]) * (1 - u[1]))
        gens.append(gen)
    crops_t = torch.stack(crops)  # (N, 1, big, big)
    delta = torch.stack(deltas)  # (N, 4, 2)
    n = len(seeds)
    corners = patch_corners(patch).expand(n, 4, 2)
    h_b = get_perspective_transform(corners, corners + m + delta)  # B patch -> big crop coords
    if distorted:
        q = radial_distortion_grid(patch, torch.stack(k2s), torch.stack(k4s))  # (N, P, P, 2)
    else:
        ys, xs = torch.meshgrid(torch.arange(patch, dtype=torch.float32), torch.arange(patch, dtype=torch.float32), indexing="ij")
        q = torch.stack([xs, ys], dim=-1).expand(n, patch, patch, 2)
    src_a = q + m
    qh = torch.cat([q, torch.ones_like(q[..., :1])], dim=-1).reshape(n, -1, 3)
    src_b = qh @ h_b.transpose(1, 2)
    src_b = (src_b[..., :2] / src_b[..., 2:]).reshape(n, patch, patch, 2)
    grid = torch.cat([src_a, src_b]) / (big - 1) * 2 - 1
    imgs = F.grid_sample(torch.cat([crops_t, crops_t]), grid, mode="bilinear", padding_mode="border", align_corners=True)
    a, b = imgs[:n], imgs[n:]
    a = torch.stack([_photometric(a[i], gens[i], d) for i in range(n)])
    b = torch.stack([_photometric(b[i], gens[i], d) for i in range(n)])
    return {"a": a, "b": b, "delta": delta}


def train_seeds(cfg: dict, step: int) -> list[int]:
    """Seeds of the pairs of a training step: unique per (seed, step, index), arm-independent."""
    bs, base = int(cfg["train"]["batch_size"]), int(cfg["train"]["seed"])
    return [base * 1_000_003 + 7919 + step * bs + i for i in range(bs)]


def eval_seeds(cfg: dict) -> list[int]:
    base = int(cfg["eval"]["seed"])
    return [base * 1_000_003 + 104_729 + i for i in range(int(cfg["eval"]["n_pairs"]))]


# ----------------------------------------------------------------------------- model


def _offset_head(in_features: int, hidden: int) -> nn.Sequential:
    """Flatten -> hidden -> 8 corner offsets; the last layer starts at zero (identity)."""
    head = nn.Sequential(nn.Flatten(), nn.Linear(in_features, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 8))
    nn.init.zeros_(head[-1].weight)
    nn.init.zeros_(head[-1].bias)
    return head


def _standardise(x: torch.Tensor) -> torch.Tensor:
    """Each (patch, channel) to zero mean and unit variance (variance floored)."""
    mu = x.mean(dim=(2, 3), keepdim=True)
    return (x - mu) / x.std(dim=(2, 3), keepdim=True).clamp_min(1e-3)


def _bounded(raw: torch.Tensor, rho: float) -> torch.Tensor:
    """(B, 8) -> (B, 4, 2) offsets squashed into +-1.5 rho: a runaway prediction cannot push A
    out of the frame (where the masked losses would be trivially small)."""
    return 1.5 * rho * torch.tanh(raw.view(-1, 4, 2) / 1.5)


class HomographyNet(nn.Module):
    """Two stacked grey patches (B, 2, P, P) -> four corner offsets (B, 4, 2) in px.

    A small VGG-like regressor in the style of HomographyNet (DeTone et al. 2016). Each patch is
    normalised to zero mean and unit variance first; the last layer starts at zero, so the
    untrained network predicts the identity. The offsets are squashed into [-1.5 rho, 1.5 rho].
    """

    def __init__(self, patch: int = 128, rho: float = 16.0, width: int = 16, hidden: int = 256, norm: bool = True) -> None:
        super().__init__()
        w = width
        chans = [w, 2 * w, 4 * w, 4 * w, 8 * w]  # five stride-2 convolutions: P -> P / 32
        layers: list[nn.Module] = []
        cin = 2
        for cout in chans:
            layers += [nn.Conv2d(cin, cout, 3, stride=2, padding=1, bias=not norm)]
            layers += [nn.BatchNorm2d(cout)] if norm else []
            layers += [nn.ReLU(inplace=True)]
            cin = cout
        self.features = nn.Sequential(*layers)
        self.head = _offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = rho

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        x = _standardise(torch.cat([a, b], dim=1))
        return _bounded(self.head(self.features(x)), self.rho)


class CorrelationHomographyNet(nn.Module):
    """Same input and output as :class:`HomographyNet`, with a correlation front end.

    A shared (siamese) encoder maps each normalised patch to unit feature vectors at 1/8
    resolution; their local correlation over displacements of up to ``ceil(1.5 rho / 8)``
    feature pixels is a cost volume that a small CNN regresses onto the four corner offsets. Reading
    the displacement from a cost volume is far easier to learn than from stacked patches, which
    is what makes a CPU budget of a thousand steps enough.
    """

    def __init__(self, patch: int = 128, rho: float = 16.0, width: int = 16, hidden: int = 256, norm: bool = True) -> None:
        super().__init__()

        def block(cin, cout, stride):
            return [nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=not norm)] + (
                [nn.BatchNorm2d(cout)] if norm else []
            ) + [nn.ReLU(inplace=True)]

        w = width
        self.encoder = nn.Sequential(
            *block(1, w, 2), *block(w, 2 * w, 2), *block(2 * w, 2 * w, 2), nn.Conv2d(2 * w, 2 * w, 3, padding=1)
        )
        self.radius = math.ceil(1.5 * rho / 8)  # feature pixels are 8 px
        n_disp = (2 * self.radius + 1) ** 2
        self.regressor = nn.Sequential(*block(n_disp, 4 * w, 1), *block(4 * w, 4 * w, 2), *block(4 * w, 8 * w, 2))
        self.head = _offset_head(8 * w * (patch // 32) ** 2, hidden)
        self.rho = rho

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        f = F.normalize(self.encoder(_standardise(torch.cat([a, b], dim=0))), dim=1)
        fa, fb = f[: a.shape[0]], f[a.shape[0] :]
        n, c, h, w = fa.shape
        k = 2 * self.radius + 1
        windows = F.unfold(fb, k, padding=self.radius).view(n, c, k * k, h * w)
        cost = (fa.view(n, c, 1, h * w) * windows).sum(1).view(n, k * k, h, w)
        return _bounded(self.head(self.regressor(cost)), self.rho)


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


def corner_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Mean Euclidean corner error per pair, px: (N,)."""
    return (pred - gt).norm(dim=-1).mean(dim=-1)


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
    """
    err = loss_fn(warped.clamp(0, 1), b, valid)  # reduction="none": (B, 1, H/8, W/8)
    bs = loss_fn.config.block_size
    vb = F.avg_pool2d(valid, bs, bs)
    return err.sum() / vb.sum().clamp_min(1.0)


# ----------------------------------------------------------------------------- schedule


def arm_schedule(arm: dict, step: int, steps: int) -> tuple[float, float]:
    """(lambda, temperature scale) of the quality loss at ``step``."""
    lam = float(arm["lambda_quality"])
    if lam == 0.0:
        return 0.0, 1.0
    start = float(arm["quality_start"]) * steps
    ramp = float(arm["quality_ramp"]) * steps
    if step < start:
        return 0.0, 1.0
    w = 1.0 if ramp <= 0 else min(1.0, (step - start + 1) / ramp)
    frac = (step - start) / max(1.0, steps - 1 - start)
    t0, t1 = float(arm["tau_scale_start"]), float(arm["tau_scale_end"])
    return lam * w, t0 * (t1 / t0) ** min(1.0, max(0.0, frac))


def learning_rate(cfg: dict, step: int, steps: int) -> float:
    lr0, lr1 = float(cfg["train"]["lr"]), float(cfg["train"]["lr_final"])
    return lr1 + 0.5 * (lr0 - lr1) * (1 + math.cos(math.pi * step / max(1, steps)))


# ----------------------------------------------------------------------------- training


def _atomic_save(obj: Any, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def _comparable(cfg: dict) -> dict:
    """The config without the keys that do not change the training (threads, logging)."""
    out = json.loads(json.dumps(cfg))
    for key in ("threads", "log_every", "checkpoint_every"):
        out["train"].pop(key, None)
    return out


def build(cfg: dict, device: str = "cpu"):
    torch.manual_seed(int(cfg["train"]["seed"]))
    d, mcfg = cfg["data"], cfg["model"]
    kinds = {"correlation": CorrelationHomographyNet, "stacked": HomographyNet}
    if mcfg["kind"] not in kinds:
        raise ValueError(f"model.kind must be one of {sorted(kinds)}, got {mcfg['kind']!r}")
    model = kinds[mcfg["kind"]](int(d["patch"]), float(d["rho"]), int(mcfg["width"]), int(mcfg["hidden"]), bool(mcfg["batch_norm"])).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=float(cfg["train"]["lr"]), weight_decay=float(cfg["train"]["weight_decay"]))
    return model, opt


def train_step(model, opt, batch, arm: dict, step: int, steps: int, cfg: dict, base_q: QualityConfig):
    """One optimisation step; returns a dict of floats (losses, lambda, corner error)."""
    lam, tscale = arm_schedule(arm, step, steps)
    for g in opt.param_groups:
        g["lr"] = learning_rate(cfg, step, steps)
    model.train()
    pred = model(batch["a"], batch["b"])
    warped, valid = warp_a_to_b(batch["a"], pred)
    l1 = l1_loss(warped, batch["b"], valid, int(cfg["train"]["l1_levels"]))
    loss = float(arm["l1_weight"]) * l1
    q = torch.zeros(())
    if lam > 0:
        qcfg = base_q.with_temperature_scale(tscale) if tscale != 1.0 else base_q
        q = quality_loss(RegistrationQualityLoss(qcfg, reduction="none"), warped, batch["b"], valid)
        loss = loss + lam * q
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    with torch.no_grad():
        ce = corner_error(pred, batch["delta"]).mean()
    return {"loss": float(loss.detach()), "l1": float(l1.detach()), "quality": float(q.detach()), "lambda": lam, "tau_scale": tscale, "corner_error": float(ce)}


def train_arm(
    cfg: dict,
    arm_name: str,
    out: Path,
    device: str = "cpu",
    resume: bool = False,
    stop_after: int | None = None,
    progress: bool = True,
    scenes: list[torch.Tensor] | None = None,
):
    """Train one arm; returns (model, history, training wall seconds summed over resumes).

    ``stop_after`` simulates a crash after that many steps (no checkpoint is written then).
    """
    arm = cfg["arms"][arm_name]
    steps = int(cfg["train"]["steps"])
    ckpt_every = int(cfg["train"]["checkpoint_every"])
    ckpt_path = out / "checkpoints" / f"{arm_name}.pt"
    scenes = scenes if scenes is not None else [load_scene(s) for s in cfg["data"]["scenes"]]
    model, opt = build(cfg, device)
    start, history, wall_before = 0, [], 0.0
    if resume and ckpt_path.is_file():
        state = torch.load(ckpt_path, map_location=device, weights_only=True)
        if _comparable(state["config"]) != _comparable(cfg):
            raise ValueError(f"{ckpt_path} was written with another config; remove it or drop --resume")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        torch.set_rng_state(state["rng"])
        start, history = int(state["step"]), list(state["history"])
        wall_before = float(state.get("wall_s", 0.0))
    base_q = QualityConfig()
    bar = None
    if progress and tqdm is not None:
        bar = tqdm(total=steps, initial=start, desc=arm_name, dynamic_ncols=True, leave=True)
    t0 = time.perf_counter()
    for step in range(start, steps):
        batch = make_pairs(scenes, train_seeds(cfg, step), cfg["data"], bool(arm["distorted"]), held_out=False)
        batch = {k: v.to(device) for k, v in batch.items()}
        rec = train_step(model, opt, batch, arm, step, steps, cfg, base_q)
        rec["step"] = step
        history.append(rec)
        done = step + 1
        if bar is not None:
            bar.update(1)
            if done % int(cfg["train"]["log_every"]) == 0 or done == steps:
                recent = history[-int(cfg["train"]["log_every"]) :]
                bar.set_postfix(
                    l1=f"{sum(r['l1'] for r in recent) / len(recent):.4f}",
                    q=f"{sum(r['quality'] for r in recent) / len(recent):.3f}",
                    ce=f"{sum(r['corner_error'] for r in recent) / len(recent):.2f}px",
                )
        if done % ckpt_every == 0 or done == steps:
            _atomic_save(
                {
                    "model": model.state_dict(),
                    "optimizer": opt.state_dict(),
                    "step": done,
                    "rng": torch.get_rng_state(),
                    "history": history,
                    "config": json.loads(json.dumps(cfg)),
                    "arm": arm_name,
                    "wall_s": wall_before + time.perf_counter() - t0,
                },
                ckpt_path,
            )
        if stop_after is not None and done >= stop_after:
            break
    if bar is not None:
        bar.close()
    return model, history, wall_before + time.perf_counter() - t0


@torch.no_grad()
def evaluate(model, cfg: dict, distorted: bool, device: str = "cpu", scenes=None) -> dict[str, float]:
    """Corner errors on the held-out pairs (another seed, the bottom rows of the scenes)."""
    scenes = scenes if scenes is not None else [load_scene(s) for s in cfg["data"]["scenes"]]
    model.eval()
    seeds = eval_seeds(cfg)
    bs = int(cfg["eval"]["batch_size"])
    errs, ident = [], []
    for i in range(0, len(seeds), bs):
        batch = make_pairs(scenes, seeds[i : i + bs], cfg["data"], distorted, held_out=True)
        pred = model(batch["a"].to(device), batch["b"].to(device)).cpu()
        errs.append(corner_error(pred, batch["delta"]))
        ident.append(corner_error(torch.zeros_like(batch["delta"]), batch["delta"]))
    e, e0 = torch.cat(errs), torch.cat(ident)
    return {
        "mean_corner_error": float(e.mean()),
        "median_corner_error": float(e.median()),
        "share_under_1px": float((e < 1.0).float().mean()),
        "identity_mean_corner_error": float(e0.mean()),
        "n_pairs": int(e.numel()),
    }


# ----------------------------------------------------------------------------- reporting


def write_markdown(results: dict, cfg: dict, path: Path, wall: float | None = None) -> str:
    lines = [
        "| arm | lambda | schedule | mean corner error (px) | median (px) | share < 1 px |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        arm = cfg["arms"][name]
        lam = arm["lambda_quality"]
        if lam:
            sched = f"L1 only for {arm['quality_start']:.0%}, ramp {arm['quality_ramp']:.0%}"
            if arm["tau_scale_start"] != 1.0 or arm["tau_scale_end"] != 1.0:
                sched += f", tau x{arm['tau_scale_start']:g} -> x{arm['tau_scale_end']:g}"
        else:
            sched = "-"
        if arm["distorted"]:
            sched += " (lens distortion)"
        lines.append(
            f"| `{name}` | {lam:g} | {sched} | {r['mean_corner_error']:.2f} | "
            f"{r['median_corner_error']:.2f} | {r['share_under_1px']:.1%} |"
        )
    first = next(iter(results.values()))
    d, t = cfg["data"], cfg["train"]
    lines += [
        "",
        f"{first['n_pairs']} held-out pairs; identity (no registration) mean corner error "
        f"{first['identity_mean_corner_error']:.2f} px. {t['steps']} steps of {t['batch_size']} pairs, "
        f"{d['patch']} x {d['patch']} patches, corners perturbed up to {d['rho']:g} px, seed {t['seed']}."
        + (f" Wall time of this invocation {wall / 60:.1f} min." if wall is not None else ""),
    ]
    text = "\n".join(lines) + "\n"
    path.write_text(text)
    return text


def plot_curves(histories: dict[str, list[dict]], path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False

    def smooth(v, k=25):
        out, acc = [], 0.0
        for i, x in enumerate(v):
            acc += x
            if i >= k:
                acc -= v[i - k]
            out.append(acc / min(i + 1, k))
        return out

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for name, hist in histories.items():
        steps = [r["step"] for r in hist]
        axes[0].plot(steps, smooth([r["corner_error"] for r in hist]), label=name)
        axes[1].plot(steps, smooth([r["l1"] for r in hist]), label=name)
        axes[2].plot(steps, smooth([r["quality"] for r in hist]), label=name)
    axes[0].set(title="training corner error (px)", xlabel="step", yscale="log")
    axes[1].set(title="photometric L1", xlabel="step")
    axes[2].set(title="quality loss (when on)", xlabel="step")
    for ax in axes:
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


# ----------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/learned_registration.toml")
    ap.add_argument("--out", default="results/learned_registration")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--arms", default=None, help="comma-separated arms (default: all in the config)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--resume", action="store_true", help="continue each arm from its checkpoint")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.batch_size=8")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)

    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        overrides[key.strip()] = _parse_value(value.strip())
    if args.steps is not None:
        overrides["train.steps"] = args.steps
    cfg = load_train_config(args.config if args.config else None, overrides)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device available")
    torch.set_num_threads(int(cfg["train"]["threads"]))
    arms = args.arms.split(",") if args.arms else list(cfg["arms"])
    for a in arms:
        if a not in cfg["arms"]:
            raise SystemExit(f"unknown arm {a!r}; the config has {list(cfg['arms'])}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenes = [load_scene(s) for s in cfg["data"]["scenes"]]

    results, histories, t_start = {}, {}, time.perf_counter()
    for name in arms:
        model, hist, wall = train_arm(cfg, name, out, args.device, args.resume, progress=not args.no_progress, scenes=scenes)
        r = evaluate(model, cfg, bool(cfg["arms"][name]["distorted"]), args.device, scenes)
        r["train_wall_s"] = round(wall, 1)
        r["steps"] = int(cfg["train"]["steps"])
        results[name], histories[name] = r, hist
        print(f"{name}: mean {r['mean_corner_error']:.3f} px, median {r['median_corner_error']:.3f} px, "
              f"<1 px {r['share_under_1px']:.1%} (identity {r['identity_mean_corner_error']:.2f} px)", flush=True)
    wall = time.perf_counter() - t_start
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "config_used.json").write_text(json.dumps(cfg, indent=2) + "\n")
    print(write_markdown(results, cfg, out / "results.md", wall))
    if plot_curves(histories, out / "curves.png"):
        print(f"curves: {out / 'curves.png'}")
    print(f"total wall time {wall:.0f} s")
    return results


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    main()
