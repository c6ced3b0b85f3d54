"""Which calibration the scene's own texture agrees with: every lens judged on the frames' feature matches.

    python benchmarks/bench_calibration_verdict.py FRAMES CALIBRATION.json CORNERS.json ANSWER.json
        [--threads 2] [--out docs/results/bench_calibration_verdict.json]

(``--threads 1``: COLMAP's matches repeat bit for bit; with more, a few matches differ run to run.)

A chessboard calibration is a truth only as far as its model follows the lens: two OpenCV models
fitted to the same corners put Delta_avg 3.4 % apart (``bench_calibration_spread.py``). The board's
corners cannot referee between them (each model was fitted to them), but the frames can: where
the scene is a plane (the GoPro views: a flat wall), the right lens makes every pair's matches one
homography apart. This benchmark finds the frames' matches as ``lensdist calibrate`` does
(COLMAP's SIFT and verified matches into a temporary database, guided matching and sub-pixel
refinement under ANSWER's lens: :func:`~lensdist_torch.calibration.guided_matching.guided_matches`,
:func:`~lensdist_torch.calibration.guided_matching.refined_matches`) and judges each lens on them:
the published calibration, the board calibrated again (``bench_calibration_spread.calibrations``:
OpenCV's standard and rational models on all, even and odd views), COLMAP's camera where ANSWER
carries one (``multiview``: its self-calibration by bundle adjustment on the same frames, an
OpenCV model), and ANSWER's homography model,
both as answered (fitted on these matches: in-sample) and held out (fitted on every other pair,
judged on the rest, and the other way round; :func:`~lensdist_torch.calibration.planar_features.self_calibrate_planar`).

Per pair and lens: the matches' ideal points, one homography between them (``cv2.findHomography``,
RANSAC at 3 px, the same for every lens), each match's transfer error taken back through the lens
into the image (px, the mean of both directions); a match the lens does not invert is counted as
such, not as an error. Reported over the board's region (both points inside some view's board,
where the corners measured the lens), outside it, and over all matches: the median, RMS and the
share over 2 px; beside them each lens's Delta_avg where the published calibration inverts (the
truth of ``bench_real_calibration.py``; the held-out row: each half's). ANSWER.json: the JSON of
``lensdist calibrate FRAMES --json`` (or ``bench_real_calibration.py``'s report).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import torch
from bench_calibration_spread import board_region, calibrations

from lensdist_torch.calibration.guided_matching import guided_matches, read_features, refined_matches
from lensdist_torch.calibration.matches import PLANAR_MIN_MATCHES, PlanarMatches, read_verified_matches
from lensdist_torch.calibration.multiview import extract_and_match
from lensdist_torch.calibration.planar_features import self_calibrate_planar
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.core.frames import list_frames
from lensdist_torch.core.images import load_image
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.geometry.opencv_model import grid_points, opencv_distort_full, opencv_ideal_points
from lensdist_torch.geometry.radial_lens import lens_distorted_points, lens_ideal_points


def opencv_lens(k, dist):
    """(ideal, distort) of an OpenCV camera: pixels -> (ideal pixels, ok) and back."""
    k, dist = torch.tensor(k, dtype=torch.float64), torch.tensor(dist, dtype=torch.float64)
    f, c = torch.stack([k[0, 0], k[1, 1]]), k[:2, 2]
    return (lambda p: opencv_ideal_points(p, k, dist),
            lambda u: (opencv_distort_full((u - c) / f, dist) * f + c, torch.ones(len(u), dtype=torch.bool)))


def radial_lens(coefficients, centre, size):
    """(ideal, distort) of the homography model's lens a_1 .. a_n about ``centre``."""
    h, w = size
    return (lambda p: (lens_ideal_points(p, coefficients, h, w, centre=centre), torch.ones(len(p), dtype=torch.bool)),
            lambda u: lens_distorted_points(u, coefficients, h, w, centre=centre))


def transfer_errors(lens, m: PlanarMatches, pairs) -> torch.Tensor:
    """(N,) each match's transfer error (image px) under ``lens`` on the ``pairs`` given; NaN elsewhere or where it
    does not invert."""
    import cv2

    ideal, distort = lens
    u1, ok1 = ideal(m.x1)
    u2, ok2 = ideal(m.x2)
    out = torch.full((len(m.x1),), math.nan, dtype=torch.float64)
    for p in pairs:
        s = (m.pair == p) & ok1 & ok2
        if int(s.sum()) < 8:
            continue
        hm, _ = cv2.findHomography(u1[s].numpy(), u2[s].numpy(), cv2.RANSAC, 3.0)
        if hm is None:
            continue
        hm = torch.from_numpy(hm)
        p2, k2 = distort(apply_homography(hm[None], u1[s])[0])
        p1, k1 = distort(apply_homography(torch.linalg.inv(hm)[None], u2[s])[0])
        e = 0.5 * ((p2 - m.x2[s]).norm(dim=-1) + (p1 - m.x1[s]).norm(dim=-1))
        out[s] = torch.where(k1 & k2, e, torch.full_like(e, math.nan))
    return out


def delta_avg(lens, points: torch.Tensor) -> float:
    """Delta_avg (px) of ``lens`` over ``points`` where it inverts."""
    ideal, ok = lens[0](points)
    return float((ideal - points).norm(dim=-1)[ok].mean())


