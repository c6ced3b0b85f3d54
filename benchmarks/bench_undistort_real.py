"""Real frames undistorted as a user does it: the chessboard found again in `lensdist undistort`'s output.

    python benchmarks/bench_undistort_real.py FRAMES_DIR CALIBRATION.json ANSWER.json [--out F.json]

ANSWER.json: the JSON of ``lensdist calibrate FRAMES --json`` (or bench_real_calibration.py's
report, whose ``answer`` it holds). The frames are undistorted three ways, each at the input's
scale: ``undistort_path(from_json=ANSWER)`` (= ``lensdist undistort --from``: the homography
model's own lens where it answered), ``undistort_path(k2=, k4=)`` with the answer's eq. 4
coefficients (what ``--from`` applied before 2026-11-28), and ``cv2.undistort`` with the
chessboard's own calibration (the reference). In every output the board's 8 x 6 inner corners are
found by ``cv2.findChessboardCorners`` and refined by ``cornerSubPix`` (11 x 11), one homography
per view is fitted to them, and its RMS (px, the undistorted image's) is reported over the views
where all three found the board (near the edges the undistorted frames lose it). The board is
never shown to the estimators; this is the end-to-end check of what a user's undistorted
frames look like.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
from pathlib import Path

import numpy as np
import torch

from lensdist_torch.core import atomic_write_text
from lensdist_torch.core.images import IMAGE_SUFFIXES
from lensdist_torch.workflows.undistort import undistort_path


def board_rms(folder: Path, pattern=(8, 6)) -> dict[str, float]:
    """Per image of ``folder``: the RMS (px) of one homography fitted to the board's refined inner corners."""
    import cv2

    obj = np.array([[x, y] for y in range(pattern[1]) for x in range(pattern[0])], np.float64)
    out = {}
    for f in sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(grey, pattern)
        if not found:
            continue
        stop = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
        c = cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), stop).reshape(-1, 2).astype(np.float64)
        h, _ = cv2.findHomography(obj, c, 0)
        fit = cv2.perspectiveTransform(obj[:, None], h)[:, 0]
        out[f.stem] = float(np.sqrt(((fit - c) ** 2).sum(1).mean()))
    return out


def main() -> None:
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames")
    ap.add_argument("calibration")
    ap.add_argument("answer")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    answer = json.loads(Path(args.answer).read_text())
    answer = answer["answer"] if "answer" in answer and "image_size" not in answer else answer
    cal = json.loads(Path(args.calibration).read_text())["primary"]
    k, dist = np.array(cal["K"]), np.array(cal["dist"])
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "answer.json"
        src.write_text(json.dumps(answer))
        runs = {"lensdist undistort --from the answer": {"from_json": src},
                "eq. 4 of the same answer (--k2 --k4)": {"k2": answer["k2_user"], "k4": answer["k4_user"]}}
        for i, (name, kwargs) in enumerate(runs.items()):
            res = undistort_path(args.frames, Path(tmp) / f"out{i}", **kwargs)
            rows[name] = {"applied": res["camera"]["applied"], "views": board_rms(Path(tmp) / f"out{i}")}
        ref = Path(tmp) / "calibration"
        ref.mkdir()
        for f in sorted(p for p in Path(args.frames).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
            cv2.imwrite(str(ref / f"{f.stem}.png"), cv2.undistort(cv2.imread(str(f)), k, dist, None, k))
        rows["the chessboard calibration (cv2.undistort)"] = {"applied": "OpenCV", "views": board_rms(ref)}
    common = sorted(set.intersection(*(set(r["views"]) for r in rows.values())))
    report = {"frames": args.frames, "answer_method": answer.get("method"), "common_views": common, "rows": rows}
    for name, r in rows.items():
        v = [r["views"][c] for c in common]
        r.update(found=len(r["views"]), median_px=statistics.median(v), worst_px=max(v),
                 within_1px=sum(x <= 1 for x in v) / len(v))
        print(
            f"{name}: board found in {r['found']} frames; over the {len(common)} common ones "
            f"median {r['median_px']:.3f} px, worst {r['worst_px']:.2f} px, within 1 px {100 * r['within_1px']:.0f} %"
        )
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
