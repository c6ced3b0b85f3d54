"""End-to-end speed of the pair protocol at 320 x 424, split by stage, and peak memory.

    python benchmarks/bench_generate.py [--pairs 64] [--batch 16] [--threads 2] [--workers 2]

Part 1 (one process, ``--threads`` threads): seconds per pair of each stage (draw, render,
registration, warp, metric) over ``--pairs`` training pairs, and the registration's accuracy
against the true motion on undistorted copies of the same pairs (median / max corner error).
Part 2: ``lensdist generate`` itself with ``--workers`` processes of one thread each, pairs per
second end to end, shards written, and the peak RSS of the biggest process.

The peer (``--ecc``, needs opencv): the same pairs registered by OpenCV's ECC
(``cv2.findTransformECC``, MOTION_HOMOGRAPHY, from OpenCV's phase correlation's translation
(Hann window), 50 iterations or 1e-6, Gaussian 5 x 5), one pair at a time on ``--threads``
OpenCV threads, in the same run. ``ecc_ratio`` is part 1's pairs per second over the same
pipeline's with ECC's seconds in place of the registration's (how many times faster generation
is than it would be with ECC), and ``ecc_corner_error_*`` ECC's accuracy on the undistorted
copies (failures, ``cv2.error``, count as infinite).

    python benchmarks/bench_generate.py --pairs 64 --threads 2 --ecc --e2e-pairs 0
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import tempfile
import time


def _ecc(i1, i2, threads: int) -> tuple:
    """OpenCV ECC's seconds for the pairs (B, C, H, W) and its (B, 3, 3) homographies img1 -> img2 (NaN: failed)."""
    import cv2
    import numpy as np
    import torch

    cv2.setNumThreads(threads)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-6)
    a = i1.mean(1).float().numpy()
    b = i2.mean(1).float().numpy()
    out = torch.full((len(a), 3, 3), float("nan"), dtype=torch.float64)
    t0 = time.perf_counter()
    for k in range(len(a)):
        hann = cv2.createHanningWindow(a[k].shape[::-1], cv2.CV_64F)
        (dx, dy), _ = cv2.phaseCorrelate(a[k].astype(np.float64), b[k].astype(np.float64), hann)
        warp = np.array([[1, 0, dx], [0, 1, dy], [0, 0, 1]], dtype=np.float32)
        try:  # ECC's warp maps the template's (img1) pixels into the input (img2): img1(p) = img2(W p)
            _, warp = cv2.findTransformECC(a[k], b[k], warp, cv2.MOTION_HOMOGRAPHY, criteria, None, 5)
            out[k] = torch.from_numpy(warp.astype(np.float64))
        except cv2.error:
            pass
    return time.perf_counter() - t0, out


def stages(pairs: int, batch: int, threads: int, ecc: bool = False) -> dict:
    import torch

    torch.set_num_threads(threads)
    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data import draw_pairs, render_pairs
    from lensdist_torch.data.shards import load_scenes
    from lensdist_torch.geometry import corner_error
    from lensdist_torch.metric import registration_error_counts
    from lensdist_torch.registration import estimate_homography, warp_to_reference

    cfg = LensdistConfig()
    scenes, _ = load_scenes(cfg)
    t = dict.fromkeys(["draw", "render", "registration", "warp", "metric"], 0.0)
    errors, ecc_seconds, ecc_errors = [], 0.0, []
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
        if ecc:
            ecc_seconds += _ecc(i1, i2, threads)[0]
        # accuracy on the same pairs without distortion, where the true H = M^-1 is exact
        p.k2.zero_()
        p.k4.zero_()
        u1, u2 = render_pairs(scenes, p, cfg)
        Hu, _ = estimate_homography(u1, u2)
        errors.append(corner_error(Hu.double(), torch.linalg.inv(p.M), cfg.image.height, cfg.image.width))
        if ecc:
            He = _ecc(u1, u2, threads)[1]
            e = corner_error(He.nan_to_num(0.0), torch.linalg.inv(p.M), cfg.image.height, cfg.image.width)
            ecc_errors.append(torch.where(torch.isfinite(He).all(dim=(1, 2)), e, torch.full_like(e, float("inf"))))
    err = torch.cat(errors)
    total = sum(t.values())
    peer = {}
    if ecc:
        ee = torch.cat(ecc_errors)
        peer = {"ecc_ms_per_pair": 1000 * ecc_seconds / pairs,
                "ecc_ratio": (total - t["registration"] + ecc_seconds) / total,
                "ecc_corner_error_median_px": float(ee.median()),
                "ecc_failed": int((~torch.isfinite(ee)).sum())}
    return {
        "threads": threads,
        "batch": batch,
        "pairs": pairs,
        "ms_per_pair": {k: 1000 * v / pairs for k, v in t.items()},
        "pairs_per_s": pairs / total,
        "corner_error_median_px": float(err.median()),
        "corner_error_max_px": float(err.max()),
        **peer,
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
    p.add_argument("--ecc", action="store_true", help="OpenCV's ECC on the same pairs, the peer (needs opencv)")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    a = stages(args.pairs, args.batch, args.threads, ecc=args.ecc)
    print(json.dumps(a, indent=2))
    b = end_to_end(args.e2e_pairs, args.workers, args.batch) if args.e2e_pairs else None
    print(json.dumps(b, indent=2))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"stages": a, "end_to_end": b}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
