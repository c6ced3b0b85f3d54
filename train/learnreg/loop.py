"""Training: the schedule of an arm, one optimisation step, checkpoints, and an arm end to end.

Checkpoints go through ``lensdist_torch.core.storage`` (atomic and fsynced, with a kind and a
format version, read with ``torch.load(weights_only=True)``); each carries the config it was
written with, and ``--resume`` refuses one written under another config.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch
from tqdm.auto import tqdm

from lensdist_torch import QualityConfig, RegistrationQualityLoss
from lensdist_torch.core import CheckpointError, load_versioned, save_versioned

from .config import comparable
from .data import load_scenes, make_pairs, train_seeds
from .losses import corner_error, l1_loss, quality_loss, warp_a_to_b
from .models import build_model

__all__ = [
    "CHECKPOINT_KIND",
    "CHECKPOINT_VERSION",
    "arm_schedule",
    "learning_rate",
    "build",
    "train_step",
    "checkpoint_path",
    "restore",
    "save_checkpoint",
    "load_checkpoint",
    "train_arm",
]

CHECKPOINT_KIND = "learned_registration_arm"
CHECKPOINT_VERSION = 1


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
    """Cosine decay from ``train.lr`` at step 0 to ``train.lr_final`` at ``steps``."""
    lr0, lr1 = float(cfg["train"]["lr"]), float(cfg["train"]["lr_final"])
    return lr1 + 0.5 * (lr0 - lr1) * (1 + math.cos(math.pi * step / max(1, steps)))


def build(cfg: dict, device: str = "cpu"):
    """The network (initialised from ``train.seed``) and its Adam optimiser."""
    torch.manual_seed(int(cfg["train"]["seed"]))
    model = build_model(cfg).to(device)
    t = cfg["train"]
    opt = torch.optim.Adam(model.parameters(), lr=float(t["lr"]), weight_decay=float(t["weight_decay"]))
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
    ce = corner_error(pred, batch["delta"], batch["a"].shape[-1]).mean()
    return {
        "loss": float(loss.detach()),
        "l1": float(l1.detach()),
        "quality": float(q.detach()),
        "lambda": lam,
        "tau_scale": tscale,
        "corner_error": float(ce),
    }


def checkpoint_path(out: Path, arm_name: str) -> Path:
    return Path(out) / "checkpoints" / f"{arm_name}.pt"


def save_checkpoint(path: Path, model, opt, step: int, history: list, cfg: dict, arm_name: str, wall_s: float,
                    kind: str = CHECKPOINT_KIND, version: int = CHECKPOINT_VERSION, **extra) -> None:
    """Everything needed to continue the arm bit for bit, written atomically.

    ``kind`` / ``version`` name the file format (another training script passes its own);
    ``extra`` entries are stored beside the standard ones.
    """
    payload = {
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
        "step": step,
        "rng": torch.get_rng_state(),
        "history": history,
        "config": json.loads(json.dumps(cfg)),
        "arm": arm_name,
        "wall_s": wall_s,
        **extra,
    }
    save_versioned(path, kind, version, payload)


def load_checkpoint(path: Path, cfg: dict, arm_name: str, model, opt) -> dict:
    """Restore model, optimiser and RNG from ``path``; returns the checkpoint's payload.

    Raises CheckpointError for another kind, format version, arm or config.
    """
    state = load_versioned(
        path, kind=CHECKPOINT_KIND, version=CHECKPOINT_VERSION, what="learned-registration", map_location="cpu"
    )
    if state.get("arm") != arm_name:
        raise CheckpointError(f"{path} holds arm {state.get('arm')!r}, not {arm_name!r}")
    if comparable(state["config"]) != comparable(cfg):
        raise CheckpointError(f"{path} was written with another config; remove it or drop --resume")
    return restore(state, model, opt)


def restore(state: dict, model, opt) -> dict:
    """Load a checked checkpoint payload's model, optimiser and RNG state; returns the payload."""
    model.load_state_dict(state["model"])
    opt.load_state_dict(state["optimizer"])
    torch.set_rng_state(state["rng"])
    return state


def _show_progress(bar, history: list, done: int, steps: int, log_every: int) -> None:
    bar.update(1)
    if done % log_every == 0 or done == steps:
        recent = history[-log_every:]
        bar.set_postfix(
            l1=f"{sum(r['l1'] for r in recent) / len(recent):.4f}",
            q=f"{sum(r['quality'] for r in recent) / len(recent):.3f}",
            ce=f"{sum(r['corner_error'] for r in recent) / len(recent):.2f}px",
        )


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
    arm, t = cfg["arms"][arm_name], cfg["train"]
    steps, ckpt_every, log_every = int(t["steps"]), int(t["checkpoint_every"]), int(t["log_every"])
    ckpt = checkpoint_path(out, arm_name)
    scenes = scenes if scenes is not None else load_scenes(cfg)
    model, opt = build(cfg, device)
    start, history, wall_before = 0, [], 0.0
    if resume and ckpt.is_file():
        state = load_checkpoint(ckpt, cfg, arm_name, model, opt)
        start, history, wall_before = int(state["step"]), list(state["history"]), float(state["wall_s"])
    base_q = QualityConfig()
    bar = tqdm(total=steps, initial=start, desc=arm_name, dynamic_ncols=True) if progress else None
    t0 = time.perf_counter()
    for step in range(start, steps):
        batch = make_pairs(scenes, train_seeds(cfg, step), cfg["data"], bool(arm["distorted"]), held_out=False)
        batch = {k: v.to(device) for k, v in batch.items()}
        history.append({**train_step(model, opt, batch, arm, step, steps, cfg, base_q), "step": step})
        done = step + 1
        if bar is not None:
            _show_progress(bar, history, done, steps, log_every)
        if done % ckpt_every == 0 or done == steps:
            save_checkpoint(ckpt, model, opt, done, history, cfg, arm_name, wall_before + time.perf_counter() - t0)
        if stop_after is not None and done >= stop_after:
            break
    if bar is not None:
        bar.close()
    return model, history, wall_before + time.perf_counter() - t0
