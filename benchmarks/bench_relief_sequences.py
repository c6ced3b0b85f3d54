"""`lensdist calibrate` on rendered sequences of scenes with relief (issue 18, item 8).

Each sequence: 20 frames at 320 x 424 of a camera panning down an embedded scene (gravel or
grass) raised by a height field whose largest height is ``relief`` ~ U[1, 3] % of the camera's
height, seen as a pinhole camera looking straight down sees it (lensdist_torch.data.relief:
parallax in proportion to the baseline), with the realistic protocol's per-frame photometry
(``synthetic_sequence(..., realistic=True, relief=..., altitude=...)``), distorted by eq. 4 at
the levels of bench_calibrate.py (about the centres of classes R, 1-4). Four motions, in turn:

- ``pan``: translation only (5-10 px a frame, +-1 px jitter, no rotation, one altitude): the
  degenerate motion, under which a relief can imitate a distortion; the answer must be right or
  "cannot tell";
- ``pan+yaw``: the same with +-3 degrees of rotation per frame;
- ``pan+altitude``: the view's scale ~ U[0.9, 1] per frame (the camera's height changes);
- ``mixed``: both.

``--tilt DEG`` renders the same sequences as oblique views (each frame's optical axis tilted by a
pitch and a roll ~ U[-DEG, DEG], ``synthetic_sequence(..., tilt_deg=DEG)``): the frames' axes no
longer parallel, the configuration in which a 3-D scene and a radial distortion can no longer
trade (docs/method.md, section 11). ``--cases`` runs the listed indices instead of ``--start``/``--n``.

Each sequence is written as PNG frames and calibrated through the user's path,
``calibration.controllers.calibrate.calibrate_path(folder, method="auto")`` (the direct path and, with
pycolmap, the multi-view path, combined). Figures: Delta_avg error as % of the range (14.4 px)
over every sequence's estimate, coverage of the 95 % interval, confidently wrong (a class given
and wrong), "cannot tell", per motion and overall. Results are appended to ``--out`` after each
sequence (a long run keeps what it finished).

    python benchmarks/bench_relief_sequences.py --n 20 --threads 2 --out docs/results/bench_relief_sequences.json
    python benchmarks/bench_relief_sequences.py --n 40 --method direct \\
        --out docs/results/bench_relief_sequences_direct.json
    python benchmarks/bench_relief_sequences.py --start 40 --n 40 --method direct --raw \\
        --out ..._raw_validation.json

(``--raw``: the constants ``calibration.direct.RELIEF_TEST`` and ``RELIEF_REL`` set to 0 in this run: every
sequence reports its raw relief effect and z, the intervals without the relief term.)
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import torch

from lensdist_torch.calibration import direct
from lensdist_torch.calibration.controllers.calibrate import calibrate_path, synthetic_sequence
from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.core.png import encode_png
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.geometry.distortion import delta_avg, delta_top, distortion_class

LEVELS = (0.0, 0.125, 0.375, 0.625, 0.875)
SIZE = (320, 424)
MOTIONS = {
    "pan": {"rotation_deg": 0.0, "altitude": 0.0},
    "pan+yaw": {"rotation_deg": 3.0, "altitude": 0.0},
    "pan+altitude": {"rotation_deg": 0.0, "altitude": 0.1},
    "mixed": {"rotation_deg": 3.0, "altitude": 0.1},
}


def case(i: int, tilt_deg: float = 0.0) -> dict:
    """The i-th sequence's settings (deterministic in i), its frames tilted by up to ``tilt_deg``."""
    g = torch.Generator().manual_seed(70_000 + i)
    u = torch.rand(2, generator=g, dtype=torch.float64)
    cfg = LensdistConfig().distortion
    level = LEVELS[(i // len(MOTIONS)) % len(LEVELS)]
    c = 0.75 + 0.5 * float(u[0])
    motion = list(MOTIONS)[i % len(MOTIONS)]
    return {"index": i, "motion": motion, "relief": 0.01 + 0.02 * float(u[1]), "scene": ("gravel", "grass")[i % 2],
            "k2": level * cfg.k2_max * c, "k4": level * cfg.k4_max * (2 - c), "tilt_deg": tilt_deg, **MOTIONS[motion]}


def write_frames(frames: torch.Tensor, folder: Path) -> None:
    """(N, 1, H, W) frames in [0, 1] as 8-bit PNGs, with the writer undistort uses."""
    for j, f in enumerate(frames):
        (folder / f"frame_{j:03d}.png").write_bytes(encode_png((f.clamp(0, 1) * 255).round().to(torch.uint8)))


def run_one(spec: dict, method: str = "auto", settings: LensdistConfig | None = None) -> dict:
    frames, _ = synthetic_sequence(20, spec["k2"], spec["k4"], size=SIZE, scene=spec["scene"], seed=spec["index"],
                                   rotation_deg=spec["rotation_deg"], altitude=spec["altitude"],
                                   relief=spec["relief"], realistic=True, tilt_deg=spec["tilt_deg"])
    truth = float(delta_avg(spec["k2"], spec["k4"], *SIZE))
    with tempfile.TemporaryDirectory() as tmp:
        write_frames(frames, Path(tmp))
        t0 = time.perf_counter()
        res = calibrate_path(
            tmp, method=method, config=None if settings is None else settings.calibration, settings=settings
        )
        seconds = time.perf_counter() - t0
    top = delta_top("delta_avg", LensdistConfig())
    true_class = "R" if truth == 0 else str(int(distortion_class(torch.tensor([truth]), top)[0]) + 1)
    est = res.get("delta_avg_user_px")
    if est is None:
        est = res.get("estimated_delta_avg_user_px", res.get("estimated_delta_avg"))
    interval = res.get("delta_avg_user_interval")
    covered = None if not interval or interval[0] is None else bool(  # an upper end of None: unbounded (strict JSON)
        interval[0] <= truth <= (math.inf if interval[1] is None else interval[1]))
    cls = res.get("class")
    return {
        **spec,
        "truth_delta_avg": truth,
        "true_class": true_class,
        "estimate": est,
        "interval": interval,
        "covered": covered,
        "class": cls,
        "reason": res.get("reason"),
        "method": res.get("method"),
        "confidence": res.get("confidence"),
        "seconds": round(seconds, 1),
        "relief_effect_px": res.get("relief_effect_px"),
        "relief_z": res.get("relief_z"),
        "paths": {k: _path_summary(res.get(k)) for k in ("direct", "multiview", "planar")},
        "pairs_used": res.get("pairs_used"),
        "confidently_wrong": cls is not None and str(cls) != true_class,
    }


def _path_summary(part: dict | None) -> dict | None:
    """One path's own answer (class, Delta_avg, interval, reason) as calibrate_path reports it."""
    if not part:
        return None
    out = {k: part.get(k) for k in ("class", "delta_avg_user_px", "delta_avg_user_interval", "reason", "model",
                                     "rotation_spread_deg", "registered", "dispersion") if k in part}
    if part.get("models"):  # the multi-view comparison: each candidate's Delta_avg, weight and held-out RMS
        out["models"] = {
            m: {k: v.get(k) for k in ("delta_avg_px", "delta_avg_std_px", "weight", "elpd", "heldout_rms_px")}
            for m, v in part["models"].items()
        }
    return out


def summary(rows: list[dict]) -> dict:
    rng = float(delta_top("delta_avg", LensdistConfig()))
    out = {}
    for name in [*MOTIONS, "all"]:
        sel = [r for r in rows if name in ("all", r["motion"])]
        if not sel:
            continue
        err = [r["estimate"] - r["truth_delta_avg"] for r in sel if r["estimate"] is not None]
        cov = [r["covered"] for r in sel if r["covered"] is not None]
        out[name] = {
            "n": len(sel),
            "rmse_pct_of_range": None
            if not err
            else round(100 * math.sqrt(sum(e * e for e in err) / len(err)) / rng, 2),
            "worst_pct_of_range": None if not err else round(100 * max(abs(e) for e in err) / rng, 2),
            "coverage": None if not cov else round(sum(cov) / len(cov), 3),
            "with_interval": len(cov),
            "answered": sum(r["class"] is not None for r in sel),
            "confidently_wrong": sum(r["confidently_wrong"] for r in sel),
            "cannot_tell": sum(r["class"] is None for r in sel),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=16, help="number of sequences (the motions in turn)")
    ap.add_argument("--start", type=int, default=0, help="first sequence index (to resume)")
    ap.add_argument("--cases", type=int, nargs="+", default=None, help="these sequence indices instead")
    ap.add_argument("--tilt", type=float, default=0.0, help="oblique views: each frame tilted by up to this (deg)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--method", choices=["auto", "direct", "multiview"], default="auto",
                    help="calibrate_path's method (direct: the photometric path alone, seconds a sequence)")
    ap.add_argument(
        "--config", default=None, help="a TOML config for calibrate_path's settings (e.g. [selfcal] parallax)"
    )
    ap.add_argument("--raw", action="store_true", help="direct.RELIEF_TEST = RELIEF_REL = 0: no relief term")
    ap.add_argument("--out", type=Path, default=Path("bench_relief_sequences.json"))
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.raw:
        direct.RELIEF_TEST = direct.RELIEF_REL = 0.0
    rows = json.loads(args.out.read_text())["rows"] if args.start and args.out.exists() else []
    settings = load_config(args.config) if args.config else None  # read once, not per sequence
    for i in args.cases or range(args.start, args.start + args.n):
        rows.append(run_one(case(i, args.tilt), args.method, settings))
        r = rows[-1]
        print(f"{i:3d} {r['motion']:13s} relief {100 * r['relief']:.1f} %  truth {r['truth_delta_avg']:6.2f}  "
              f"est {r['estimate']}  interval {r['interval']}  class {r['class']} ({r['true_class']})  "
              f"{r['method']}  {r['seconds']} s  {r['reason'] or ''}", flush=True)
        atomic_write_text(args.out, json.dumps({"rows": rows, "summary": summary(rows)}, indent=1))
    print(json.dumps(summary(rows), indent=1))


if __name__ == "__main__":
    main()
