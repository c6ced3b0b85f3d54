"""How well a chessboard calibration knows its own Delta_avg, and where an answer stands beside it.

    python benchmarks/bench_calibration_spread.py CALIBRATION.json CORNERS.json ANSWER.json
        [--out docs/results/bench_calibration_spread.json]

The truth of ``bench_real_calibration.py`` is one calibration's Delta_avg over the pixels where its
model inverts; beyond the board the model extrapolates, and near its limit of inversion a small
change of the coefficients moves Delta by a lot. This benchmark calibrates again from the same
corners (CORNERS.json: per view ``image_points`` and the board's ``object_points_xy``) with
``cv2.calibrateCamera`` under the choices a careful user could make (OpenCV's 5 coefficients as
published; the 8 of its rational model; each on the even and on the odd views), and reports for
each its reprojection RMS, its held-out RMS (fitted on one half of the views, each view of the
other half posed under those intrinsics; the all-views row: both halves pooled), Delta_avg where
it inverts, where the published calibration inverts (and it too), and over the board's region
(the pixels inside some view's board, where the corners measure the lens). ANSWER.json: the JSON
of ``lensdist calibrate FRAMES --json`` (or ``bench_real_calibration.py``'s report); its
homography model's Delta_avg and interval over the same two regions, from its own replicates
(:func:`~lensdist_torch.calibration.planar_features.delta_avg_where`). The answer never saw the
board.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from lensdist_torch.calibration.planar_features import delta_avg_where
from lensdist_torch.config import CalibrationConfig, LensdistConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.geometry.opencv_model import grid_points, opencv_ideal_points


def board_region(corners: dict, size: tuple[int, int], points: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which ``points`` lie inside the convex hull of some view's board corners."""
    import cv2

    h, w = size
    mask = np.zeros((h, w), np.uint8)
    for pts in corners["image_points"].values():
        hull = cv2.convexHull(np.asarray(pts, np.float32).reshape(-1, 2))
        cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    return torch.from_numpy(mask.astype(bool))[points[:, 1].round().long(), points[:, 0].round().long()]


def held_out_rms(obj, img: list, k, dist) -> tuple[float, int]:
    """Sum of squared reprojection errors (px^2) of views ``img`` under fixed intrinsics (k, dist),
    and the corners counted.

    Each view's pose by ``cv2.solvePnP`` refined by ``cv2.solvePnPRefineLM``; the intrinsics stay as fitted
    on other views.
    """
    import cv2

    se, n = 0.0, 0
    for pts in img:
        _, rv, tv = cv2.solvePnP(obj, pts, k, dist)
        rv, tv = cv2.solvePnPRefineLM(obj, pts, k, dist, rv, tv)
        proj, _ = cv2.projectPoints(obj, rv, tv, k, dist)
        se += float(((proj - pts) ** 2).sum())
        n += len(obj)
    return se, n


