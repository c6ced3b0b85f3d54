"""Seed statistics, the choice of lambda and lr on validation, the verdict, the outputs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

from lensdist_torch.core import atomic_write_text
from lensdist_torch.workflows.figures import have_matplotlib, save_curves

__all__ = [
    "METRICS",
    "LABELS",
    "seed_stats",
    "choose",
    "verdict",
    "merge_results",
    "write_markdown",
    "save_figures",
    "write_outputs",
]

METRICS = ("mean_corner_error", "median_corner_error", "share_below_0_5px", "share_below_1px")
#: The sections of results.json that hold arms, with their titles.
LABELS = {
    "network": "Fine-stage network, illumination change",
    "network_distorted": "Fine-stage network, illumination change + lens distortion",
    "refinement": "Test-time refinement (Adam on the 8 offsets), illumination change",
    "refinement_distorted": "Test-time refinement, illumination change + lens distortion",
}


def seed_stats(per_seed: list[dict], seeds: list) -> dict:
    """Mean, std over seeds (n - 1 in the denominator; 0 for one seed) and the per-seed values."""
    out: dict = {"seeds": list(seeds)}
    for m in METRICS:
        t = torch.tensor([r[m] for r in per_seed], dtype=torch.float64)
        std = float(t.std(unbiased=True)) if t.numel() > 1 else 0.0
        out[m] = {"mean": float(t.mean()), "std": std, "per_seed": [float(x) for x in t]}
    return out


def choose(candidates: dict, key: str = "median_corner_error"):
    """The candidate with the lowest validation ``key`` (the first on ties)."""
    return min(candidates, key=lambda c: candidates[c][key])


def _m(arm: dict, key: str = "median_corner_error") -> tuple[float, float]:
    return arm[key]["mean"], arm[key]["std"]


def verdict(section: dict) -> dict | None:
    """The claim on one section: L1 + quality lowers the median corner error by >= 10 % against
    L1, by more than the two arms' seed std together, and is no worse than NCC and NGF by more
    than their seed std. None when the section lacks an arm."""
    need = ("l1", "l1+quality", "ncc", "ngf")
    if any(a not in section for a in need):
        return None
    (m1, s1), (mq, sq) = _m(section["l1"]), _m(section["l1+quality"])
    rel = (m1 - mq) / m1 if m1 > 0 else float("nan")
    paired = [
        (a - b) / a
        for a, b in zip(
            section["l1"]["median_corner_error"]["per_seed"], section["l1+quality"]["median_corner_error"]["per_seed"]
        )
    ]
    level = {p: mq <= _m(section[p])[0] + _m(section[p])[1] for p in ("ncc", "ngf")}
    beyond = (m1 - mq) > s1 + sq
    return {
        "median_reduction_vs_l1": rel,
        "paired_median_reduction_per_seed": paired,
        "beyond_seed_spread": bool(beyond),
        "level_with": level,
        "claim_met": bool(rel >= 0.10 and beyond and all(level.values())),
    }


def merge_results(parts: list[dict]) -> dict:
    """Pool the seeds of several results.json of the same study (e.g. seeds 0-2 and 3-5).

    An arm is kept where every part has it with the same lambda (and lr); its per-seed values
    are concatenated and the statistics recomputed. The training config must agree apart from
    the seeds and the sweep (which do not change a run); a seed may appear only once.
    """
    base = parts[0]
    keep = {"train": ("seeds", "log_every", "checkpoint_every", "group_size")}

    def same(cfg):
        out = {k: v for k, v in cfg.items() if k in ("data", "model", "loss", "train")}
        out["train"] = {k: v for k, v in out["train"].items() if k not in keep["train"]}
        return out

    for p in parts[1:]:
        if same(p["config"]) != same(base["config"]):
            raise ValueError("merge_results: the parts were trained with different configs")
    merged = {
        "device": base["device"],
        "merged_from": len(parts),
        "identity": base["identity"],
        "config": base["config"],
    }
    for section in LABELS:
        arms = {}
        for name, a in (base.get(section) or {}).items():
            others = [p.get(section, {}).get(name) for p in parts[1:]]
            if any(o is None or o["lambda"] != a["lambda"] or o.get("lr") != a.get("lr") for o in others):
                continue
            group = [a, *others]
            seeds = [s for g in group for s in g["seeds"]]
            if len(set(map(str, seeds))) != len(seeds):
                raise ValueError(f"merge_results: {section}/{name} has a seed twice: {seeds}")
            per_seed = [{m: g[m]["per_seed"][i] for m in METRICS} for g in group for i in range(len(g["seeds"]))]
            arms[name] = {
                "peer": a["peer"],
                "lambda": a["lambda"],
                **({"lr": a["lr"]} if "lr" in a else {}),
                **seed_stats(per_seed, seeds),
            }
        if arms:
            merged[section] = arms
    merged["verdict"] = {s: v for s in LABELS if merged.get(s) and (v := verdict(merged[s])) is not None}
    return merged


def _fmt(arm: dict, key: str, pct: bool = False) -> str:
    m, s = _m(arm, key)
    return f"{100 * m:.1f} ± {100 * s:.1f} %" if pct else f"{m:.3f} ± {s:.3f}"


def write_markdown(results: dict, path: Path) -> str:
    """One table per section (mean ± std over seeds), the selections and the verdicts."""
    lines = [
        f"Device: {results['device']}. Identity (no correction) on the test pairs: mean "
        f"{results['identity']['test']['mean_corner_error']:.3f} px, median "
        f"{results['identity']['test']['median_corner_error']:.3f} px.",
        "",
    ]
    for section, title in LABELS.items():
        arms = results.get(section) or {}
        if not arms:
            continue
        lines += [
            f"### {title}",
            "",
            "| arm | lambda | lr | seeds | mean (px) | median (px) | < 0.5 px | < 1 px |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, a in arms.items():
            lr = f"{a['lr']:g}" if "lr" in a else "-"
            lines.append(
                f"| `{name}` | {a['lambda']:g} | {lr} | {len(a['seeds'])} | {_fmt(a, 'mean_corner_error')} | "
                f"{_fmt(a, 'median_corner_error')} | {_fmt(a, 'share_below_0_5px', True)} | "
                f"{_fmt(a, 'share_below_1px', True)} |"
            )
        v = results.get("verdict", {}).get(section)
        if v:
            lines += [
                "",
                f"L1 + quality against L1: median {100 * v['median_reduction_vs_l1']:+.1f} % "
                f"(per seed {', '.join(f'{100 * x:+.1f} %' for x in v['paired_median_reduction_per_seed'])}); "
                f"beyond the seed spread: {v['beyond_seed_spread']}; level with NCC / NGF: "
                f"{v['level_with']['ncc']} / {v['level_with']['ngf']}; **claim met: {v['claim_met']}**.",
            ]
        lines.append("")
    text = "\n".join(lines)
    atomic_write_text(path, text)
    return text


def _smooth(values: list[float], k: int) -> list[float]:
    out, acc = [], 0.0
    for i, x in enumerate(values):
        acc += x - (values[i - k] if i >= k else 0.0)
        out.append(acc / min(i + 1, k))
    return out


def save_figures(results: dict, histories: dict, curves: dict, out: Path, prefix: str = "fine_stage") -> list[Path]:
    """The median corner error per arm (bars: mean over seeds, whiskers: std), the refinement
    curves and the training curves; [] without matplotlib."""
    if not have_matplotlib():
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sections = [s for s in LABELS if results.get(s)]
    fig, axes = plt.subplots(1, len(sections), figsize=(4.2 * len(sections), 3.8), squeeze=False)
    for ax, s in zip(axes[0], sections):
        names = list(results[s])
        m = [results[s][n]["median_corner_error"]["mean"] for n in names]
        e = [results[s][n]["median_corner_error"]["std"] for n in names]
        ax.bar(range(len(names)), m, yerr=e, capsize=3, color=["#4477aa" if "+" not in n else "#cc6677" for n in names])
        ax.set_xticks(range(len(names)), [n.replace("dist-", "") for n in names], rotation=40, ha="right")
        ax.set_ylabel("median corner error (px)")
        ax.set_title(LABELS[s].replace(", ", ",\n", 1), fontsize=9)
    fig.tight_layout()
    paths = [Path(out) / f"{prefix}_summary.png"]
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)
    if curves:
        paths.append(
            save_curves(
                curves,
                Path(out) / f"{prefix}_refine_curves.png",
                xlabel="Adam step",
                ylabel="mean corner error (px)",
                title="test-time refinement, test set 0",
            )
        )
    if histories:
        k = max(1, min(50, len(next(iter(histories.values()))) // 10))
        series = {n: _smooth([r["corner_error"] for r in h], k) for n, h in histories.items()}
        paths.append(
            save_curves(
                series,
                Path(out) / f"{prefix}_train_curves.png",
                xlabel="step",
                ylabel="training corner error (px)",
                title=f"seed 0, smoothed over {k} steps",
            )
        )
    return paths


def _clean(x):
    """JSON-safe: non-finite floats as null."""
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_outputs(out: Path, results: dict, histories: dict, curves: dict) -> str:
    out = Path(out)
    atomic_write_text(out / "results.json", json.dumps(_clean(results), indent=1, allow_nan=False) + "\n")
    text = write_markdown(results, out / "results.md")
    for p in save_figures(results, histories, curves, out):
        print(f"figure: {p}")
    return text
