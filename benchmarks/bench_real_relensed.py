"""Real frames through known lenses within the classes' range: lensdist calibrate against the truth.

    python benchmarks/bench_real_relensed.py FRAMES_DIR CALIBRATION.json [--levels 0 3 6 12]
        [--first 0 --count 22] [--size 288 384] [--method auto] [--out docs/results/bench_real_relensed.json]

The only calibrated real footage at hand (a GoPro HERO4's 37 views of a wall, 103 px of
distortion) lies far beyond the classes' range. ``lensdist_torch.data.relens`` turns its frames
into the same real scene, light, noise and camera motion seen through an eq. 4 lens of our
choosing: undistorted by the chessboard calibration (0.56 px RMS at 1280 x 960), re-distorted by
(k2, 0) whose Delta_avg at ``--size`` is each of ``--levels`` px. Each level's frames are written
as PNG and calibrated by ``calibrate_path`` (= ``lensdist calibrate FOLDER``, ``--method``), the
user's path. Reported per level: the truth, the answer, its 95 % interval and class, each path's
own answer, and COLMAP's models on the same tracks where it reconstructs.

The truth's own uncertainty is the calibration's: ``--alternative`` (the calibration file's
``alternative_subpix``, the same views with sub-pixel corners, 0.82 px RMS) relenses the frames
once more, and the mean distance between the two relensing maps after the homography that best
aligns them (what a registration absorbs) is reported at ``--size``.

Frames ``--first`` .. ``--first + --count - 1`` of the folder (sorted by name): the first 22 are
the test frames (as in ``bench_real_calibration.py``'s runs at 384 x 288); the other 15 are the
validation frames, on which choices were checked first.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from lensdist_torch.core import atomic_write_text, load_image
from lensdist_torch.core.png import encode_png, to_uint8
from lensdist_torch.data.relens import relens_frames, relens_map
from lensdist_torch.geometry.distortion import delta_avg


def k2_for(level: float, size: tuple[int, int]) -> float:
    """The k2 (k4 = 0) whose Delta_avg at ``size`` is ``level`` px (Delta_avg is linear in k2)."""
    return level / float(delta_avg([1e-6], [0.0], *size)[0]) * 1e-6


def calibration_spread(cal: dict, alt: dict, hw: tuple[int, int], size: tuple[int, int]) -> float:
    """Mean distance (px at ``size``) between the two calibrations' undistortion maps, a homography apart."""
    import cv2

    h, w = hw
    a = relens_map(h, w, cal["K"], cal["dist"], k2=0.0, k4=0.0)[0][::8, ::8].reshape(-1, 2).numpy()
    b = relens_map(h, w, alt["K"], alt["dist"], k2=0.0, k4=0.0)[0][::8, ::8].reshape(-1, 2).numpy()
    hom, _ = cv2.findHomography(b, a, 0)
    moved = cv2.perspectiveTransform(b[:, None], hom)[:, 0]
    return float(np.linalg.norm(moved - a, axis=1).mean()) * size[0] / h


