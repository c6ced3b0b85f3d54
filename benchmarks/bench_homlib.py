"""Benchmark of our self-calibration against homlib's radial-distortion homography solvers.

The peers a practitioner would use instead of ``lensdist_torch.selfcal.estimate_distortion``:
the division-model homography solvers of homlib (Fitzgibbon CVPR 2001, Kukelova et al. CVPR 2015,
Wadenbaeck et al. 3DV 2026, Nakano ICPR 2024), each inside homlib's own LO-RANSAC ("LOMSAC",
``homlib.lomsac_*``), on point matches of the same SPEC test pairs. The matches come from
OpenCV SIFT + Lowe's ratio test on the uint8 versions of the pair.

homlib and OpenCV are optional dependencies of this benchmark only (never of the package):

    pip install homlib opencv-python-headless
    python benchmarks/bench_homlib.py --n 100 --threads 2 [--json out.json]

Conventions (checked against ``homlib.generate_problem_instance``, homlib 0.1.2):
- homlib's solvers take x, y as (2, n) float64 arrays and fit y_u ~ H x_u with the division model
  x_u = (x_d, 1 + lambda1 |x_d|^2), y_u = (y_d, 1 + lambda2 |y_d|^2), in whatever coordinates they
  are given: homlib does no normalisation itself. Here the coordinates are centred on the SPEC
  distortion centre p0 = ((W-1)/2, (H-1)/2) and divided by s = max(W, H) / 2 (212 px at 424 x 320),
  so lambda is in units of s^-2. The one-sided solvers return the lambda of the *second* image in
  ``distortion_parameter``; the two-sided ones return lambda1, lambda2 in ``distortion_parameter``
  and ``distortion_parameter2`` (both images of a SPEC pair carry the same distortion; the
  benchmark uses their mean).
- ``squared_inlier_threshold`` is in the same (normalised) units: the threshold is given in px
  (--inlier-px) and divided by s^2.
- lambda -> Delta (SPEC 6, same evaluation as eq. 4): at every pixel centre p_d, the ideal point is
  p = p0 + (p_d - p0) / (1 + lambda r_n^2), r_n = ||p_d - p0|| / s; delta(p_d) = ||p - p_d||;
  Delta_avg is its mean, Delta_max its maximum. If 1 + lambda r_n^2 <= 0 somewhere in the image,
  the model is not a valid undistortion there: Delta is infinite and the pair counts as a failure
  (wrong class, excluded from the RMSE, counted in the "failed" column), as do pairs with too few
  matches or a solver that returns nothing.
- The division model with one lambda cannot represent SPEC's k2 r^2 + k4 r^4 exactly; that misfit
  is part of what the comparison measures.

Timing: ours = estimate_distortion on batches (--batch) with torch at --threads threads; theirs =
one pair at a time in this process, OpenCV at 1 thread (homlib's C++ core is single-threaded; the
CPU / wall ratio is recorded in the JSON). Theirs' pairs/s includes SIFT + matching (also
reported alone); rendering is excluded on both sides. Both sides run interleaved, batch by batch,
so a busy machine slows both alike.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_selfcal import figures  # the same figures as the self-calibration benchmark

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data import draw_pairs, render_pairs
from lensdist_torch.data.shards import load_scenes
from lensdist_torch.geometry import delta_avg, delta_max, delta_top
from lensdist_torch.selfcal import estimate_distortion

PIP = "pip install homlib opencv-python-headless"

# name -> (homlib function, how its lambdas are read)
#   "equal": one lambda shared by both images (distortion_parameter)
#   "two":   lambda1, lambda2 (distortion_parameter, distortion_parameter2), averaged
#   "one":   one-sided: only the second image distorted (distortion_parameter); misspecified here
SOLVERS = {
    "fitzgibbon2001_equal": ("lomsac_fitzgibbon_cvpr_2001_two_sided_equal", "equal"),
    "kukelova2015_equal": ("lomsac_kukelova_cvpr_2015_two_sided_equal", "equal"),
    "kukelova2015_equal_6pt": ("lomsac_kukelova_cvpr_2015_two_sided_equal_6pt", "equal"),
    "kukelova2015_two": ("lomsac_kukelova_cvpr_2015_two_sided", "two"),
    "kukelova2015_two_6pt": ("lomsac_kukelova_cvpr_2015_two_sided_6pt", "two"),
    "wadenback2026_equal": ("lomsac_wadenback_3dv_2026_two_sided_equal", "equal"),
    "wadenback2026_two": ("lomsac_wadenback_3dv_2026_two_sided", "two"),
    "fitzgibbon2001_one": ("lomsac_fitzgibbon_cvpr_2001_one_sided", "one"),
    "nakano2024_one": ("lomsac_nakano_icpr_2025_one_sided", "one"),
    "wadenback2026_one": ("lomsac_wadenback_3dv_2026_one_sided", "one"),
}
DEFAULT_SOLVERS = ["fitzgibbon2001_equal", "kukelova2015_equal", "kukelova2015_equal_6pt",
                   "kukelova2015_two", "wadenback2026_equal"]


class DivisionDelta:
    """Delta_avg / Delta_max of a division-model lambda over the H x W pixel centres (SPEC 6)."""

    def __init__(self, h: int, w: int):
        y, x = np.mgrid[0:h, 0:w].astype(np.float64)
        x0, y0 = (w - 1) / 2, (h - 1) / 2
        self.s = max(w, h) / 2
        self.r = np.hypot(x - x0, y - y0).ravel()
        self.rn2 = (self.r / self.s) ** 2

    def __call__(self, lam: float) -> tuple[float, float]:
        if not np.isfinite(lam):
            return float("inf"), float("inf")
        den = 1.0 + lam * self.rn2
        if (den <= 0).any():
            return float("inf"), float("inf")
        d = self.r * np.abs(1.0 / den - 1.0)
        return float(d.mean()), float(d.max())

    def best_lambda(self, k2: float, k4: float) -> float:
        """The division-model lambda closest to SPEC's (k2, k4): least squares of the ideal radius
        r / (1 + lambda r_n^2) against r (1 + k2 r^2 + k4 r^4) over every 4th pixel centre."""
        r, rn2 = self.r[::4], self.rn2[::4]
        target = r * (1 + k2 * r**2 + k4 * r**4)
        lo, hi = -0.6, 0.0
        for _ in range(3):  # grid, then two finer grids around the best
            lams = np.linspace(lo, hi, 401)
            den = 1.0 + lams[:, None] * rn2[None]
            cost = np.where((den > 0).all(1), ((r / np.where(den > 0, den, 1.0) - target) ** 2).sum(1), np.inf)
            i = int(np.argmin(cost))
            step = lams[1] - lams[0]
            lo, hi = lams[i] - step, lams[i] + step
        return float(lams[i])


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.squeeze(0).clamp(0, 1) * 255).round().to(torch.uint8).numpy()


def sift_matches(cv2, sift, matcher, a: np.ndarray, b: np.ndarray, ratio: float):
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((2, 0)), np.zeros((2, 0))
    good = [m for m, n in (p for p in matcher.knnMatch(da, db, k=2) if len(p) == 2) if m.distance < ratio * n.distance]
    x = np.array([ka[m.queryIdx].pt for m in good], dtype=np.float64).reshape(-1, 2).T
    y = np.array([kb[m.trainIdx].pt for m in good], dtype=np.float64).reshape(-1, 2).T
    return x, y


def read_lambda(pose, kind: str) -> float:
    if kind == "two":
        return 0.5 * (pose.distortion_parameter + pose.distortion_parameter2)
    return float(pose.distortion_parameter)


def run(a, config: LensdistConfig, homlib, cv2) -> dict:
    scenes, _ = load_scenes(config)
    h, w = config.image.height, config.image.width
    top = delta_top("delta_avg", config)
    top_max = delta_top("delta_max", config)
    conv = DivisionDelta(h, w)
    p0 = np.array([[(w - 1) / 2], [(h - 1) / 2]])
    sift = cv2.SIFT_create()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    opts = homlib.LORansacOptions()
    opts.squared_inlier_threshold = (a.inlier_px / conv.s) ** 2
    opts.random_seed = 0
    opts.final_least_squares = True

    n = min(a.n, 400)  # test indices < 400 are the distorted pairs
    trues, trues_max, tys, k2_true, k4_true = [], [], [], [], []
    ours_avg, ours_max, ours_conf, t_ours = [], [], [], 0.0
    t_sift = c_sift = 0.0
    n_matches = []
    theirs = {
        k: {"avg": [], "max": [], "lam": [], "inliers": [], "t": 0.0, "cpu": 0.0, "errors": []} for k in a.solvers
    }
    for s0 in range(0, n, a.batch):
        idx = list(range(s0, min(n, s0 + a.batch)))
        p = draw_pairs(config, "test", idx, len(scenes))
        i1, i2 = render_pairs(scenes, p, config)
        trues.append(delta_avg(p.k2, p.k4, h, w))
        trues_max.append(delta_max(p.k2, p.k4, h, w))
        tys.append(p.motion[:, 0])
        k2_true.append(p.k2)
        k4_true.append(p.k4)
        # ours, batched
        t0 = time.perf_counter()
        k2, k4, _, info = estimate_distortion(i1, i2)
        t_ours += time.perf_counter() - t0
        ours_avg.append(info.delta_avg)
        ok = info.converged & torch.isfinite(k2) & torch.isfinite(k4)
        dm = torch.full((len(idx),), float("nan"), dtype=torch.float64)
        if ok.any():
            dm[ok] = delta_max(k2[ok].double(), k4[ok].double(), h, w)
        ours_max.append(dm)
        ours_conf.append(info.confident)
        # theirs, one pair at a time
        for b in range(len(idx)):
            u1, u2 = to_uint8(i1[b]), to_uint8(i2[b])
            t0, c0 = time.perf_counter(), time.process_time()
            x, y = sift_matches(cv2, sift, matcher, u1, u2, a.ratio)
            t_sift += time.perf_counter() - t0
            c_sift += time.process_time() - c0
            n_matches.append(x.shape[1])
            xn, yn = (x - p0) / conv.s, (y - p0) / conv.s
            for name in a.solvers:
                fn, kind = SOLVERS[name]
                lam, inl = float("nan"), 0
                t0, c0 = time.perf_counter(), time.process_time()
                if x.shape[1] >= 8:
                    try:
                        pose, stats = getattr(homlib, fn)(xn, yn, opts)
                        lam, inl = read_lambda(pose, kind), int(stats.best_num_inliers)
                    except (RuntimeError, ValueError) as exc:  # a solver failure is a failed pair, not a crash
                        theirs[name]["errors"].append(f"pair {idx[b]}: {exc}")
                r = theirs[name]
                r["t"] += time.perf_counter() - t0
                r["cpu"] += time.process_time() - c0
                da, dx = conv(lam) if inl > 0 else (float("inf"), float("inf"))
                r["avg"].append(da)
                r["max"].append(dx)
                r["lam"].append(lam)
                r["inliers"].append(inl)
        print(f"  {idx[-1] + 1}/{n} pairs", file=sys.stderr, flush=True)

    true, true_max, ty = torch.cat(trues), torch.cat(trues_max), torch.cat(tys)
    out = {"n": n, "load_average_end": os.getloadavg(), "sift_pairs_per_s": n / t_sift,
           "sift_cpu_per_wall": c_sift / t_sift, "matches_median": float(np.median(n_matches)),
           "matches_min": int(np.min(n_matches)), "methods": {}}
    ours = figures(torch.cat(ours_avg), true, ty, top, torch.cat(ours_conf))
    ours["delta_max"] = figures(torch.cat(ours_max), true_max, ty, top_max)
    ours["pairs_per_s"] = n / t_ours
    out["methods"]["ours: selfcal.estimate_distortion"] = ours
    # not a peer: the best any one-lambda division model could do on these pairs (from the truth)
    k2s, k4s = torch.cat(k2_true).tolist(), torch.cat(k4_true).tolist()
    orc = [conv(conv.best_lambda(k2_, k4_)) for k2_, k4_ in zip(k2s, k4s)]
    f = figures(torch.tensor([o[0] for o in orc], dtype=torch.float64), true, ty, top)
    f["delta_max"] = figures(torch.tensor([o[1] for o in orc], dtype=torch.float64), true_max, ty, top_max)
    out["methods"]["(oracle: best division-model lambda for the true k2, k4)"] = f
    for name in a.solvers:
        r = theirs[name]
        est = torch.tensor(r["avg"], dtype=torch.float64)
        est_max = torch.tensor(r["max"], dtype=torch.float64)
        f = figures(est, true, ty, top)
        f["delta_max"] = figures(est_max, true_max, ty, top_max)
        f["homlib_function"] = SOLVERS[name][0]
        f["pairs_per_s"] = n / (t_sift + r["t"])
        f["solver_pairs_per_s"] = n / r["t"]
        f["solver_cpu_per_wall"] = r["cpu"] / r["t"]
        f["inliers_median"] = float(np.median(r["inliers"]))
        f["lambda"] = r["lam"]
        f["solver_errors"] = r["errors"]
        out["methods"][f"homlib {name} + SIFT"] = f
    return out


def table(res: dict, threads: int) -> str:
    lines = [
        (f"{res['n']} distorted SPEC test pairs (320 x 424); class = 4 bins of ]0, 14.4] px of Delta_avg. "
         f"SIFT + ratio-test matching alone: {res['sift_pairs_per_s']:.1f} pairs/s "
         f"(median {res['matches_median']:.0f} matches, min {res['matches_min']})."),
        "",
        ("| method | pairs | failed | class rate (%) | RMSE Delta_avg (px) | bias (px) | RMSE Delta_max (px) "
         "| pairs/s | solver-only pairs/s |"),
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, f in res["methods"].items():
        ours = name.startswith("ours")
        if name.startswith("(oracle"):
            lines.append(f"| {name} | {f['n']} | {f['flagged']} | {100 * f['class_rate']:.1f} | {f['rmse_px']:.2f} | "
                         f"{f['bias_px']:+.2f} | {f['delta_max']['rmse_px']:.2f} | - | - |")
            continue
        speed = (
            f"{f['pairs_per_s']:.2f} (batched, {threads} thr)"
            if ours
            else f"{f['pairs_per_s']:.2f} (1 thr, incl. SIFT)"
        )
        solver = "" if ours else f"{f['solver_pairs_per_s']:.1f}"
        lines.append(f"| {name} | {f['n']} | {f['flagged']} | {100 * f['class_rate']:.1f} | {f['rmse_px']:.2f} | "
                     f"{f['bias_px']:+.2f} | {f['delta_max']['rmse_px']:.2f} | {speed} | {solver} |")
    lines.append("")
    lines.append("RMSE and bias over the pairs a method did not fail on; a failed pair counts as a wrong class. "
                 "The oracle row is no peer: the lambda that best fits the true radial map, i.e. the floor of the "
                 "one-parameter division model on SPEC's k2, k4 distortion.")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=100, help="distorted test pairs (at most 400)")
    ap.add_argument("--batch", type=int, default=20, help="our batch size")
    ap.add_argument("--threads", type=int, default=2, help="torch threads for ours")
    ap.add_argument("--solvers", default=",".join(DEFAULT_SOLVERS),
                    help=f"comma list or 'all'; known: {', '.join(SOLVERS)}")
    ap.add_argument("--inlier-px", type=float, default=2.0, help="LO-RANSAC inlier threshold (px)")
    ap.add_argument("--ratio", type=float, default=0.8, help="Lowe ratio test")
    ap.add_argument("--json", default="", help="write the full results here")
    a = ap.parse_args()
    try:
        import cv2
        import homlib
    except ImportError as exc:
        print(f"bench_homlib: optional dependency missing ({exc}). It needs homlib and OpenCV, "
              f"which are not dependencies of lensdist_torch. Install them with:\n    {PIP}")
        sys.exit(0)
    a.solvers = list(SOLVERS) if a.solvers == "all" else [s for s in a.solvers.split(",") if s]
    unknown = [s for s in a.solvers if s not in SOLVERS]
    if unknown:
        ap.error(f"unknown solvers {unknown}; known: {list(SOLVERS)}")
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(1)
    res = run(a, LensdistConfig(), homlib, cv2)
    res.update({"threads": a.threads, "batch": a.batch, "homlib_version": homlib.__version__,
                "opencv_version": cv2.__version__, "torch_version": torch.__version__,
                "inlier_px": a.inlier_px, "ratio": a.ratio})
    print(table(res, a.threads))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
