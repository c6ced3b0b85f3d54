"""Accuracy on a scene never used in training: fit on one embedded scene, test on the other.

    python benchmarks/bench_unseen_scene.py --data results/reproduce/data [--train-scene gravel]

Uses a data set written by `lensdist generate` / `lensdist reproduce` (both scenes). The
eigen-space classifier (10 EV, Delta_avg) and the regression are fitted on the training pairs of
``--train-scene`` only and evaluated on the test pairs of the other scene; the
self-calibration, which learns nothing, is run on the same unseen test pairs. Prints one
Markdown table and writes JSON with ``--json``.
"""

from __future__ import annotations

import argparse
import json

import torch


def _subset(data: dict, mask: torch.Tensor) -> dict:
    return {k: (v[mask] if isinstance(v, torch.Tensor) else v) for k, v in data.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data", required=True)
    p.add_argument("--train-scene", default="gravel")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    from lensdist_torch.data.shards import load_scenes, load_set, read_manifest
    from lensdist_torch.workflows.evaluate import (
        evaluate_classifier,
        evaluate_regressor,
        evaluate_selfcal,
        features_of,
        fit_classifier,
        fit_regressor,
    )

    scenes_ids = read_manifest(args.data)["scenes"]
    if args.train_scene not in scenes_ids or len(scenes_ids) < 2:
        raise SystemExit(f"--train-scene must be one of the data set's scenes {scenes_ids}")
    s_train = scenes_ids.index(args.train_scene)
    train, test = load_set(args.data, "train"), load_set(args.data, "test")
    cfg = train["config"]
    train = _subset(train, train["scene"] == s_train)
    test = _subset(test, test["scene"] != s_train)
    rows = {}
    eig = fit_classifier(train, cfg, 10, "delta_avg")
    rows["eigen-space 10 EV, delta_avg"] = evaluate_classifier(eig, test)
    reg = fit_regressor(train, cfg, features_of(train, cfg))
    rows["regression, delta_avg"] = evaluate_regressor(reg, test, features_of(test, cfg))["delta_avg"]
    scenes, _ = load_scenes(cfg)
    rows["selfcal, delta_avg"] = evaluate_selfcal(test, cfg, scenes, progress=False)["delta_avg"]
    print(f"trained on {args.train_scene} ({int(train['index'].numel())} pairs), tested on the other scene "
          f"({int(test['index'].numel())} pairs, {int((test['class_avg'] == 4).sum())} of them class R)")
    print("| method | rate | R rejected | RMSE class 1-4 (px) | confident share, rate |")
    print("|---|---|---|---|---|")
    for name, f in rows.items():
        rmse = ", ".join(f"{v:.2f}" for v in f["rmse_px"])
        conf = f"{f['confident_share']:.0f} %, {f['confident_rate']:.1f} %" if "confident_share" in f else "-"
        print(f"| {name} | {f['rate']:.1f} % | {f['rejected_R']} of {f['n_R']} | {rmse} | {conf} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
