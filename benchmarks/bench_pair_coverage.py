"""Is a pair's answer honest at every motion? Coverage of the 95 % interval per motion bin.

Renders two-frame pans of the embedded training scenes (``synthetic_sequence``: both frames
carry the same eq. 4 distortion, Delta_avg ~ U[0, 14.4] px at 320 x 424, 80 % barrel, every
third pair with the realistic protocol's photometry, noise and JPEG), one motion per pair from
``STEPS`` (px per frame, from 0 to the protocol's largest t_y, 40 px), and analyses each with
``analyze_batch`` (the user's path). Per bin of the registration's motion (``motion_px``): the
pairs, the share answered (a class), the coverage of ``delta_avg_interval`` over the answered
pairs, the coverage of the estimate +- z std over all pairs, and the answered pairs whose class
is wrong. ``--methods`` adds the learned methods' answers on the same pairs (how many answer,
how many answer below ``analysis.min_motion_px``, how many of their answers are a wrong class).

``--fit`` (validation only: use another ``--seed`` than the one you report) runs with
``selfcal.fit.SMALL_MOTION_ERROR = 0`` and prints the smallest floor e (std = sqrt(std_cov^2 +
(e R^2 / m)^2)) whose intervals cover the truth in >= 95 % of every bin.

    python benchmarks/bench_pair_coverage.py --seed 1 --n 650 --fit            # validation: e
    python benchmarks/bench_pair_coverage.py --seed 2 --n 650 --out docs/results/bench_pair_coverage.json
    python benchmarks/bench_pair_coverage.py --design slow-pans --seed 11 --n 72 --fit  # the second validation set
    python benchmarks/bench_pair_coverage.py --design slow-pans --seed 0 --n 96        # the audit's own seeds
    python benchmarks/bench_pair_coverage.py --seed 1 --n 650 --score-level 1         # the relief stage on every pair
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch

from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.geometry.distortion import CLASS_LABELS, delta_avg, delta_top, distortion_class
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.selfcal import fit as selfcal_fit
from lensdist_torch.workflows.analyze import analyze_batch, prepare_batch
from lensdist_torch.workflows.class_mass import INTERVAL_CONFIDENCE

STEPS = (0.0, 0.3, 0.5, 1, 1.5, 2, 3, 4, 6, 8, 12, 16, 24, 32, 40)
BINS = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 64.0)
SIZE = (320, 424)


def draw(seed: int, j: int) -> dict:
    """Pair j of the run: its motion, distortion, scene and photometry (one generator per pair)."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + j)
    truth = float(torch.rand(1, generator=g, dtype=torch.float64)) * 14.4
    sign = 1.0 if float(torch.rand(1, generator=g)) < 0.8 else -1.0
    unit = (
        float(delta_avg(torch.tensor([1e-6], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64), *SIZE)[0])
        / 1e-6
    )
    return {
        "step": STEPS[j % len(STEPS)],
        "truth": truth,
        "k2": sign * truth / unit,
        "scene": ("gravel", "grass")[j % 2],
        "realistic": j % 3 == 0,
        "seed": seed * 1_000_003 + j,
    }


SLOW_K2 = (0.7e-6, 1.5e-6, 2.5e-6, 3.2e-6)  # Delta_avg 2.9, 6.3, 10.5, 13.4 px: near class boundaries
SLOW_STEPS = (1.2, 1.6, 2.2, 3.0, 4.0, 6.0)


