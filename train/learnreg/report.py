"""Evaluation on the held-out pairs and the outputs: results.json, results.md, curves."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from lensdist_torch.core import atomic_write_text
from lensdist_torch.workflows.figures import have_matplotlib, save_curves

from .data import eval_seeds, load_scenes, make_pairs
from .losses import corner_error

__all__ = ["evaluate", "write_markdown", "save_training_curves", "write_outputs", "CURVES"]

#: Training curves, one PNG each: history key -> (file name, y label).
CURVES = {
    "corner_error": ("curves.png", "training corner error (px)"),
    "l1": ("curves_l1.png", "photometric L1"),
    "quality": ("curves_quality.png", "quality loss (0 while off)"),
}


@torch.no_grad()
def evaluate(model, cfg: dict, distorted: bool, device: str = "cpu", scenes=None) -> dict[str, float]:
    """Corner errors on the held-out pairs (another seed, the bottom rows of the scenes)."""
    scenes = scenes if scenes is not None else load_scenes(cfg)
    model.eval()
    seeds = eval_seeds(cfg)
    bs, patch = int(cfg["eval"]["batch_size"]), int(cfg["data"]["patch"])
    errs, ident = [], []
    for i in range(0, len(seeds), bs):
        batch = make_pairs(scenes, seeds[i : i + bs], cfg["data"], distorted, held_out=True)
        pred = model(batch["a"].to(device), batch["b"].to(device)).cpu()
        errs.append(corner_error(pred, batch["delta"], patch))
        ident.append(corner_error(torch.zeros_like(batch["delta"]), batch["delta"], patch))
    e, e0 = torch.cat(errs), torch.cat(ident)
    return {
        "mean_corner_error": float(e.mean()),
        "median_corner_error": float(e.median()),
        "share_under_1px": float((e < 1.0).double().mean()),
        "identity_mean_corner_error": float(e0.mean()),
        "n_pairs": int(e.numel()),
    }


def _schedule_text(arm: dict) -> str:
    if not arm["lambda_quality"]:
        text = "-"
    else:
        text = f"L1 only for {arm['quality_start']:.0%}, ramp {arm['quality_ramp']:.0%}"
        if arm["tau_scale_start"] != 1.0 or arm["tau_scale_end"] != 1.0:
            text += f", tau x{arm['tau_scale_start']:g} -> x{arm['tau_scale_end']:g}"
    return text + (" (lens distortion)" if arm["distorted"] else "")


def write_markdown(results: dict, cfg: dict, path: Path, wall: float | None = None) -> str:
    """The results table and a line on the setting; written to ``path`` and returned."""
    lines = [
        "| arm | lambda | schedule | mean corner error (px) | median (px) | share < 1 px |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        arm = cfg["arms"][name]
        lines.append(
            f"| `{name}` | {arm['lambda_quality']:g} | {_schedule_text(arm)} | {r['mean_corner_error']:.2f} | "
            f"{r['median_corner_error']:.2f} | {r['share_under_1px']:.1%} |"
        )
    first = next(iter(results.values()))
    d, t = cfg["data"], cfg["train"]
    lines += [
        "",
        f"{first['n_pairs']} held-out pairs; identity (no registration) mean corner error "
        f"{first['identity_mean_corner_error']:.2f} px. {t['steps']} steps of {t['batch_size']} pairs, "
        f"{d['patch']} x {d['patch']} patches, corners perturbed up to {d['rho']:g} px, seed {t['seed']}, "
        f"{t['threads']} thread(s)."
        + (f" Wall time of this invocation {wall / 60:.1f} min." if wall is not None else ""),
    ]
    text = "\n".join(lines) + "\n"
    atomic_write_text(path, text)
    return text


def _smooth(values: list[float], k: int = 25) -> list[float]:
    """Running mean over the last ``k`` values (fewer at the start)."""
    out, acc = [], 0.0
    for i, x in enumerate(values):
        acc += x
        if i >= k:
            acc -= values[i - k]
        out.append(acc / min(i + 1, k))
    return out


def save_training_curves(histories: dict[str, list[dict]], out: Path) -> list[Path]:
    """One PNG per entry of :data:`CURVES` (arm -> smoothed series); [] without matplotlib."""
    if not have_matplotlib():
        return []
    paths = []
    for key, (name, label) in CURVES.items():
        series = {arm: _smooth([r[key] for r in hist]) for arm, hist in histories.items()}
        paths.append(
            save_curves(series, Path(out) / name, xlabel="step", ylabel=label, title=f"{label}, smoothed over 25 steps")
        )
    return paths


def write_outputs(out: Path, results: dict, histories: dict, cfg: dict, wall: float) -> str:
    """results.json, config_used.json, results.md and the curves under ``out``; returns the table."""
    out = Path(out)
    atomic_write_text(out / "results.json", json.dumps(results, indent=2) + "\n")
    atomic_write_text(out / "config_used.json", json.dumps(cfg, indent=2) + "\n")
    text = write_markdown(results, cfg, out / "results.md", wall)
    for path in save_training_curves(histories, out):
        print(f"curves: {path}")
    return text
