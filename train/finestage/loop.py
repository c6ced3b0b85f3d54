"""One training run of the fine stage (an arm and a seed), its checkpoints and its evaluation.

Checkpoints go through ``lensdist_torch.core.storage.save_versioned`` (atomic, with a kind and
a format version, read back with ``torch.load(weights_only=True)``). Each records the arm, the
seed and the training part of the config; ``resume`` refuses a checkpoint of another arm, seed
or config and continues to bit-identical parameters. A finished run keeps its evaluation in its
checkpoint, so a resumed invocation does not evaluate it again.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from learnreg.loop import arm_schedule, learning_rate, restore, save_checkpoint
from learnreg.losses import corner_error, warp_a_to_b
from tqdm.auto import tqdm

from lensdist_torch.core import CheckpointError, load_versioned

from .config import arm_name, comparable
from .data import load_scenes, make_pairs, split_seeds, train_seeds
from .losses import Criterion
from .models import build_model

__all__ = [
    "CHECKPOINT_KIND",
    "CHECKPOINT_VERSION",
    "quality_weight",
    "build",
    "train_step",
    "checkpoint_path",
    "metrics",
    "evaluate",
    "evaluate_group",
    "run_group",
    "run",
]

CHECKPOINT_KIND = "fine_stage_run"
CHECKPOINT_VERSION = 1
_KEYS = ("loss", "peer", "quality", "lambda", "corner_error")


def quality_weight(spec: dict, step: int, steps: int) -> float:
    """lambda at ``step``: learnreg's schedule (off before quality_start, then a linear ramp)."""
    arm = {
        "lambda_quality": spec["lambda"],
        "quality_start": spec["quality_start"],
        "quality_ramp": spec["quality_ramp"],
        "tau_scale_start": 1.0,
        "tau_scale_end": 1.0,
    }
    return arm_schedule(arm, step, steps)[0]


def build(cfg: dict, seed: int, device: str = "cpu"):
    """The fine network (initialised from ``seed``) and its Adam optimiser."""
    torch.manual_seed(int(seed))
    model = build_model(cfg).to(device)
    t = cfg["train"]
    opt = torch.optim.Adam(model.parameters(), lr=float(t["lr"]), weight_decay=float(t["weight_decay"]))
    return model, opt


def train_step(model, opt, batch: dict, crit: Criterion, lam: float, lr: float) -> torch.Tensor:
    """One optimisation step; returns (loss, peer, quality, lambda, corner error) on the device."""
    for g in opt.param_groups:
        g["lr"] = lr
    model.train()
    pred = model(batch["a"], batch["b"])
    warped, valid = warp_a_to_b(batch["a"], pred)
    loss, peer, q = crit(warped, batch["b"], valid, lam)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    ce = (pred.detach() - batch["delta"]).norm(dim=-1).mean()  # = the homography corner error (a test)
    return torch.stack([loss.detach(), peer.detach(), q.detach(), ce.new_tensor(lam), ce])


def checkpoint_path(out: Path, spec: dict, seed: int) -> Path:
    return Path(out) / "checkpoints" / f"{arm_name(spec)}_s{int(seed)}.pt"


def _save(path, model, opt, step, history, cfg, spec, seed, wall_s, evaluation=None) -> None:
    save_checkpoint(path, model, opt, step, history, comparable(cfg), arm_name(spec), wall_s, CHECKPOINT_KIND,
                    CHECKPOINT_VERSION, spec=dict(spec), seed=int(seed), eval=evaluation)


def _load(path, cfg, spec, seed, model, opt) -> dict:
    state = load_versioned(
        path, kind=CHECKPOINT_KIND, version=CHECKPOINT_VERSION, what="fine-stage", map_location="cpu"
    )
    if state.get("arm") != arm_name(spec) or state.get("seed") != int(seed):
        raise CheckpointError(f"{path} holds arm {state.get('arm')!r} seed {state.get('seed')}, not {arm_name(spec)!r}")
    if state["config"] != comparable(cfg) or state.get("spec") != dict(spec):
        raise CheckpointError(f"{path} was written with another config; remove it or drop --resume")
    return restore(state, model, opt)


def metrics(errors: torch.Tensor) -> dict[str, float]:
    """Mean and median corner error, shares under 0.5 and 1 px, of per-pair errors (px)."""
    e = errors.double()
    return {
        "mean_corner_error": float(e.mean()),
        "median_corner_error": float(e.median()),
        "share_below_0_5px": float((e < 0.5).double().mean()),
        "share_below_1px": float((e < 1.0).double().mean()),
        "n_pairs": int(e.numel()),
    }


def split_pairs(cfg: dict, split: str, index: int = 0) -> list[int]:
    """Seeds of the validation set, or of test set ``index`` (0: the network's test set)."""
    e = cfg["eval"]
    if split == "val":
        return split_seeds(int(e["val_seed"]), int(e["val_pairs"]))
    return split_seeds(int(e["test_seed"]) + index, int(e["test_pairs"]))


def evaluate(model, cfg, distorted, device="cpu", scenes=None) -> dict:
    """Validation and test metrics of a trained network, with the per-pair errors."""
    return evaluate_group([model], cfg, distorted, device, scenes)[0]


def _flush(buf: list, history: list, start_step: int) -> None:
    if buf:
        for i, row in enumerate(torch.stack(buf).cpu().tolist()):
            history.append({"step": start_step + i, **dict(zip(_KEYS, row))})
        buf.clear()


