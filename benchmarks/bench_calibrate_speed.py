"""The speed of `lensdist calibrate` against its goals: 22 frames of 384 x 288 in 60 s on 2 cores
(and 300 of 1920 x 1080 in 10 min).

Renders the goal's sequence (``synthetic_sequence(22, k2, k4, size=(288, 384), scene="gravel",
seed=0, relief=0.02, realistic=True)``, eq. 4 scaled from the library's largest coefficients to
Delta_avg = 7.5 px; ``--rotation 3 --altitude 0.1`` for a camera that turns) as 8-bit PNGs into a
temporary folder and times the user's path, ``calibrate_path(folder, method="auto")`` (the direct
path and the multi-view path on COLMAP, combined), and as a peer measured in the same run the
direct path alone (``method="direct"``), so the figure is a ratio as well as seconds. Each run is
a fresh process (spawned), so its peak resident memory (``VmHWM`` of /proc/self/status, which exec
resets: ``ru_maxrss`` keeps the parent's resident size at the fork, 6-7 GB with 300 1080p frames in
memory, and is the fallback where /proc is missing) is its own; torch and
COLMAP use ``--threads`` threads. Writes JSON to ``--out``.

    python benchmarks/bench_calibrate_speed.py --threads 2 --repeats 2 --out docs/results/bench_calibrate_speed.json
    python benchmarks/bench_calibrate_speed.py --frames 300 --size 1080 1920 \\
        --out docs/results/bench_calibrate_speed_1080p.json

``--frames`` and ``--size`` render another sequence (the same lens scaled to the frame: Delta_avg 7.5 px
times width / 384); its goal is 60 s for the first, 180 s for 80 frames of 968 x 608 and 600 s for
any other (the 1080p video's).
``--upsample F`` renders at 1 / F of the size (rows and columns rounded up to 8) and enlarges the frames F times
(bilinear, about the centre, cropped to the size): rendering 1080p frames takes seconds each. Eq. 4 is
applied to the rendered frames with (k2 F^2, k4 F^4), which is (k2, k4) in the enlarged frames' pixels.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import json
import math
import multiprocessing
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import torch

from lensdist_torch.calibration import calibrate_path, synthetic_sequence
from lensdist_torch.config import LensdistConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.core.png import encode_png
from lensdist_torch.geometry import delta_avg

SIZE = (288, 384)
GOAL_S = 60.0
GOAL_LONG_S = 600.0
GOALS_S = {(22, SIZE): GOAL_S, (80, (608, 968)): 180.0}  # (frames, (H, W)) -> seconds; others GOAL_LONG_S


def coefficients(target: float = 7.5, size: tuple[int, int] = SIZE) -> tuple[float, float]:
    """(k2, k4) whose Delta_avg at ``size`` is ``target`` px, eq. 4's (k2, k4) at 384 x 288 on the line to the
    library's largest pair, rescaled to ``size``'s width (the same lens: k2 by s^-2, k4 by s^-4, s = W / 384)."""
    d, lo, hi = LensdistConfig().distortion, 0.0, 1.0
    s = size[1] / SIZE[1]
    for _ in range(60):
        mid = (lo + hi) / 2
        k2, k4 = mid * d.k2_max / s**2, mid * d.k4_max / s**4
        lo, hi = (mid, hi) if float(delta_avg([k2], [k4], *size)[0]) < target else (lo, mid)
    return lo * d.k2_max / s**2, lo * d.k4_max / s**4


def render(n: int, size: tuple[int, int], *, upsample: int = 1, rotation: float = 0.2,
           altitude: float = 0.0) -> torch.Tensor:
    """The goal's sequence of ``n`` frames (N, 1, H, W) at ``size`` through :func:`coefficients`' lens (module
    docstring): rendered at 1 / ``upsample`` of the size, rows and columns rounded up to the blocks, enlarged
    about the same centre and cropped, so eq. 4 with (k2 up^2, k4 up^4) there is (k2, k4) in the frames' pixels."""
    up = upsample
    rendered = (8 * math.ceil(size[0] / up / 8), 8 * math.ceil(size[1] / up / 8))
    k2, k4 = coefficients(7.5 * size[1] / SIZE[1], size)
    frames, _ = synthetic_sequence(n, k2 * up**2, k4 * up**4, size=rendered, scene="gravel", seed=0,
                                   relief=0.02, realistic=True, rotation_deg=rotation, altitude=altitude)
    if up > 1:
        frames = torch.nn.functional.interpolate(frames, scale_factor=up, mode="bilinear", align_corners=False)
        top, left = (frames.shape[-2] - size[0]) // 2, (frames.shape[-1] - size[1]) // 2
        frames = frames[..., top:top + size[0], left:left + size[1]]
    return frames


def write_frames(frames: torch.Tensor, folder) -> list[str]:
    """(N, 1, H, W) frames in [0, 1] as 8-bit PNGs ``frame_000.png`` ... in ``folder``; their names, in order."""
    names = [f"frame_{j:03d}.png" for j in range(len(frames))]
    for name, f in zip(names, frames):
        (Path(folder) / name).write_bytes(encode_png((f.clamp(0, 1) * 255).round().to(torch.uint8)))
    return names


