"""The homography model on real views against their chessboard calibration, over the pixels where it inverts.

    python benchmarks/bench_real_homography.py [--views tests/data/real/gopro_hero4_wall]
        [--answer ANSWER.json --calibration ../shared/real/gopro_hero4_wall/calibration.json]
        [--out docs/results/bench_real_homography.json]

``--views``: a folder of frames with ``calibration.json`` (``K``, ``dist``, ``frames``) at the frames'
size, by default the twelve GoPro views at 320 x 240 the tests use. The homography model runs through
the public API four ways, as ``tests/geometry/test_real_frames.py`` runs it: on COLMAP's verified
matches, with guided matching forced, with the matches refined against the frames, and both. Each
answer's Delta_avg and interval are measured where the calibration's model inverts
(:func:`~lensdist_torch.calibration.planar_features.delta_avg_where`), beside the calibration's own.

``--answer``: also the ``planar`` block of a saved ``lensdist calibrate FRAMES --json`` answer, at
its own frame size, against ``--calibration``'s ``primary`` camera (calibrated at ``image_size``,
scaled to the answer's: f times s, c as (c + 0.5) s - 0.5).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from lensdist_torch.calibration import guided_matching
from lensdist_torch.calibration.guided_matching import self_calibrate_guided
from lensdist_torch.calibration.matches import read_verified_matches
from lensdist_torch.calibration.multiview import extract_and_match
from lensdist_torch.calibration.planar_features import delta_avg_where, self_calibrate_planar
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.core import atomic_write_text, load_image
from lensdist_torch.geometry.opencv_model import grid_points, opencv_ideal_points


def on_footprint(planar, k: torch.Tensor, dist: torch.Tensor, h: int, w: int) -> dict:
    """The calibration's Delta_avg where it inverts, and the answer's there with its interval."""
    g = grid_points(h, w, 1)
    ideal, ok = opencv_ideal_points(g, k, dist)
    value, (lo, hi) = delta_avg_where(planar, g[ok], h, w)
    truth = float((ideal[ok] - g[ok]).norm(dim=-1).mean())
    model = planar.model if hasattr(planar, "model") else planar["model"]
    return {"model": model, "truth_px": truth, "answer_px": value, "interval": [lo, hi], "covers": lo <= truth <= hi,
            "error_rel": value / truth - 1, "footprint": float(ok.double().mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=Path, default=Path("tests/data/real/gopro_hero4_wall"))
    ap.add_argument("--answer", type=Path, default=None)
    ap.add_argument("--calibration", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cal = json.loads((args.views / "calibration.json").read_text())
    names = sorted(cal["frames"])
    h, w = load_image(args.views / names[0]).shape[-2:]
    k, dist = (torch.tensor(cal[key], dtype=torch.float64) for key in ("K", "dist"))
    first = MultiViewConfig(num_threads=1)

    def forced(run):  # guided matching wherever the first fit found a plane (PLANAR_GUIDED_BELOW at 1)
        def call():
            below, guided_matching.PLANAR_GUIDED_BELOW = guided_matching.PLANAR_GUIDED_BELOW, 1.0
            try:
                return run()
            finally:
                guided_matching.PLANAR_GUIDED_BELOW = below
        return call

    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "db.db"
        extract_and_match(db, args.views, names, config=first, image_size=(h, w))
        images = lambda v: load_image(args.views / names[v])[0, 0]  # noqa: E731
        runs = {
            "verified": lambda: self_calibrate_planar(read_verified_matches(db, names), (h, w), config=first),
            "guided": forced(lambda: self_calibrate_guided(db, names, (h, w), config=first)),
            "refined": lambda: self_calibrate_guided(db, names, (h, w), config=first, images=images),
            "guided and refined": forced(lambda: self_calibrate_guided(db, names, (h, w), config=first, images=images)),
        }
        for name, run in runs.items():
            t0 = time.perf_counter()
            res = run()
            rows[name] = {**on_footprint(res, k, dist, h, w), "seconds": time.perf_counter() - t0}
    if args.answer is not None:
        answer = json.loads(args.answer.read_text())
        primary = json.loads(args.calibration.read_text())["primary"]
        ah, aw = answer["image_size"]
        s = aw / primary["image_size"][0]
        ka = torch.tensor(primary["K"], dtype=torch.float64)
        ka[:2, :2] *= s
        ka[:2, 2] = (ka[:2, 2] + 0.5) * s - 0.5
        rows[f"answer at {aw} x {ah}"] = on_footprint(answer["planar"], ka, torch.tensor(primary["dist"]).double(),
                                                      ah, aw)
    print("| matches | model | truth (px) | answer (px) | 95 % interval | covers |\n|---|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {r['model']} | {r['truth_px']:.2f} | {r['answer_px']:.2f} ({100 * r['error_rel']:+.1f} %) | "
              f"[{r['interval'][0]:.2f}, {r['interval'][1]:.2f}] | {'yes' if r['covers'] else 'no'} |")
    if args.out is not None:
        atomic_write_text(args.out, json.dumps({"views": str(args.views), "rows": rows}, indent=1, allow_nan=False))


if __name__ == "__main__":
    main()
