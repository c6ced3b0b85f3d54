"""GPU throughput of the metric, the loss and the estimators, against the CPU of the same machine.

    python benchmarks/bench_gpu.py [--device cuda] [--threads N] [--seconds 1] [--pairs 32]
        [--config configs/realistic.toml] [--compile] [--out OUT.json]

Every case runs in one process on the device and on the CPU (``--threads``, pinned; default
every core), one after the other, so the two share the machine's state; the ratio device / CPU
is the figure to compare across machines, with kornia's SSIM on the same batch as the peer on
each. The metric and the loss at 320 x 424 (the analysis size) and 1080 x 1920; the estimators
on rendered pairs of the protocol (``--config``): the registration (``estimate_homography``),
the self-calibration started from it (``estimate_distortion``), the eigen-space classifier on
quality maps, and ``analyze_batch``, the path ``lensdist analyze`` runs. Device rows carry the
peak memory the case allocated (``torch.cuda.max_memory_allocated`` above what was allocated
before it), divided by the batch. Agreement rows compare what the device and the CPU answered
on the same pairs (the estimators' float32 work runs in another order on the GPU). ``--device cpu``
is a smoke run (both passes on the CPU, every ratio 1).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch
from kornia.metrics import ssim

from lensdist_torch import (
    EigenSpaceClassifier,
    analyze_batch,
    estimate_distortion,
    estimate_homography,
    load_config,
    load_scene,
    quality_map,
    registration_quality,
    registration_quality_loss,
    scene_names,
)
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.workflows.analyze import default_checkpoint


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def rate(fn, batch: int, device: torch.device, seconds: float, min_runs: int = 3) -> tuple[float, float | None]:
    """Pairs per second of ``fn`` after one warm-up call, and the device's peak MB per pair."""
    fn()
    _sync(device)
    peak = None
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        fn()
        _sync(device)
        peak = (torch.cuda.max_memory_allocated(device) - base) / 2**20 / batch
    runs, t0 = 0, time.perf_counter()
    while True:
        fn()
        _sync(device)
        runs += 1
        elapsed = time.perf_counter() - t0
        if runs >= min_runs and elapsed >= seconds:
            return batch * runs / elapsed, peak


def _metric_fns(a: torch.Tensor, b: torch.Tensor, compiled: bool) -> dict:
    """The metric's cases on one batch (and the compiled hard map: one shape, compiling takes a while)."""
    x = a.clone().requires_grad_(True)
    cases = {
        "hard map": lambda: quality_map(a, b),
        "smooth map": lambda: registration_quality(a, b, smooth=True),
        "loss forward + backward": lambda: registration_quality_loss(x, b).backward(),
        "kornia SSIM (peer)": lambda: ssim(a, b, 11),
    }
    if compiled:
        hard = torch.compile(lambda p, q: quality_map(p, q, validate=False), fullgraph=True)
        cases["hard map, torch.compile"] = lambda: hard(a, b)
    return cases


