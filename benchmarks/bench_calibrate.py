"""Benchmark of the sequence calibration (lensdist_torch.calibration.direct.calibrate_sequence).

M synthetic sequences of 20 frames (calibration.controllers.calibrate.synthetic_sequence: a camera panning down
an embedded scene 5-10 px a frame, +-1 px of horizontal jitter, +-0.2 degree of rotation) at each
of 4 distortion levels and undistorted, at the paper's 320 x 424: (c k2_max, (2 - c) k4_max) times
1/8, 3/8, 5/8 and 7/8, c ~ U[0.75, 1.25] per sequence (about the centres of classes 1-4; the
largest coefficients of docs/method.md, section 6). Figures:

- Delta_avg error: RMSE, bias and largest error in px and as % of the range (14.4 px; goal 2 %);
- coverage of the 95 % intervals of Delta_avg and Delta_max (goal >= 90 %) and their half-width;
- class rate, and the share of undistorted sequences called R;
- the OpenCV export's error: cv2.undistortPoints (when OpenCV is installed; the library's own
  emulation otherwise) against eq. 4 over the frame, mean and max (goal <= 0.1 px mean);
- the time for 20 frames of 640 x 480 (default analysis size: 512 x 384), goal < 20 s, on
  ``--threads`` threads (torch.set_num_threads pinned): every run, the fastest (the cost when the
  machine gives the threads their cores) and the median, with the load average.

    python benchmarks/bench_calibrate.py --m 8 --threads 2 [--noise 2] [--out results/bench_calibrate.json]

``--noise`` adds Gaussian noise of that std (grey levels) and 8-bit rounding to every frame.
``--realistic`` renders the frames with the realistic protocol's per-frame effects instead (own
gain, offset, gamma, illumination ramp, sensor noise, JPEG, a moving patch in 20 % of the
frames: ``synthetic_sequence(realistic=True)``, docs/method.md section 7), the timing sequence too.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from lensdist_torch.calibration import calibrate_sequence, synthetic_sequence
from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import delta_avg, delta_max, delta_top, distortion_center, undistort_points
from lensdist_torch.geometry.opencv_model import opencv_camera, opencv_undistort_points

LEVELS = (0.0, 0.125, 0.375, 0.625, 0.875)
SIZE = (320, 424)


def coefficients(level: float, seed: int) -> tuple[float, float]:
    cfg = LensdistConfig().distortion
    c = 0.75 + 0.5 * float(torch.rand(1, generator=torch.Generator().manual_seed(10_000 + seed)))
    return level * cfg.k2_max * c, level * cfg.k4_max * (2 - c)


def opencv_error(k2: float, k4: float, size: tuple[int, int]) -> tuple[float, float, str]:
    """Mean and max error of cv2.undistortPoints (or the library's emulation) over the frame."""
    cam = opencv_camera(k2, k4, *size)
    h, w = size
    xs, ys = torch.arange(0, w, 2.0, dtype=torch.float64), torch.arange(0, h, 2.0, dtype=torch.float64)
    pd = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    ideal = undistort_points(pd[None], [k2], [k4], distortion_center(h, w))[0]
    try:
        import cv2

        k, d = cam.camera_matrix.numpy(), cam.dist_coeffs.numpy()
        got = torch.from_numpy(cv2.undistortPoints(pd.numpy().reshape(-1, 1, 2), k, d, P=k).reshape(-1, 2))
        source = "cv2"
    except ImportError:
        got, source = opencv_undistort_points(pd, cam.camera_matrix, cam.dist_coeffs), "emulation"
    err = (got - ideal).norm(dim=-1)
    return float(err.mean()), float(err.max()), source


def accuracy(m: int, noise: float = 0.0, realistic: bool = False) -> dict:
    top = delta_top("delta_avg", LensdistConfig())
    rows = []
    for level in LEVELS:
        for i in range(m):
            seed = int(level * 1000) + i
            k2, k4 = coefficients(level, seed)
            frames = synthetic_sequence(20, k2, k4, size=SIZE, scene=("gravel", "grass")[i % 2], seed=seed,
                                        realistic=realistic)[0]
            if noise > 0:  # sensor noise, then 8-bit quantisation
                g = torch.Generator().manual_seed(seed)
                frames = (
                    (frames + noise / 255 * torch.randn(frames.shape, generator=g)).clamp(0, 1) * 255
                ).round() / 255
            t0 = time.perf_counter()
            cal = calibrate_sequence(frames)
            rows.append(
                {
                    "level": level,
                    "seed": seed,
                    "time_s": time.perf_counter() - t0,
                    "cal": cal,
                    "true_avg": float(delta_avg([k2], [k4], *SIZE)[0]),
                    "true_max": float(delta_max([k2], [k4], *SIZE)[0]),
                }
            )
    out = {"range_px": top, "per_level": {}}
    for level in LEVELS:
        sel = [r for r in rows if r["level"] == level]
        err = torch.tensor([r["cal"].delta_avg_user_px - r["true_avg"] for r in sel], dtype=torch.float64)
        cover_avg = [
            r["cal"].delta_avg_user_interval[0] <= r["true_avg"] <= r["cal"].delta_avg_user_interval[1] for r in sel
        ]
        cover_max = [
            r["cal"].delta_max_user_interval[0] <= r["true_max"] <= r["cal"].delta_max_user_interval[1] for r in sel
        ]
        want = "R" if level == 0 else str(1 + int(level * 4))
        half = torch.tensor(
            [(r["cal"].delta_avg_user_interval[1] - r["cal"].delta_avg_user_interval[0]) / 2 for r in sel]
        )
        out["per_level"][str(level)] = {
            "n": len(sel),
            "true_delta_avg_px": sum(r["true_avg"] for r in sel) / len(sel),
            "rmse_px": float(err.pow(2).mean().sqrt()),
            "rmse_pct": float(100 * err.pow(2).mean().sqrt() / top),
            "bias_px": float(err.mean()),
            "max_abs_err_px": float(err.abs().max()),
            "coverage_delta_avg": sum(cover_avg) / len(sel),
            "coverage_delta_max": sum(cover_max) / len(sel),
            "median_halfwidth_px": float(half.median()),
            "class_rate": sum(r["cal"].class_label == want for r in sel) / len(sel),
            "pairs_used_mean": sum(r["cal"].pairs_used for r in sel) / len(sel),
            "pairs_rejected_total": sum(r["cal"].pairs_rejected for r in sel),
        }
    all_err = torch.tensor([r["cal"].delta_avg_user_px - r["true_avg"] for r in rows], dtype=torch.float64)
    cov = [r["cal"].delta_avg_user_interval[0] <= r["true_avg"] <= r["cal"].delta_avg_user_interval[1] for r in rows]
    covm = [r["cal"].delta_max_user_interval[0] <= r["true_max"] <= r["cal"].delta_max_user_interval[1] for r in rows]
    out["all"] = {
        "n": len(rows),
        "rmse_pct": float(100 * all_err.pow(2).mean().sqrt() / top),
        "max_abs_err_pct": float(100 * all_err.abs().max() / top),
        "coverage_delta_avg": sum(cov) / len(rows),
        "coverage_delta_max": sum(covm) / len(rows),
        "seconds_per_sequence": sum(r["time_s"] for r in rows) / len(rows),
    }
    errs = [opencv_error(r["cal"].k2_user, r["cal"].k4_user, SIZE) for r in rows if r["level"] > 0]
    out["opencv_320x424"] = {"source": errs[0][2], "mean_px_mean": sum(e[0] for e in errs) / len(errs),
                             "mean_px_worst": max(e[0] for e in errs), "max_px_worst": max(e[1] for e in errs)}
    return out


def timing(repeats: int, realistic: bool = False) -> dict:
    size = (480, 640)
    s = 424 / 640
    cfg = LensdistConfig().distortion
    k2, k4 = 0.625 * cfg.k2_max * s**2, 0.625 * cfg.k4_max * s**4
    frames = synthetic_sequence(20, k2, k4, size=size, seed=99, realistic=realistic)[0]
    times, cal = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        cal = calibrate_sequence(frames)
        times.append(time.perf_counter() - t0)
    true = float(delta_avg([k2], [k4], *size)[0])
    mean, worst, source = opencv_error(cal.k2_user, cal.k4_user, size)
    return {"frames": 20, "size": list(size), "analysis_size": list(cal.analysis_size), "pairs": len(cal.pairs),
            "seconds": times, "seconds_min": min(times), "seconds_median": sorted(times)[len(times) // 2],
            "true_delta_avg_px": true,
            "delta_avg_px": cal.delta_avg_user_px, "interval_px": list(cal.delta_avg_user_interval),
            "opencv_640x480": {"source": source, "mean_px": mean, "max_px": worst}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--m", type=int, default=8, help="sequences per distortion level")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5, help="timing runs of the 640 x 480 sequence")
    ap.add_argument("--noise", type=float, default=0.0, help="std of Gaussian noise added to the frames, grey levels")
    ap.add_argument("--realistic", action="store_true", help="frames with the realistic protocol's effects")
    ap.add_argument("--skip-timing", action="store_true")
    ap.add_argument("--out", default=None, help="also write the JSON here")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    res = {"threads": a.threads, "torch": torch.__version__, "load_average_before": os.getloadavg()}
    if not a.skip_timing:
        res["timing_640x480"] = timing(a.repeats, a.realistic)
    res["noise_grey_levels"], res["realistic"] = a.noise, a.realistic
    res["accuracy_320x424"] = accuracy(a.m, a.noise, a.realistic)
    res["load_average_after"] = os.getloadavg()
    text = json.dumps(res, indent=1)
    print(text)
    if a.out:
        os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
        with open(a.out, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