def main() -> None:
    from lensdist_torch.calibration import calibrate_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames")
    ap.add_argument("calibration")
    ap.add_argument(
        "--levels", type=float, nargs="+", default=[0.0, 3.0, 6.0, 12.0], help="truth Delta_avg at --size, px"
    )
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--count", type=int, default=22)
    ap.add_argument("--size", type=int, nargs=2, default=[288, 384], metavar=("H", "W"))
    ap.add_argument("--method", choices=["auto", "direct", "multiview"], default="auto")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cals = json.loads(Path(args.calibration).read_text())
    cal = cals["primary"]
    files = sorted(p for p in Path(args.frames).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    files = files[args.first : args.first + args.count]
    frames = torch.cat([load_image(f) for f in files])
    size = tuple(args.size)
    spread = (
        calibration_spread(cal, cals["alternative_subpix"], frames.shape[-2:], size)
        if "alternative_subpix" in cals
        else None
    )
    rows = []
    for level in args.levels:
        k2 = k2_for(level, size)
        out = relens_frames(frames, cal["K"], cal["dist"], k2=k2, k4=0.0, size=size)
        with tempfile.TemporaryDirectory(prefix="lensdist-relensed-") as tmp:
            for f, img in zip(files, out.frames):
                (Path(tmp) / f"{f.stem}.png").write_bytes(encode_png(to_uint8(img)))
            t0 = time.perf_counter()
            res = calibrate_path(tmp, method=args.method)
            seconds = time.perf_counter() - t0
        truth = float(delta_avg([k2], [0.0], *size)[0])
        iv = res["delta_avg_user_interval"]
        mv, d = res.get("multiview") or {}, res.get("direct") or {}
        rows.append(
            {
                "level": level,
                "k2_user": k2,
                "truth_px": truth,
                "valid_fraction": out.valid_fraction,
                "seconds": seconds,
                "answer_px": res["delta_avg_user_px"],
                "interval": iv,
                "class": res["class"],
                "reason": res["reason"],
                "method": res.get("method"),
                "pairs_used": res.get("pairs_used"),
                "relief_z": res.get("relief_z"),
                "covers": bool(iv is not None and iv[0] is not None and iv[0] <= truth <= iv[1]),
                "direct": {k: d.get(k) for k in ("delta_avg_user_px", "delta_avg_user_interval", "class", "reason")},
                "multiview": {
                    k: mv.get(k)
                    for k in ("delta_avg_user_px", "delta_avg_user_interval", "class", "reason", "registered", "model")
                },
                "colmap_models": {m: v.get("delta_avg_px") for m, v in (mv.get("models") or {}).items()},
                "planar": {
                    k: (res.get("planar") or {}).get(k)
                    for k in (
                        "delta_avg_user_px",
                        "delta_avg_user_interval",
                        "class",
                        "reason",
                        "terms",
                        "pairs",
                        "inliers",
                    )
                },
            }
        )
        r = rows[-1]
        print(f"level {level:g} px: truth {truth:.2f}, answer {r['answer_px']:.2f} "
              f"[{iv[0]:.2f}, {iv[1]:.2f}] class {r['class'] or 'cannot tell'} ({r['reason'] or r['method']}), "
              f"{seconds:.0f} s", flush=True)
    h, w = size
    print(
        f"\n{len(files)} real frames ({files[0].name} .. {files[-1].name}) relensed at {w} x {h}"
        + (
            f"; the truth's own uncertainty (two chessboard calibrations, a homography apart): {spread:.3f} px"
            if spread
            else ""
        )
    )
    print(
        "| truth Delta_avg (px) | answer (px) | error | 95 % interval | covers | class | reason | direct | multi-view |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        iv, err = r["interval"], r["answer_px"] - r["truth_px"]
        rel = f" ({100 * err / r['truth_px']:+.1f} %)" if r["truth_px"] > 0 else ""
        dv, mvv = r["direct"]["delta_avg_user_px"], r["multiview"]["delta_avg_user_px"]
        print(f"| {r['truth_px']:.2f} | {r['answer_px']:.2f} | {err:+.2f}{rel} | [{iv[0]:.2f}, {iv[1]:.2f}] | "
              f"{'yes' if r['covers'] else 'no'} | {r['class'] or 'cannot tell'} | {r['reason'] or ''} | "
              f"{'-' if dv is None else f'{dv:.2f}'} | {'-' if mvv is None else f'{mvv:.2f}'} "
              f"({r['multiview']['reason'] or r['multiview']['class']}) |")
    if args.out:
        report = {"frames": [f.name for f in files], "size": list(size), "method": args.method,
                  "calibration_spread_px": spread, "rows": rows}
        strict = json.loads(json.dumps(report, default=str).replace("NaN", "null").replace("Infinity", "null"))
        atomic_write_text(Path(args.out), json.dumps(strict, indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
