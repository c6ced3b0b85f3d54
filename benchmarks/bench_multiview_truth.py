"""Does the multi-view path's held-out evidence see the truth? The true lens held on COLMAP's tracks beside its models.

Renders the speed benchmark's sequence (:func:`bench_calibrate_speed.render`: gravel, hills 2 % of
the camera's height, eq. 4 scaled to Delta_avg = 7.5 px times width / 384), maps it as ``lensdist
calibrate`` does (:func:`~lensdist_torch.calibration.multiview.reconstruct` on the
``multiview.mapped_frames`` evenly spaced frames), and self-calibrates the reconstruction
(:func:`~lensdist_torch.calibration.multiview.self_calibrate_reconstruction`) with the true lens
passed as ``others``: its OpenCV camera (eq. 4 fitted by the rational model at the mapped focal
length, :func:`~lensdist_torch.geometry.opencv_model.opencv_export`) held on the same tracks and
scored on the same held-out frames as COLMAP's models; and, in a second run, the direct path's
answer on the same frames (``calibrate_path(folder, method="direct")``, its eq. 4 lens by the same
export) held in its place, as "every path in one comparison" would (docs/method.md, section 11,
point 6). Writes per candidate its Delta_avg, posterior std, weight, elpd, in-sample and held-out
RMS, and each run's answer, to ``--out``.

    python benchmarks/bench_multiview_truth.py --frames 80 --size 608 968 \\
        --out docs/results/bench_multiview_truth_80.json
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import torch
from bench_calibrate_speed import coefficients, render, write_frames

from lensdist_torch.calibration.controllers.calibrate import calibrate_path
from lensdist_torch.calibration.controllers.multiview_path import evenly_spaced
from lensdist_torch.calibration.multiview import camera_of, reconstruct, self_calibrate_reconstruction
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.geometry import delta_avg, delta_max
from lensdist_torch.geometry.opencv_model import opencv_export

ROW_KEYS = ("delta_avg_px", "delta_avg_std_px", "weight", "elpd", "reprojection_px", "heldout_rms_px", "converged",
            "iterations")


def _rows(res) -> dict:
    """Per candidate its figures (strict JSON), printed too."""
    rows = {m: {k: (None if isinstance(r.get(k), float) and not math.isfinite(r[k]) else r.get(k)) for k in ROW_KEYS}
            for m, r in res.models.items()}
    for m, r in rows.items():
        print(f"{m:12s} {r['delta_avg_px']:7.3f} px  weight {r['weight']:.3f}  elpd {r['elpd']:.1f}  "
              f"rms {r['reprojection_px']:.4f}  held-out {r['heldout_rms_px']:.4f}")
    return rows


def _answer(res) -> dict:
    return {"model": res.model, "delta_avg_user_px": res.delta_avg_user_px,
            "delta_avg_user_interval": list(res.delta_avg_user_interval), "class": res.class_label,
            "reason": res.reason or None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--size", type=int, nargs=2, default=[608, 968], metavar=("H", "W"))
    ap.add_argument("--rotation", type=float, default=0.2)
    ap.add_argument("--altitude", type=float, default=0.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    size = tuple(args.size)
    k2, k4 = coefficients(7.5 * size[1] / 384, size)
    truth, most = float(delta_avg([k2], [k4], *size)[0]), float(delta_max([k2], [k4], *size)[0])
    cfg = MultiViewConfig(num_threads=args.threads)
    frames = render(args.frames, size, rotation=args.rotation, altitude=args.altitude)
    with tempfile.TemporaryDirectory() as tmp:
        names = write_frames(frames, tmp)
        direct = calibrate_path(tmp, method="direct")
        names = [names[i] for i in evenly_spaced(len(names), cfg.mapped_frames)]
        rec = reconstruct(tmp, names, config=cfg, image_size=size)[0]
    if rec is None:
        raise SystemExit("COLMAP reconstructed nothing")
    focal = camera_of(rec).mean_focal_length()
    cam = opencv_export(k2, k4, *size, focal=focal, model="rational")
    held = {"camera_matrix": cam["camera_matrix"], "dist_coeffs": cam["dist_coeffs"], "delta_avg_user_px": truth,
            "delta_avg_user_interval": [truth, truth], "delta_max_user_px": most,
            "delta_max_user_interval": [most, most]}
    res = self_calibrate_reconstruction(rec, cfg, image_size=size, others={"truth": held})
    rows = _rows(res)
    dcam = opencv_export(direct["k2_user"], direct["k4_user"], *size, focal=focal, model="rational")
    keys = ("delta_avg_user_px", "delta_avg_user_interval", "delta_max_user_px", "delta_max_user_interval")
    with_direct = self_calibrate_reconstruction(rec, cfg, image_size=size, others={"direct": {
        "camera_matrix": dcam["camera_matrix"], "dist_coeffs": dcam["dist_coeffs"], **{k: direct[k] for k in keys}}})
    command = (f"python benchmarks/bench_multiview_truth.py --frames {args.frames} --size {size[0]} {size[1]} "
               f"--rotation {args.rotation} --altitude {args.altitude} --threads {args.threads} --out {args.out}")
    out = {"command": command,
           "truth_delta_avg_px": truth, "registered": rec.num_reg_images(), "points3D": rec.num_points3D(),
           "truth_opencv_fit_error_px": cam["fit_error_mean_px"], "answer": _answer(res), "candidates": rows,
           "direct": {k: direct[k] for k in keys}, "answer_with_direct": _answer(with_direct),
           "candidates_with_direct": _rows(with_direct)}
    atomic_write_text(args.out, json.dumps(out, indent=1, allow_nan=False))


if __name__ == "__main__":
    main()