def draw_slow(seed: int, j: int) -> dict:
    """Pair j of the slow-pan design (the third issue-19 audit's): clean gravel pans of a step
    ~ U[s, 1.1 s] px, +-0.5 px jitter, +-0.1 degree, every (k2, s) of the grid once per seed
    ``seed``, ``seed`` + 1, ..."""
    k2, step = SLOW_K2[(j // len(SLOW_STEPS)) % len(SLOW_K2)], SLOW_STEPS[j % len(SLOW_STEPS)]
    truth = float(
        delta_avg(torch.tensor([k2], dtype=torch.float64), torch.tensor([0.0], dtype=torch.float64), *SIZE)[0]
    )
    return {"step": step, "truth": truth, "k2": k2, "scene": "gravel", "realistic": False,
            "seed": seed + j // (len(SLOW_K2) * len(SLOW_STEPS)), "design": "slow-pans"}


def run(seed: int, n: int, cfg: LensdistConfig, methods: tuple[str, ...], design: str = "pans") -> list[dict]:
    rows = []
    for j in range(n):
        d = draw(seed, j) if design == "pans" else draw_slow(seed, j)
        steps, jitter, rot = (
            ((d["step"],) * 2, 1.0, 0.5) if design == "pans" else ((d["step"], 1.1 * d["step"]), 0.5, 0.1)
        )
        frames, _ = synthetic_sequence(2, d["k2"], 0.0, size=SIZE, scene=d["scene"], seed=d["seed"], step_px=steps,
                                       jitter_px=jitter, rotation_deg=rot, realistic=d["realistic"], config=cfg)
        prep = prepare_batch(frames[:1], frames[1:], config=cfg)
        for method in methods:
            r = analyze_batch(None, None, method=method, config=cfg, prepared=prep)[0]
            rows.append({**d, "method": method, "motion": r.motion_px, "class": r.class_label,
                         "estimate": r.estimated_delta_avg, "std": r.delta_avg_std,
                         "interval": r.delta_avg_interval, "confidence": r.confidence,
                         "raw_confidence": r.raw_confidence, "estimated_class": r.estimated_class})
    return rows


def _true_class(truth: float, cfg: LensdistConfig) -> str:
    t = torch.tensor([truth], dtype=torch.float64)
    return (
        CLASS_LABELS[int(distortion_class(t, delta_top("delta_avg", cfg))[0])]
        if truth >= cfg.analysis.no_distortion_px
        else "R"
    )


def table(rows: list[dict], cfg: LensdistConfig, floor: float | None = None) -> list[dict]:
    """Per motion bin: the figures of the self-calibration's rows (``floor``: recompute the std with it)."""
    z = float(torch.special.ndtri(torch.tensor(0.5 + INTERVAL_CONFIDENCE / 2, dtype=torch.float64)))
    r0 = half_diagonal(*SIZE)
    out = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = [r for r in rows if r["method"] == "selfcal" and r["motion"] is not None and lo <= r["motion"] < hi]
        est = [r for r in sel if r["estimate"] is not None and r["std"] is not None and math.isfinite(r["std"])]
        def std(r):
            return r["std"] if floor is None else math.hypot(r["std"], floor * r0**2 / max(r["motion"], 1e-3))
        cov_all = [abs(r["estimate"] - r["truth"]) <= z * std(r) for r in est]
        answered = [r for r in sel if r["class"] is not None]
        cov_ans = [r["interval"][0] <= r["truth"] <= r["interval"][1] for r in answered if r["interval"]]
        wrong = [r["class"] != _true_class(r["truth"], cfg) for r in answered]
        out.append({"motion_px": [lo, hi], "pairs": len(sel), "answered": len(answered),
                    "coverage_answered": sum(cov_ans) / len(cov_ans) if cov_ans else None,
                    "coverage_all": sum(cov_all) / len(cov_all) if cov_all else None,
                    "wrong_class_answered": sum(wrong)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--n", type=int, default=650)
    ap.add_argument("--config", default=None)
    ap.add_argument("--fit", action="store_true", help="fit selfcal.fit.SMALL_MOTION_ERROR (validation seed only)")
    ap.add_argument("--methods", nargs="+", default=["selfcal"], choices=["selfcal", "regression", "eigenspace"])
    ap.add_argument("--design", choices=["pans", "slow-pans"], default="pans",
                    help="pans: 0-40 px, any distortion; slow-pans: 1.2-6.6 px near class boundaries (n = 24 per seed)")
    ap.add_argument("--score-level", type=float, default=None,
                    help="selfcal.fit.PARALLAX_SCORE_LEVEL for this run (1: the relief stage fitted on every pair)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(args.config) if args.config else LensdistConfig()
    if args.fit:  # the floor off in this run: the covariance's own coverage
        selfcal_fit.SMALL_MOTION_ERROR = 0.0
    if args.score_level is not None:
        selfcal_fit.PARALLAX_SCORE_LEVEL = args.score_level
    t0 = time.perf_counter()
    rows = run(args.seed, args.n, cfg, tuple(dict.fromkeys(["selfcal", *args.methods])), args.design)
    result = {"seed": args.seed, "pairs": args.n, "design": args.design, "seconds": time.perf_counter() - t0,
              "small_motion_error": selfcal_fit.SMALL_MOTION_ERROR,
              "parallax_score_level": selfcal_fit.PARALLAX_SCORE_LEVEL, "bins": table(rows, cfg)}
    for method in args.methods:
        if method != "selfcal":
            sel = [r for r in rows if r["method"] == method]
            still = [r for r in sel if r["motion"] is not None and r["motion"] < cfg.analysis.min_motion_px]
            result[f"{method}_answered_below_min_motion"] = [sum(r["class"] is not None for r in still), len(still)]
            result[f"{method}_answered"] = sum(r["class"] is not None for r in sel)
            result[f"{method}_wrong_class_answered"] = sum(
                r["class"] not in (None, _true_class(r["truth"], cfg)) for r in sel
            )
    if args.fit:
        for e in [k * 1e-6 for k in range(0, 101)]:
            bins = table(rows, cfg, floor=e)
            if all(b["coverage_all"] is None or b["coverage_all"] >= 0.95 for b in bins):
                result["fitted_small_motion_error"] = e
                result["bins_fitted"] = bins
                break
    print(json.dumps(result, indent=1))
    if args.out:
        from lensdist_torch.core.storage import atomic_write_text

        atomic_write_text(args.out, json.dumps({**result, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
