"""The whole study: which runs, grouped how, in how many processes, and what goes where.

Network arms, one phase: every peer alone and every peer + lambda for each swept lambda, every
training seed; the same on lens-distorted pairs for the peers in ``sweep.distorted``; the
L1 + quality variants (temperature, schedule) with the first seed, reported on validation
only. The arms of one (seed, distorted) are trained in groups of ``train.group_size`` on the
same batches. Each section's lambda is then chosen per peer on its validation pairs (the mean
over seeds of the validation median corner error).

Test-time refinement: lr chosen per peer alone, (lambda, lr) jointly per peer + quality, on the
validation pairs; then each arm on ``refine.test_sets`` disjoint test sets. With ``--jobs`` > 1
it runs in its own process beside the training.

Every selection reads validation metrics only; the test pairs are only ever reported.
"""

from __future__ import annotations

import os
import warnings
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import torch
from tqdm.auto import tqdm

from .config import PEERS, arm_name, arm_spec
from .data import load_scenes, make_pairs, split_seeds
from .loop import metrics, run_group, split_pairs
from .refine import refine
from .report import choose, seed_stats, verdict

__all__ = ["setup_determinism", "plan", "refinement_study", "run_all"]


def setup_determinism(device: str, threads: int) -> None:
    """Pin the CPU threads; on CUDA, deterministic cuDNN and cuBLAS (no TF32), and warnings for
    the ops without a deterministic implementation (collected and reported)."""
    torch.set_num_threads(int(threads))
    if str(device).startswith("cuda"):
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        torch.backends.cudnn.deterministic = True
        torch.backends.cudnn.benchmark = False
        torch.backends.cuda.matmul.allow_tf32 = False
        torch.backends.cudnn.allow_tf32 = False
        torch.use_deterministic_algorithms(True, warn_only=True)


def _notes(caught) -> list[str]:
    return sorted({str(w.message).split(".")[0][:200] for w in caught if "deterministic" in str(w.message)})