def metric_cases(device: torch.device, size: tuple[int, int], batches, seconds: float, compiled: bool) -> list[dict]:
    """The hard map, the smooth map, the loss forward + backward and kornia's SSIM on ``device``."""
    h, w = size
    scene = load_scene("gravel").to(device)
    reps = (1, 1, -(-h // scene.shape[-2]) + 1, -(-w // scene.shape[-1]) + 1)
    scene = scene.repeat(reps)  # tiled: 1080p is larger than the scene
    rows = []
    for batch in batches:
        a = scene[..., :h, :w].expand(batch, -1, -1, -1).contiguous()
        b = scene[..., 2 : h + 2, 1 : w + 1].expand(batch, -1, -1, -1).contiguous()
        cases = _metric_fns(a, b, compiled and device.type == "cuda" and batch == 64 and size == (320, 424))
        for name, fn in cases.items():
            with torch.set_grad_enabled(name.startswith("loss")):
                pps, peak = rate(fn, batch, device, seconds)
            rows.append(
                {"case": name, "size": f"{h}x{w}", "batch": batch, "pairs_per_s": pps, "peak_mb_per_pair": peak}
            )
    return rows


def protocol_pairs(config_path: str | None, n: int) -> tuple[torch.Tensor, torch.Tensor, object]:
    """``n`` rendered test pairs of the protocol in ``config_path`` (default settings without one)."""
    cfg = load_config(config_path)
    scenes = [load_scene(s) for s in scene_names()]
    params = draw_pairs(cfg, "test", list(range(n)), len(scenes))
    img1, img2 = render_pairs(scenes, params, cfg)
    return img1, img2, cfg


def estimator_cases(device: torch.device, img1, img2, cfg, seconds: float) -> tuple[list[dict], dict]:
    """The estimators on ``device``: rates, and their answers for the agreement rows."""
    a, b = img1.to(device), img2.to(device)
    n = a.shape[0]
    h, w = a.shape[-2:]
    out: dict = {}

    def register():
        out["H"] = estimate_homography(a, b, config=cfg.registration)[0]

    def selfcal():
        k2, k4, _, _ = estimate_distortion(a, b, init=out["H"], config=cfg.selfcal)
        out["delta"] = delta_avg(k2, k4, h, w)

    rows = []
    for name, fn, batch in (("registration", register, n), ("self-calibration", selfcal, n)):
        pps, peak = rate(fn, batch, device, seconds, min_runs=2)
        rows.append({"case": name, "size": f"{h}x{w}", "batch": batch, "pairs_per_s": pps, "peak_mb_per_pair": peak})
    clf = EigenSpaceClassifier.load(default_checkpoint("delta_avg")).to(device)
    feats = quality_map(a, b).flatten(1).repeat(max(1, 256 // n), 1)
    pps, peak = rate(lambda: clf(feats), feats.shape[0], device, seconds)
    rows.append({"case": "eigen-space classifier", "size": "features", "batch": feats.shape[0], "pairs_per_s": pps,
                 "peak_mb_per_pair": peak})

    def analyze():
        out["answers"] = analyze_batch(a, b, config=cfg, device=device)

    pps, peak = rate(analyze, n, device, seconds, min_runs=1)
    rows.append({"case": "analyze_batch (lensdist analyze)", "size": f"{h}x{w}", "batch": n, "pairs_per_s": pps,
                 "peak_mb_per_pair": peak})
    return rows, out


def agreement(cpu: dict, dev: dict) -> dict:
    """How far the device's answers are from the CPU's on the same pairs."""
    h_err = (cpu["H"].cpu() - dev["H"].cpu()).abs().amax(dim=(1, 2))
    d_err = (cpu["delta"].cpu() - dev["delta"].cpu()).abs()
    ca = [r.class_label for r in cpu["answers"]]
    da = [r.class_label for r in dev["answers"]]
    dd = [abs(x.delta_avg - y.delta_avg) for x, y in zip(cpu["answers"], dev["answers"], strict=True)
          if x.delta_avg is not None and y.delta_avg is not None]
    return {
        "registration_max_abs_H_diff": float(h_err.nan_to_num(float("inf")).max()),
        "selfcal_delta_avg_max_abs_diff_px": float(d_err.nan_to_num(float("inf")).max()),
        "selfcal_delta_avg_median_abs_diff_px": float(d_err.nan_to_num(float("inf")).median()),
        "analyze_same_class": sum(x == y for x, y in zip(ca, da, strict=True)),
        "analyze_same_registered_by": sum(x.registered_by == y.registered_by
                                          for x, y in zip(cpu["answers"], dev["answers"], strict=True)),
        "analyze_registered_by_self_calibration": sum(r.registered_by == "self-calibration" for r in dev["answers"]),
        "analyze_pairs": len(ca),
        "analyze_delta_avg_max_abs_diff_px": max(dd) if dd else None,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--seconds", type=float, default=1.0)
    p.add_argument("--pairs", type=int, default=32)
    p.add_argument("--config", default="configs/realistic.toml")
    p.add_argument(
        "--compile", action="store_true", help="also the compiled hard map on the device (320 x 424, batch 64)"
    )
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        p.error("argument --device: CUDA is not available on this machine")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cpu = torch.device("cpu")
    result = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "cpu_threads": args.threads, "torch": torch.__version__, "rows": []}
    img1, img2, cfg = protocol_pairs(args.config, args.pairs)
    answers = {}
    for where in (device, cpu):
        rows = metric_cases(where, (320, 424), (1, 16, 64, 256), args.seconds, args.compile)
        rows += metric_cases(where, (1080, 1920), (1, 8), args.seconds, args.compile)
        est, answers[where.type] = estimator_cases(where, img1, img2, cfg, args.seconds)
        for r in rows + est:
            r["on"] = where.type
        result["rows"] += rows + est
        print(f"{where}: done", flush=True)
    result["agreement"] = agreement(answers["cpu"], answers[device.type])
    key = {(r["case"], r["size"], r["batch"], r["on"]): r for r in result["rows"]}
    print(f"device: {result['device']}; CPU: {args.threads} threads; torch {torch.__version__}")
    print(
        "| case | size | batch | device pairs/s | CPU pairs/s | device / CPU | x SSIM (device) | "
        "device peak MB / pair |"
    )
    print("|---|---|---|---|---|---|---|---|")
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    for r in result["rows"]:
        if r["on"] != device.type:
            continue
        c = key.get((r["case"], r["size"], r["batch"], "cpu"))
        peer = key.get(("kornia SSIM (peer)", r["size"], r["batch"], device.type))
        r["device_over_cpu"] = r["pairs_per_s"] / c["pairs_per_s"] if c else None
        r["over_ssim"] = r["pairs_per_s"] / peer["pairs_per_s"] if peer else None
        print(
            f"| {r['case']} | {r['size']} | {r['batch']} | {r['pairs_per_s']:.1f} | "
            f"{fmt(c and c['pairs_per_s'], '.1f')} | "
            f"{fmt(r['device_over_cpu'], '.1f')} | {fmt(r['over_ssim'], '.2f')} | {fmt(r['peak_mb_per_pair'], '.1f')} |"
        )
    print(json.dumps(result["agreement"]))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
