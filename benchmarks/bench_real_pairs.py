"""Single pairs of real frames with a published calibration: does a confident answer's interval cover the truth?

Every consecutive pair of FRAMES_DIR is analysed as `lensdist analyze` does (`analyze_pair`,
self-calibration); the answer's Delta_avg and its interval in the user's pixels over the whole frame
(`delta_avg_user_px`, `delta_avg_user_interval`) against the truth, Delta_avg of the calibration
(user px, over the pixels where its model inverts: the `truth` of bench_real_calibration.py's JSON,
given here as --truth).

    python benchmarks/bench_real_pairs.py /work/shared/real/gopro_hero4_wall/frames --truth 103.15 [--out F.json]

``--config`` analyses under another decision, e.g. a ``calibration.toml`` that ``lensdist
reproduce`` fitted on a rendered condition (its std scales): do they hold on real frames?
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from lensdist_torch.core.images import IMAGE_SUFFIXES
from lensdist_torch.workflows import analyze_pair


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames")
    ap.add_argument("--truth", type=float, required=True, help="Delta_avg of the published calibration, user px")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    ap.add_argument("--config", default=None, help="TOML config of the analysis (default: the shipped one)")
    args = ap.parse_args()
    from lensdist_torch.config import load_config

    cfg = load_config(args.config)
    torch.set_num_threads(args.threads)
    frames = sorted(p for p in Path(args.frames).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    rows = []
    for a, b in zip(frames[:-1], frames[1:]):
        r = analyze_pair(str(a), str(b), config=cfg)
        s = r.user_px_per_analysis_px  # the answer's own numbers over the whole frame; the estimate's where none
        estimate = r.delta_avg_user_px if r.delta_avg_user_px is not None else (
            None if r.estimated_delta_avg is None else r.estimated_delta_avg * s)
        rows.append({"pair": [a.name, b.name], "registered": r.registration_ok, "motion_px": r.motion_px,
                     "class": r.class_label, "confidence": r.confidence, "reasons": r.cannot_tell_reasons,
                     "relief_z": r.relief_z, "estimate_user_px": estimate,
                     "interval_user_px": r.delta_avg_user_interval})
    answered = [x for x in rows if x["class"] is not None]
    with_iv = [x for x in answered if x["interval_user_px"]]
    covers = [x for x in with_iv if x["interval_user_px"][0] <= args.truth <= x["interval_user_px"][1]]
    summary = {
        "pairs": len(rows),
        "registered": sum(x["registered"] for x in rows),
        "answered": len(answered),
        "classes": sorted({x["class"] for x in answered}),
        "answered_with_interval": len(with_iv),
        "interval_covers_truth": len(covers),
        "truth_user_px": args.truth,
        "config": args.config,
        "estimates_user_px": [round(x["estimate_user_px"], 1) for x in answered],
        "cannot_tell_reasons": {
            c: sum(c in x["reasons"] for x in rows) for c in sorted({c for x in rows for c in x["reasons"]})
        },
    }
    print(json.dumps(summary, indent=1))
    if args.out:
        from lensdist_torch.core import atomic_write_text

        atomic_write_text(args.out, json.dumps({**summary, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
