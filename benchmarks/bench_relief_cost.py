"""What the plane + parallax test costs a user's analysis: ``analyze_batch`` with and without it.

The same rendered pairs of the protocol's test set, analysed with the default settings
(``selfcal.parallax`` = 5, the test on every pair) and with ``selfcal.parallax = 0`` (planar
scenes only), alternately in one process with pinned threads; reports ms per pair of each, the
ratio, and how many pairs each says "cannot tell" for, and why. ``--against`` times the default
against another single setting instead (e.g. ``selfcal.parallax_evidence=false``: the evidence's
cost).

    python benchmarks/bench_relief_cost.py --n 48 --threads 1 [--config configs/realistic.toml]
    python benchmarks/bench_relief_cost.py --n 24 --threads 1 --config configs/realistic.toml \\
        --against selfcal.parallax_evidence=false
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from bench_relief_test import condition_config  # the config layer's own --set parsing and checks

from lensdist_torch import analyze_batch, load_scene
from lensdist_torch.data import draw_pairs, render_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default=None)
    ap.add_argument("--n", type=int, default=48, help="test pairs, spread over the set")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=2, help="alternating timed passes per setting (the best counts)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--against",
        default="selfcal.parallax=0",
        help="SECTION.KEY=VALUE (TOML value): the setting timed against the default",
    )
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = condition_config(a.config, [])
    total = cfg.protocol.n_test_distorted + cfg.protocol.n_test_undistorted
    idx = list(range(0, total, max(1, total // a.n)))[: a.n]
    params = draw_pairs(cfg, "test", idx, len(cfg.protocol.scenes))
    img1, img2 = render_pairs([load_scene(s) for s in cfg.protocol.scenes], params, cfg)
    settings = {a.against: condition_config(a.config, [a.against]), "default": cfg}
    best, answers = {k: float("inf") for k in settings}, {}
    for _ in range(a.repeats):
        for name, c in settings.items():
            t0 = time.perf_counter()
            res = [
                r
                for s in range(0, len(idx), a.batch)
                for r in analyze_batch(img1[s : s + a.batch], img2[s : s + a.batch], config=c)
            ]
            best[name] = min(best[name], time.perf_counter() - t0)
            answers[name] = res
    out = {"config": a.config, "pairs": len(idx), "threads": a.threads}
    for name, res in answers.items():
        reasons = [code for r in res for code in r.cannot_tell_reasons]
        out[name] = {
            "ms_per_pair": round(1000 * best[name] / len(idx), 1),
            "cannot_tell": sum(r.cannot_tell for r in res),
            "reasons": {c: reasons.count(c) for c in sorted(set(reasons))},
        }
    out["ratio"] = round(best["default"] / best[a.against], 2)  # default / against
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