def summary(errors: torch.Tensor, where: torch.Tensor) -> dict:
    """Median, RMS, share over 2 px of the finite ``errors`` among ``where``, and how many were not judged."""
    e = errors[where]
    ok = torch.isfinite(e)
    e = e[ok]
    if not len(e):
        return {"matches": 0, "not_judged": int((~ok).sum())}
    return {"matches": len(e), "not_judged": int((~ok).sum()), "median_px": float(e.median()),
            "rms_px": float(e.square().mean().sqrt()), "over_2px": float((e > 2).double().mean())}


def halves(m: PlanarMatches, size, cfg: MultiViewConfig, start) -> list:
    """The homography model fitted on the even pairs and on the odd ones: [(coefficients, centre)] * 2."""
    out = []
    n = len(m.first)
    for half in (0, 1):
        keep = torch.arange(half, n, 2)
        index = torch.full((n,), -1, dtype=torch.long)
        index[keep] = torch.arange(len(keep))
        s = index[m.pair] >= 0
        sub = PlanarMatches(m.x1[s], m.x2[s], index[m.pair[s]], m.first[keep], m.second[keep], m.names)
        fit = self_calibrate_planar(sub, size, config=cfg, start=start)
        out.append((fit.coefficients, fit.centre))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames")
    ap.add_argument("calibration")
    ap.add_argument("corners")
    ap.add_argument("answer")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    frames = Path(args.frames)
    names = [p.name for p in list_frames(frames)]  # as `lensdist calibrate` orders them
    cal = json.loads(Path(args.calibration).read_text())["primary"]
    corners = json.loads(Path(args.corners).read_text())
    res = json.loads(Path(args.answer).read_text())
    res = res["answer"] if "answer" in res and "image_size" not in res else res
    size = tuple(res["image_size"])
    planar = res["planar"]
    cfg = MultiViewConfig(num_threads=args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        db = str(Path(tmp) / "frames.db")
        extract_and_match(db, frames, names, config=cfg, image_size=size)
        verified = read_verified_matches(db, names, PLANAR_MIN_MATCHES)
        found = guided_matches(
            read_features(db, names), verified, planar["coefficients"], centre=planar["centre"], size=size, config=cfg
        )
    m, info = refined_matches(found, lambda v: load_image(frames / names[v])[0, 0], planar["coefficients"],
                              centre=planar["centre"], size=size, config=cfg)
    m = m._replace(x1=m.x1.double(), x2=m.x2.double())
    board = board_region(corners, size, m.x1) & board_region(corners, size, m.x2)
    regions = {"board": board, "outside": ~board, "all": torch.ones_like(board)}
    every = range(len(m.first))
    lenses = [("published", "standard (5)", "all views", opencv_lens(cal["K"], cal["dist"]), None)]
    lenses += [
        ("refit", c["model"], c["views"], opencv_lens(c["K"], c["dist"]), None) for c in calibrations(corners, size)
    ]
    lenses.append(
        ("answer", "homography model", "in-sample", radial_lens(planar["coefficients"], planar["centre"], size), None)
    )
    mv = res.get("multiview") or {}
    if mv.get("camera_matrix") and mv.get("dist_coeffs"):  # COLMAP's self-calibration on the same frames
        lenses.append(
            (
                "COLMAP",
                mv.get("model", ""),
                "its reconstruction",
                opencv_lens(mv["camera_matrix"], mv["dist_coeffs"]),
                None,
            )
        )
    g = grid_points(*size, 2)
    g = g[opencv_lens(cal["K"], cal["dist"])[0](g)[1]]  # where the published calibration inverts
    rows = []
    for kind, model, views, lens, _ in lenses:
        e = transfer_errors(lens, m, every)
        rows.append({"calibration": kind, "model": model, "views": views, "delta_avg_px": delta_avg(lens, g),
                     **{k: summary(e, r) for k, r in regions.items()}})
    held = halves(m, size, cfg, planar["coefficients"])
    e = torch.full((len(m.x1),), math.nan, dtype=torch.float64)
    for half in (0, 1):  # fitted on one half of the pairs, judged on the other
        other = range(1 - half, len(m.first), 2)
        part = transfer_errors(radial_lens(held[half][0], held[half][1], size), m, other)
        e = torch.where(torch.isfinite(part), part, e)
    rows.append(
        {
            "calibration": "answer",
            "model": "homography model",
            "views": "held out (two halves of the pairs)",
            "delta_avg_px": [delta_avg(radial_lens(h[0], h[1], size), g) for h in held],
            **{k: summary(e, r) for k, r in regions.items()},
        }
    )
    print(f"{len(m.x1)} refined matches in {len(m.first)} pairs ({info['kept']} of {info['matches']} kept), "
          f"{int(board.sum())} inside the board's region")
    print("| lens | model | fitted on | board: median / RMS / > 2 px | outside | all | not inverted | Delta_avg (px) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        cells = [
            f"{r[k]['median_px']:.3f} / {r[k]['rms_px']:.3f} / {100 * r[k]['over_2px']:.1f} %"
            if r[k]["matches"]
            else "-"
            for k in regions
        ]
        print(
            f"| {r['calibration']} | {r['model']} | {r['views']} | {' | '.join(cells)} | {r['all']['not_judged']} | "
            f"{' / '.join(f'{v:.2f}' for v in (r['delta_avg_px'] if isinstance(r['delta_avg_px'], list) else [r['delta_avg_px']]))} |"  # noqa: E501
        )
    if args.out:
        report = {
            "matches": len(m.x1),
            "pairs": len(m.first),
            "refined": info,
            "board_matches": int(board.sum()),
            "rows": rows,
        }
        atomic_write_text(Path(args.out), json.dumps(report, indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    main()