def calibrations(corners: dict, size: tuple[int, int]) -> list[dict]:
    """The board calibrated again from ``corners``: OpenCV's standard and rational models, all, even and odd views.

    Each half's row carries ``held_out_rms_px``: its intrinsics' reprojection RMS on the other half's
    views (poses fitted there, the intrinsics held); the all-views row the two halves' pooled, the
    cross-validated error by which a careful user would choose the model.
    """
    import cv2

    h, w = size
    views = sorted(corners["image_points"])
    obj = np.asarray(corners["object_points_xy"], np.float32)
    obj = np.concatenate([obj, np.zeros((len(obj), 1), np.float32)], 1)
    img = [np.asarray(corners["image_points"][v], np.float32).reshape(-1, 1, 2) for v in views]
    even, odd = list(range(0, len(views), 2)), list(range(1, len(views), 2))
    out = []
    for model, flags in (("standard (5)", 0), ("rational (8)", cv2.CALIB_RATIONAL_MODEL)):
        rows, held = [], []
        for part, sel, other in (("all views", even + odd, []), ("even views", even, odd), ("odd views", odd, even)):
            rms, k, dist, _, _ = cv2.calibrateCamera(
                [obj] * len(sel), [img[i] for i in sel], (w, h), None, None, flags=flags
            )
            dist = dist.ravel()[: 8 if flags else 5]
            rows.append({"model": model, "views": part, "n_views": len(sel), "rms_px": float(rms), "K": k.tolist(),
                         "dist": dist.tolist()})
            if other:  # this half's intrinsics on the other half's views
                held.append(held_out_rms(obj, [img[i] for i in other], k, dist))
                rows[-1]["held_out_rms_px"] = float(np.sqrt(held[-1][0] / held[-1][1]))
        rows[0]["held_out_rms_px"] = float(
            np.sqrt(sum(se for se, _ in held) / sum(n for _, n in held))
        )  # both halves pooled
        out += rows
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration")
    ap.add_argument("corners")
    ap.add_argument("answer")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)
    cal = json.loads(Path(args.calibration).read_text())["primary"]
    corners = json.loads(Path(args.corners).read_text())
    res = json.loads(Path(args.answer).read_text())
    res = res["answer"] if "answer" in res and "image_size" not in res else res
    h, w = res["image_size"]
    g = grid_points(h, w, 2)
    board = board_region(corners, (h, w), g)
    _, published = opencv_ideal_points(g, torch.tensor(cal["K"]), torch.tensor(cal["dist"]))
    rows = []
    print(f"the board's region: {100 * float(board.double().mean()):.1f} % of the frame; the published calibration "
          f"inverts on {100 * float(published.double().mean()):.1f} %")
    print(
        "| calibration | views | RMS (px) | held out (px) | inverts | Delta_avg where it inverts | "
        "where the published one inverts | over the board's region |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for c in calibrations(corners, (h, w)):
        ideal, ok = opencv_ideal_points(
            g, torch.tensor(c["K"], dtype=torch.float64), torch.tensor(c["dist"], dtype=torch.float64)
        )
        off = (ideal - g).norm(dim=-1)
        c.update(
            invertible_fraction=float(ok.double().mean()),
            delta_avg_own_px=float(off[ok].mean()),
            delta_avg_inverts_px=float(off[published & ok].mean()),
            delta_avg_board_px=float(off[board & ok].mean()),
        )
        rows.append(c)
        print(f"| {c['model']} | {c['views']} ({c['n_views']}) | {c['rms_px']:.3f} | {c['held_out_rms_px']:.3f} | "
              f"{100 * c['invertible_fraction']:.1f} % | "
              f"{c['delta_avg_own_px']:.2f} | {c['delta_avg_inverts_px']:.2f} | {c['delta_avg_board_px']:.2f} |")
    report = {"calibrations": rows, "board_fraction": float(board.double().mean())}
    planar = res.get("planar") or {}
    if planar.get("coefficients"):
        cfg = LensdistConfig(calibration=CalibrationConfig(confidence=res.get("confidence", 0.95)))
        for key, where in (("inverts", published), ("board", board)):
            value, iv = delta_avg_where(planar, g[where], h, w, settings=cfg)
            report[f"answer_{key}"] = {"delta_avg_px": value, "interval": list(iv),
                                       "covers": [r["model"] + ", " + r["views"] for r in rows
                                                  if iv[0] <= r[f"delta_avg_{key}_px"] <= iv[1]]}
            print(
                f"the answer's homography model over the "
                f"{'pixels where the published calibration inverts' if key == 'inverts' else 'board region'}: "
                f"{value:.2f} px [{iv[0]:.2f}, {iv[1]:.2f}], "
                f"covering {len(report[f'answer_{key}']['covers'])} of {len(rows)}: "
                f"{'; '.join(report[f'answer_{key}']['covers']) or 'none'}"
            )
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
