"""The registration-quality metric as an auxiliary loss in learned registration, end to end.

A small HomographyNet-style network (two grey patches in, four corner offsets out) is trained
*unsupervised*: the predicted homography warps patch A onto patch B with
``kornia.geometry.warp_perspective`` and a loss compares the two. Arms, same seed, same data,
same number of steps:

* ``l1``                    photometric L1 alone;
* ``l1_quality``            L1 + lambda * ``RegistrationQualityLoss`` (after an L1-only warm-up);
* ``l1_quality_distorted``  the same on pairs whose two patches carry the same radial lens
                            distortion (SPEC 6), which no homography can explain.

Usage (one command, from the repository root)::

    python train/learned_registration.py --config configs/learned_registration.toml \\
        --out results/learned_registration [--device cpu|cuda] [--arms l1,l1_quality] \\
        [--steps N] [--resume] [--set train.batch_size=8 ...]

Writes ``results.json``, ``results.md``, ``config_used.json``, the training curves (when
matplotlib is present) and ``checkpoints/<arm>.pt`` under ``--out``. The work is done by the
``learnreg`` package next to this script.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from learnreg.config import config_from_args, load_train_config
from learnreg.data import load_scenes
from learnreg.loop import train_arm
from learnreg.report import evaluate, write_outputs


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="configs/learned_registration.toml")
    ap.add_argument("--out", default="results/learned_registration")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--arms", default=None, help="comma-separated arms (default: all in the config)")
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--resume", action="store_true", help="continue each arm from its checkpoint")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override, e.g. train.batch_size=8")
    ap.add_argument("--no-progress", action="store_true")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    cfg = config_from_args(args, load_train_config)
    threads = int(cfg["train"]["threads"])
    torch.set_num_threads(threads)  # the floats can depend on it: pinned by the config
    arms = args.arms.split(",") if args.arms else list(cfg["arms"])
    for a in arms:
        if a not in cfg["arms"]:
            raise SystemExit(f"unknown arm {a!r}; the config has {list(cfg['arms'])}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scenes = load_scenes(cfg)

    results, histories, t_start = {}, {}, time.perf_counter()
    for name in arms:
        model, hist, wall = train_arm(
            cfg, name, out, args.device, args.resume, progress=not args.no_progress, scenes=scenes
        )
        r = evaluate(model, cfg, bool(cfg["arms"][name]["distorted"]), args.device, scenes)
        r.update(train_wall_s=round(wall, 1), steps=int(cfg["train"]["steps"]), threads=threads)
        results[name], histories[name] = r, hist
        print(
            f"{name}: mean {r['mean_corner_error']:.3f} px, median {r['median_corner_error']:.3f} px, "
            f"<1 px {r['share_under_1px']:.1%} (identity {r['identity_mean_corner_error']:.2f} px)",
            flush=True,
        )
    wall = time.perf_counter() - t_start
    print(write_outputs(out, results, histories, cfg, wall))
    print(f"total wall time {wall:.0f} s")
    return results


if __name__ == "__main__":
    main()
