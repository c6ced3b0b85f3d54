"""The fine stage: the registration-quality loss against L1, local NCC and NGF under illumination change.

A refinement network takes a pair that a coarse stage left 0.5-3 px from registered, with
strong illumination changes between the two patches (gain, offset, gamma, a brightness ramp,
vignetting, noise), and predicts the residual corner offsets, trained unsupervised with each
loss alone and with + lambda * ``RegistrationQualityLoss`` (lambda chosen on validation pairs).
The same losses then optimise the offsets of each held-out pair directly (test-time
refinement). Same data, steps and seeds for every arm; lens-distorted pairs as a separate arm.

Usage (one command, from the repository root)::

    python train/fine_stage.py --config configs/fine_stage.toml --out results/fine_stage \\
        [--device cpu|cuda] [--jobs N] [--resume] [--steps N] [--set train.batch_size=16 ...]

Writes ``results.json``, ``results.md``, ``config_used.json``, the figures and
``checkpoints/<arm>_s<seed>.pt`` under ``--out``. The work is done by the ``finestage``
package next to this script (which reuses ``learnreg``).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch
from finestage.config import load_config
from finestage.experiment import run_all, setup_determinism
from finestage.report import merge_results, write_outputs
from learnreg.config import config_from_args

from lensdist_torch.core import atomic_write_text


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/fine_stage.toml")
    ap.add_argument("--out", default="results/fine_stage")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--jobs", type=int, default=1, help="training runs in parallel (spawned processes)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--resume", action="store_true", help="continue every run from its checkpoint")
    ap.add_argument("--no-refine", action="store_true", help="skip the test-time refinement")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.steps=50")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument(
        "--merge", nargs="+", metavar="RESULTS_JSON", help="only pool the seeds of these results into --out"
    )
    return ap.parse_args(argv)


def describe_device(device: str) -> str:
    if device.startswith("cuda"):
        return f"{torch.cuda.get_device_name(device)} (CUDA {torch.version.cuda}), torch {torch.__version__}"
    return f"CPU ({platform.processor() or platform.machine()}), torch {torch.__version__}"


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    if args.merge:
        merged = merge_results([json.loads(Path(p).read_text()) for p in args.merge])
        Path(args.out).mkdir(parents=True, exist_ok=True)
        print(write_outputs(Path(args.out), merged, {}, {}))
        return merged
    cfg = config_from_args(args, load_config)
    setup_determinism(args.device, cfg["train"]["threads"])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config_used.json", json.dumps(cfg, indent=1) + "\n")
    t0 = time.perf_counter()
    results, histories, curves = run_all(
        cfg, out, args.device, args.resume, args.jobs, not args.no_progress, do_refine=not args.no_refine
    )
    results = {
        "device": describe_device(args.device),
        "threads": int(cfg["train"]["threads"]),
        "jobs": args.jobs,
        "steps": int(cfg["train"]["steps"]),
        "wall_s": round(time.perf_counter() - t0, 1),
        **results,
        "config": cfg,
    }
    print(write_outputs(out, results, histories, curves))
    print(f"total wall time {results['wall_s']:.0f} s")
    return results


if __name__ == "__main__":
    main()