@torch.no_grad()
def evaluate_group(models: list, cfg: dict, distorted: bool, device="cpu", scenes=None) -> list[dict]:
    """:func:`evaluate` for several networks on the same pairs, each batch generated once."""
    scenes = scenes if scenes is not None else load_scenes(cfg)
    bs, patch = int(cfg["eval"]["batch_size"]), int(cfg["data"]["patch"])
    outs = [{} for _ in models]
    for split in ("val", "test"):
        seeds, errs = split_pairs(cfg, split), [[] for _ in models]
        for i in range(0, len(seeds), bs):
            batch = make_pairs(scenes, seeds[i : i + bs], cfg["data"], distorted, split)
            a, b = batch["a"].to(device), batch["b"].to(device)
            for j, model in enumerate(models):
                model.eval()
                errs[j].append(corner_error(model(a, b).cpu(), batch["delta"], patch))
        for j, e in enumerate(errs):
            e = torch.cat(e)
            outs[j][split] = metrics(e)
            outs[j][split + "_errors"] = [round(float(x), 5) for x in e]
    for o in outs:
        o["eval_config"] = json.loads(json.dumps(cfg["eval"]))
    return outs


def run_group(cfg, specs, seed, out, device="cpu", resume=False, progress=True, scenes=None, stop_after=None):
    """Train several arms with one seed on the same stream of batches (each generated once),
    then evaluate them; returns one summary dict per arm (model, history, wall_s, eval).

    The arms must share ``distorted``. An arm's result does not depend on the group it is
    trained in (a test checks it). ``stop_after`` simulates a crash after that many steps (no
    checkpoint is written then). wall_s is the group's training time, shared by its arms.
    """
    if len({s["distorted"] for s in specs}) != 1:
        raise ValueError("the arms of a group must share 'distorted'")
    t = cfg["train"]
    steps, every, log_every = int(t["steps"]), int(t["checkpoint_every"]), int(t["log_every"])
    bs, distorted = int(t["batch_size"]), specs[0]["distorted"]
    scenes = scenes if scenes is not None else load_scenes(cfg)
    arms = []
    for spec in specs:
        model, opt = build(cfg, seed, device)  # every arm of a seed starts from the same weights
        a = {
            "spec": spec,
            "model": model,
            "opt": opt,
            "path": checkpoint_path(out, spec, seed),
            "start": 0,
            "history": [],
            "wall": 0.0,
            "eval": None,
            "buf": [],
        }
        if resume and a["path"].is_file():
            state = _load(a["path"], cfg, spec, seed, model, opt)
            a.update(start=state["step"], history=list(state["history"]), wall=state["wall_s"], eval=state["eval"])
        a["crit"] = Criterion(spec["peer"], cfg["loss"], spec["tau_scale"])
        arms.append(a)
    first = min(a["start"] for a in arms)
    desc = f"s{seed} {arm_name(specs[0])}" + (f" +{len(specs) - 1}" if len(specs) > 1 else "")
    bar = tqdm(total=steps, initial=first, desc=desc, dynamic_ncols=True, leave=False) if progress else None
    t0 = time.perf_counter()
    for step in range(first, steps):
        batch = make_pairs(scenes, train_seeds(seed, step, bs), cfg["data"], distorted, "train")
        batch = {k: v.to(device, non_blocking=True) for k, v in batch.items()}
        lr, done = learning_rate(cfg, step, steps), step + 1
        for a in arms:
            if step < a["start"]:
                continue
            lam = quality_weight(a["spec"], step, steps)
            a["buf"].append(train_step(a["model"], a["opt"], batch, a["crit"], lam, lr))
            if done % log_every == 0 or done % every == 0 or done == steps:
                _flush(a["buf"], a["history"], done - len(a["buf"]))
            if done % every == 0 or done == steps:
                wall = a["wall"] + time.perf_counter() - t0
                _save(a["path"], a["model"], a["opt"], done, a["history"], cfg, a["spec"], seed, wall)
        if bar is not None:
            bar.update(1)
            if done % log_every == 0:
                bar.set_postfix(ce=" ".join(f"{a['history'][-1]['corner_error']:.2f}" for a in arms if a["history"]))
        if stop_after is not None and done >= stop_after:
            break
    if bar is not None:
        bar.close()
    elapsed = time.perf_counter() - t0
    for a in arms:
        _flush(a["buf"], a["history"], len(a["history"]))
        a["wall"] += elapsed
    finished = [a for a in arms if len(a["history"]) >= steps]
    todo = [
        a for a in finished if a["eval"] is None or a["eval"].get("eval_config") != json.loads(json.dumps(cfg["eval"]))
    ]
    for a, ev in zip(todo, evaluate_group([a["model"] for a in todo], cfg, distorted, device, scenes)):
        a["eval"] = ev
        _save(a["path"], a["model"], a["opt"], steps, a["history"], cfg, a["spec"], seed, a["wall"], ev)
    return [{"model": a["model"], "history": a["history"], "wall_s": a["wall"], "eval": a["eval"]} for a in arms]


def run(cfg, spec, seed, out, device="cpu", resume=False, progress=True, scenes=None, stop_after=None) -> dict:
    """One arm alone: :func:`run_group` with a group of one."""
    return run_group(cfg, [spec], seed, out, device, resume, progress, scenes, stop_after)[0]
