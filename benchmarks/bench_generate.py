"""End-to-end speed of the pair protocol at 320 x 424, split by stage, and peak memory.

    python benchmarks/bench_generate.py [--pairs 64] [--batch 16] [--threads 2] [--workers 2]

Part 1 (one process, ``--threads`` threads): seconds per pair of each stage (draw, render,
registration, warp, metric) over ``--pairs`` training pairs, and the registration's accuracy
against the true motion on undistorted copies of the same pairs (median / max corner error).
Part 2: ``lensdist generate`` itself with ``--workers`` processes of one thread each, pairs per
second end to end, shards written, and the peak RSS of the biggest process.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import tempfile
import time


def stages(pairs: int, batch: int, threads: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data import draw_pairs, render_pairs
    from lensdist_torch.data.shards import load_scenes
    from lensdist_torch.geometry import corner_error, estimate_homography, warp_to_reference
    from lensdist_torch.metric import registration_error_counts

    cfg = LensdistConfig()
    scenes, _ = load_scenes(cfg)
    t = dict.fromkeys(["draw", "render", "registration", "warp", "metric"], 0.0)
    errors = []
    render_pairs(scenes, draw_pairs(cfg, "train", range(2), len(scenes)), cfg)  # warm-up
    for s in range(0, pairs, batch):
        idx = range(s, min(s + batch, pairs))
        t0 = time.perf_counter()
        p = draw_pairs(cfg, "train", idx, len(scenes))
        t1 = time.perf_counter()
        i1, i2 = render_pairs(scenes, p, cfg)
        t2 = time.perf_counter()
        H, info = estimate_homography(i1, i2)
        t3 = time.perf_counter()
        w, v = warp_to_reference(i2, H)
        t4 = time.perf_counter()
        registration_error_counts(i1, w, v, config=cfg.quality, validate=False)
        t5 = time.perf_counter()
        for k, a, b in (
            ("draw", t0, t1),
            ("render", t1, t2),
            ("registration", t2, t3),
            ("warp", t3, t4),
            ("metric", t4, t5),
        ):
            t[k] += b - a
        # accuracy on the same pairs without distortion, where the true H = M^-1 is exact
        p.k2.zero_()
        p.k4.zero_()
        u1, u2 = render_pairs(scenes, p, cfg)
        Hu, _ = estimate_homography(u1, u2)
        errors.append(corner_error(Hu.double(), torch.linalg.inv(p.M), cfg.image.height, cfg.image.width))
    err = torch.cat(errors)
    total = sum(t.values())
    return {
        "threads": threads,
        "batch": batch,
        "pairs": pairs,
        "ms_per_pair": {k: 1000 * v / pairs for k, v in t.items()},
        "pairs_per_s": pairs / total,
        "corner_error_median_px": float(err.median()),
        "corner_error_max_px": float(err.max()),
    }


def end_to_end(pairs: int, workers: int, batch: int) -> dict:
    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data import generate

    base = LensdistConfig()
    shard = max(1, pairs // (2 * workers))
    cfg = dataclasses.replace(base, protocol=dataclasses.replace(base.protocol, n_train=pairs, shard_size=shard))
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        summary = generate(cfg, out, sets=("train",), workers=workers, batch_size=batch, progress=False)
        dt = time.perf_counter() - t0
    peak_self = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    peak_children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return {
        "workers": workers,
        "pairs": pairs,
        "seconds": dt,
        "pairs_per_s": pairs / dt,
        "paper_protocol_minutes": 12500 / (pairs / dt) / 60,
        "peak_rss_mb_main": peak_self,
        "peak_rss_mb_worker": peak_children,
        "registration_failed": summary["sets"]["train"].get("registration_failed"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--pairs", type=int, default=64)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--e2e-pairs", type=int, default=256)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    a = stages(args.pairs, args.batch, args.threads)
    print(json.dumps(a, indent=2))
    b = end_to_end(args.e2e_pairs, args.workers, args.batch)
    print(json.dumps(b, indent=2))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"stages": a, "end_to_end": b}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
