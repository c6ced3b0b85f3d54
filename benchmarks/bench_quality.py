"""Speed and peak memory of the quality metric at 320 x 424 (issue: the metric's benchmark).

    python benchmarks/bench_quality.py [--seconds 2] [--threads 1 2] [--batches 1 64] [--json out.json]
        [--kinds hard smooth] [--baseline DIR] [--repeats 3]

For each thread count and batch size: pairs per second of the hard map, the smooth map and
smooth forward + backward, with kornia's SSIM on the same batch as the peer measured in the
same run (absolute times drift on a shared machine; the ratios are what to compare). Each case
runs in a fresh process, so peak memory is that process's peak RSS above its baseline
after the inputs were made.

Before/after: ``--baseline DIR`` also times the ``lensdist_torch`` package found in DIR (e.g.
``git archive OLD lensdist_torch | tar -x -C DIR``) in the same run, the two alternating case by
case (``--repeats`` rounds; the best of each is reported), and prints new / old per case.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import time

KINDS = ["hard", "smooth", "smooth_fwd_bwd", "kornia_ssim"]


def _case(args):
    kind, batch, threads, seconds, code = args
    if code != "current":  # a baseline checkout: its package shadows the installed one
        import sys

        sys.path.insert(0, code)
    import torch

    torch.set_num_threads(threads)
    from kornia.metrics import ssim

    from lensdist_torch import quality_map, registration_quality, registration_quality_loss
    from lensdist_torch.core.images import load_scene  # a module path: a baseline may predate core's exports

    scene = load_scene("gravel")
    a = scene[..., :320, :424].repeat(batch, 1, 1, 1).contiguous()
    b = scene[..., 2:322, 1:425].repeat(batch, 1, 1, 1).contiguous()
    if kind == "smooth_fwd_bwd":
        a.requires_grad_(True)

    def run():
        if kind == "hard":
            quality_map(a, b)
        elif kind == "smooth":
            with torch.no_grad():
                registration_quality(a, b, smooth=True)
        elif kind == "smooth_fwd_bwd":
            registration_quality_loss(a, b).backward()
        elif kind == "kornia_ssim":
            with torch.no_grad():
                ssim(a, b, 11)
        else:
            raise ValueError(kind)

    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    run()  # warm-up
    n, t0 = 0, time.perf_counter()
    while True:
        run()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= seconds and n >= 3:
            break
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "kind": kind,
        "batch": batch,
        "threads": threads,
        "code": code,
        "pairs_per_s": n * batch / dt,
        "peak_mb": max(0, peak - base) / 1024,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=2.0)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    p.add_argument("--kinds", nargs="+", default=KINDS, choices=KINDS, help="cases to time (default: all)")
    p.add_argument("--baseline", default=None, help="directory holding another lensdist_torch to compare with")
    p.add_argument("--repeats", type=int, default=1, help="rounds per case; the best is reported")
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    kinds = list(dict.fromkeys(args.kinds + ["kornia_ssim"]))
    codes = ["current"] + ([args.baseline] if args.baseline else [])
    ctx = mp.get_context("spawn")
    best: dict = {}
    for _ in range(args.repeats):
        for threads in args.threads:
            for batch in args.batches:
                for kind in kinds:
                    for code in codes if kind != "kornia_ssim" else ["current"]:
                        with ctx.Pool(1) as pool:
                            r = pool.apply(_case, ((kind, batch, threads, args.seconds, code),))
                        key = (kind, batch, threads, code)
                        if key not in best or r["pairs_per_s"] > best[key]["pairs_per_s"]:
                            best[key] = r
    rows = list(best.values())
    print("| threads | batch | case | code | pairs/s | x kornia SSIM | peak MB |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        peer = best[("kornia_ssim", r["batch"], r["threads"], "current")]
        r["ratio_to_ssim"] = r["pairs_per_s"] / peer["pairs_per_s"]
        code = "current" if r["code"] == "current" else "baseline"
        print(
            f"| {r['threads']} | {r['batch']} | {r['kind']} | {code} | {r['pairs_per_s']:.1f} "
            f"| {r['ratio_to_ssim']:.2f} | {r['peak_mb']:.0f} |"
        )
    for threads in args.threads:
        for batch in args.batches:
            if {"smooth", "smooth_fwd_bwd"} <= set(kinds):
                ratio = (
                    best[("smooth", batch, threads, "current")]["pairs_per_s"]
                    / best[("smooth_fwd_bwd", batch, threads, "current")]["pairs_per_s"]
                )
                print(
                    f"threads {threads}, batch {batch}: smooth forward+backward costs {ratio:.2f} x the smooth forward"
                )
            if args.baseline:
                for kind in args.kinds:
                    if kind == "kornia_ssim":
                        continue
                    new = best[(kind, batch, threads, "current")]["pairs_per_s"]
                    old = best[(kind, batch, threads, args.baseline)]["pairs_per_s"]
                    print(f"threads {threads}, batch {batch}, {kind}: current / baseline = {new / old:.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