def _peak_mb() -> float:
    """This process's peak resident memory (MB) since its exec (module docstring)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


#: The stages timed in a run: (name, module, function), each function timed where ``calibrate_path`` calls it.
STAGES = (
    ("multi-view path", "lensdist_torch.calibration.controllers.calibrate", "multiview_path"),
    ("extraction", "lensdist_torch.calibration.features", "extract_in_shards"),
    ("matching", "pycolmap", "match_exhaustive"),
    ("matching", "pycolmap", "match_sequential"),
    ("verification", "lensdist_torch.calibration.features", "verify_in_shards"),
    ("homography model", "lensdist_torch.calibration.controllers.multiview_path", "planar_path"),
    ("mapping", "pycolmap", "incremental_mapping"),
    ("models", "lensdist_torch.calibration.controllers.multiview_path", "self_calibrate_reconstruction"),
)


@contextlib.contextmanager
def _timed_stages(seconds: dict):
    """Adds each stage's wall seconds (:data:`STAGES`) to ``seconds`` while the block runs."""
    saved = []
    for name, module, function in STAGES:
        mod = importlib.import_module(module)
        f = getattr(mod, function)

        def timed(*args, _f=f, _name=name, **kwargs):
            t = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                seconds[_name] = seconds.get(_name, 0.0) + time.perf_counter() - t

        saved.append((mod, function, f))
        setattr(mod, function, timed)
    try:
        yield seconds
    finally:
        for mod, function, f in reversed(saved):
            setattr(mod, function, f)


def _one(folder: str, method: str, threads: int) -> dict:
    """One timed run in this (spawned) process, with its stages' seconds (the direct path: the rest)."""
    torch.set_num_threads(threads)
    settings = LensdistConfig()
    settings = dataclasses.replace(settings, multiview=dataclasses.replace(settings.multiview, num_threads=threads))
    t0 = time.perf_counter()
    with _timed_stages({}) as stages:
        res = calibrate_path(folder, method=method, settings=settings)
    seconds = time.perf_counter() - t0
    stages["direct path and the rest"] = seconds - stages.get("multi-view path", 0.0)
    mv = res.get("multiview") or {}
    return {"method": method, "seconds": seconds, "stages_s": stages, "peak_rss_mb": _peak_mb(),
            "answered_by": res["method"], "class": res["class"], "reason": res["reason"],
            "delta_avg_user_px": res["delta_avg_user_px"], "delta_avg_user_interval": res["delta_avg_user_interval"],
            "multiview": {k: mv.get(k) for k in ("class", "reason", "delta_avg_user_px", "delta_avg_user_interval",
                                                 "rotation_spread_deg", "registered", "observations",
                                                 "reconstructions")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--rotation", type=float, default=0.2, help="synthetic_sequence's rotation_deg (its default: 0.2)")
    ap.add_argument("--altitude", type=float, default=0.0)
    ap.add_argument("--frames", type=int, default=22)
    ap.add_argument("--size", type=int, nargs=2, default=list(SIZE), metavar=("H", "W"))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--upsample", type=int, default=1)
    args = ap.parse_args()
    size, up = tuple(args.size), args.upsample
    goal = GOALS_S.get((args.frames, size), GOAL_LONG_S)
    # rendered at 1 / up of the size, rows and columns rounded up to the blocks, enlarged up times about the same
    # centre and cropped to the size: eq. 4 about the centre with (k2 up^2, k4 up^4) becomes (k2, k4) in the frames'
    # pixels
    rendered = (8 * math.ceil(size[0] / up / 8), 8 * math.ceil(size[1] / up / 8))
    k2, k4 = coefficients(7.5 * size[1] / SIZE[1], size)
    frames = render(args.frames, size, upsample=up, rotation=args.rotation, altitude=args.altitude)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        write_frames(frames, tmp)
        del frames  # written: the runs read them from the folder
        for _ in range(args.repeats):
            for method in ("direct", "auto"):
                pool = multiprocessing.get_context("spawn").Pool(1)  # a fresh process: its own peak memory
                runs.append(pool.apply(_one, (tmp, method, args.threads)))
                pool.close()
                pool.join()  # not terminate: COLMAP's signal handler would print a stack trace
                print(f"{method}: {runs[-1]['seconds']:.1f} s, {runs[-1]['peak_rss_mb']:.0f} MB, "
                      f"class {runs[-1]['class']}, {runs[-1]['delta_avg_user_px']:.2f} px", flush=True)
    best = {m: min(r["seconds"] for r in runs if r["method"] == m) for m in ("direct", "auto")}
    out = {
        "command": "python benchmarks/bench_calibrate_speed.py "
        + " ".join(f"--{k} {' '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in vars(args).items()
                   if k != "out")
        + f" --out {args.out}",
        "sequence": {
            "frames": args.frames,
            "size": list(size),
            "scene": "gravel",
            "seed": 0,
            "relief": 0.02,
            "realistic": True,
            "rotation_deg": args.rotation,
            "altitude": args.altitude,
            "k2": k2,
            "k4": k4,
            "upsample": up,
            "rendered_size": list(rendered),
            "truth_delta_avg_px": float(delta_avg([k2], [k4], *size)[0]),
        },
        "machine": {
            "cpus": multiprocessing.cpu_count(),
            "threads": args.threads,
            "python": platform.python_version(),
            "load_average_at_end": list(os.getloadavg()),
        },
        "goal_s": goal,
        "best_seconds": best,
        "auto_over_direct": best["auto"] / best["direct"],
        "meets_goal": best["auto"] <= goal,
        "runs": runs,
    }
    atomic_write_text(args.out, json.dumps(out, indent=1, allow_nan=False) + "\n")
    print(
        f"auto {best['auto']:.1f} s = {out['auto_over_direct']:.1f} x direct {best['direct']:.1f} s (goal {goal:g} s)"
    )


if __name__ == "__main__":
    main()