def _group_job(args):
    """One group of arms (one seed) in a worker process; summaries without the models."""
    cfg, specs, seed, out, device, resume, progress = args
    setup_determinism(device, cfg["train"]["threads"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rs = run_group(cfg, specs, seed, out, device, resume, progress)
    notes = _notes(caught)
    return [{"history": r["history"], "eval": r["eval"], "wall_s": r["wall_s"], "nondeterministic": notes} for r in rs]


def _refine_job(args):
    cfg, device, progress = args
    setup_determinism(device, cfg["train"]["threads"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res, curves = refinement_study(cfg, device, progress)
    res["nondeterministic_ops_refinement"] = _notes(caught)
    return res, curves


def plan(cfg: dict) -> tuple[list[tuple[list[dict], int]], dict]:
    """The groups [(specs, seed)] to train, and the specs of every result cell."""
    seeds, lams, s0 = list(cfg["train"]["seeds"]), list(cfg["sweep"]["lambdas"]), cfg["train"]["seeds"][0]
    cells = {"network": {}, "network_distorted": {}}
    for distorted, peers in ((False, PEERS), (True, tuple(cfg["sweep"]["distorted"]))):
        for p in peers:
            cells["network_distorted" if distorted else "network"][p] = {
                lam: arm_spec(cfg, p, lam, distorted) for lam in [0.0, *lams]
            }
    variants = [arm_spec(cfg, "l1", cfg["sweep"]["variant_lambda"], variant=v) for v in cfg["sweep"]["variants"]]
    size, groups = int(cfg["train"]["group_size"]), []
    for section in ("network", "network_distorted"):
        for seed in seeds:
            specs = [spec for per_peer in cells[section].values() for spec in per_peer.values()]
            specs += variants if (section == "network" and seed == s0) else []
            groups += [(specs[i : i + size], seed) for i in range(0, len(specs), size)]
    return groups, {**cells, "variants": variants}


def _entry(runs: dict, spec: dict, seeds: list) -> dict:
    rs = [runs[(arm_name(spec), s)] for s in seeds]
    return {
        "peer": spec["peer"],
        "lambda": spec["lambda"],
        **seed_stats([r["eval"]["test"] for r in rs], seeds),
        "val": seed_stats([r["eval"]["val"] for r in rs], seeds),
        "train_wall_s": [round(r["wall_s"], 1) for r in rs],
    }


def assemble(cfg: dict, runs: dict, cells: dict) -> dict:
    """Choose each section's lambdas on validation and build the result sections."""
    seeds, s0 = list(cfg["train"]["seeds"]), cfg["train"]["seeds"][0]
    res: dict = {"selection_network": {"criterion": "mean over training seeds of the validation median corner error"}}
    for section in ("network", "network_distorted"):
        res[section], chosen, table = {}, {}, {}
        for p, by_lam in cells[section].items():
            val = {lam: _entry(runs, spec, seeds)["val"] for lam, spec in by_lam.items()}
            table[p] = {
                f"{lam:g}": {m: v[m]["mean"] for m in ("median_corner_error", "mean_corner_error")}
                for lam, v in val.items()
            }
            chosen[p] = choose({lam: {"m": v["median_corner_error"]["mean"]} for lam, v in val.items() if lam}, "m")
            res[section][p] = _entry(runs, by_lam[0.0], seeds)
            res[section][p + "+quality"] = _entry(runs, by_lam[chosen[p]], seeds)
        res["selection_network"][section] = {"lambda": chosen, "validation": table}
    res["selection_network"]["variants_l1_quality"] = {
        v["variant"]: {"lambda": v["lambda"], **runs[(arm_name(v), s0)]["eval"]["val"]} for v in cells["variants"]
    }
    res["nondeterministic_ops"] = sorted({n for r in runs.values() for n in r["nondeterministic"]})
    return res


def refinement_study(cfg, device, progress, scenes=None) -> tuple[dict, dict]:
    """Selection on validation, then every arm on the test sets; returns (sections, curves)."""
    scenes = scenes if scenes is not None else load_scenes(cfg)
    r, lrs, lams = cfg["refine"], list(cfg["refine"]["lrs"]), list(cfg["refine"]["lambdas"])
    val_seeds = split_seeds(int(cfg["eval"]["val_seed"]), int(r["val_pairs"]))
    tau = float(cfg["train"]["tau_scale"])
    grid = [(p, 0.0, lr) for p in PEERS for lr in lrs] + [(p, lam, lr) for p in PEERS for lam in lams for lr in lrs]
    val = {}
    for p, lam, lr in tqdm(grid, desc="refine: validation", disable=not progress):
        val[(p, lam, lr)] = metrics(refine(cfg, p, lam, tau, lr, val_seeds, "val", False, device, scenes)[0])
    pick = {}
    for p in PEERS:
        pick[p] = (0.0, choose({lr: val[(p, 0.0, lr)] for lr in lrs}))
        pick[p + "+quality"] = choose({(lam, lr): val[(p, lam, lr)] for lam in lams for lr in lrs})
    sets = list(range(int(r["test_sets"])))
    res: dict = {"refinement": {}, "refinement_distorted": {}}
    curves = {}
    todo = [(name, d) for d in ([False, True] if r["distorted"] else [False]) for name in pick]
    for name, distorted in tqdm(todo, desc="refine: test", disable=not progress):
        lam, lr = pick[name]
        per_set = []
        for k in sets:
            seeds = split_seeds(int(cfg["eval"]["test_seed"]) + k, int(r["test_pairs"]))
            e, curve = refine(cfg, name.split("+")[0], lam, tau, lr, seeds, "test", distorted, device, scenes)
            per_set.append(metrics(e))
            if k == 0 and not distorted:
                curves[name] = [float(x) for x in curve]
        res["refinement_distorted" if distorted else "refinement"][name] = {
            "peer": name.split("+")[0],
            "lambda": lam,
            "lr": lr,
            **seed_stats(per_set, sets),
        }
    res["selection_refinement"] = {
        "criterion": f"validation median corner error, {len(val_seeds)} pairs, {r['steps']} Adam steps "
        "(the distorted section reuses these choices)",
        "chosen": {n: {"lambda": lam, "lr": lr} for n, (lam, lr) in pick.items()},
        "validation": {f"{p}|lambda={lam:g}|lr={lr:g}": m for (p, lam, lr), m in val.items()},
    }
    return res, curves


def run_all(cfg, out: Path, device: str, resume: bool, n_proc: int, progress: bool, do_refine: bool = True):
    """Everything; returns (results sections, training histories of the first seed, refinement curves)."""
    groups, cells = plan(cfg)
    do_refine = do_refine and bool(cfg["refine"]["enabled"])
    jobs = [(cfg, specs, seed, str(out), device, resume, progress and n_proc <= 1) for specs, seed in groups]
    print(f"{sum(len(s) for s, _ in groups)} training runs in {len(groups)} groups", flush=True)
    refined = None
    if n_proc <= 1:
        outs = [_group_job(j) for j in jobs]
        if do_refine:
            refined = _refine_job((cfg, device, progress))
    else:
        with ProcessPoolExecutor(n_proc, mp_context=get_context("spawn")) as pool:
            fut_refine = pool.submit(_refine_job, (cfg, device, False)) if do_refine else None
            outs = []
            for (specs, seed), rs in tqdm(
                zip(groups, pool.map(_group_job, jobs)), total=len(jobs), desc="groups", disable=not progress
            ):
                outs.append(rs)
                print(
                    f"  seed {seed}: {', '.join(arm_name(s) for s in specs)} done ({rs[0]['wall_s']:.0f} s)", flush=True
                )
            refined = fut_refine.result() if fut_refine is not None else None
    runs = {}
    for (specs, seed), rs in zip(groups, outs):
        runs.update({(arm_name(spec), seed): r for spec, r in zip(specs, rs)})
    res = assemble(cfg, runs, cells)
    curves = {}
    if refined is not None:
        res.update(refined[0])
        curves = refined[1]
    scenes = load_scenes(cfg)
    res["identity"] = {
        split: metrics(
            make_pairs(scenes, split_pairs(cfg, split), cfg["data"], False, split)["delta"]
            .double()
            .norm(dim=-1)
            .mean(dim=-1)
        )
        for split in ("val", "test")
    }
    res["verdict"] = {
        s: v
        for s in ("network", "network_distorted", "refinement", "refinement_distorted")
        if res.get(s) and (v := verdict(res[s])) is not None
    }
    s0 = cfg["train"]["seeds"][0]
    sec = res["network"]
    histories = {n: runs[(arm_name(arm_spec(cfg, a["peer"], a["lambda"])), s0)]["history"] for n, a in sec.items()}
    return res, histories, curves
