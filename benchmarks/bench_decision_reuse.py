"""What a second decision costs ``reproduce``: the same pairs answered again from their fits.

``lensdist reproduce`` answers its test pairs under the decision fitted on the validation split
and under the shipped one (the reports' rows "shipped decision"). The second comes from the
first's self-calibration fits (``PreparedPairs.with_decision``), not from a second analysis.
This times, in one process with pinned threads and alternating passes (the best of each counts),
on the same rendered test pairs: the whole self-calibration (``analyze_batch`` on a fresh
prepared batch: the fits and the answers), and the answers alone under another ``[analysis]``
from fits already made; reports seconds per pair of each and the ratio.

    python benchmarks/bench_decision_reuse.py --n 32 --threads 1 --out docs/results/bench_decision_reuse.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from lensdist_torch import analyze_batch, load_config
from lensdist_torch.core import atomic_write_text
from lensdist_torch.data import draw_pairs, render_pairs
from lensdist_torch.data.shards import load_scenes
from lensdist_torch.workflows.prepare import prepare_batch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=32, help="test pairs of the default protocol")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2, help="alternating timed passes (the best counts)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg = load_config(None)
    other = dataclasses.replace(cfg.analysis, no_distortion_px=0.25, selfcal_std_scale=0.5)  # another decision
    scenes, _ = load_scenes(cfg)
    batches = []
    for s in range(0, a.n, a.batch):
        params = draw_pairs(cfg, "test", list(range(s, min(a.n, s + a.batch))), len(scenes))
        batches.append(render_pairs(scenes, params, cfg))
    whole, again, same = [], [], True
    for _ in range(a.repeats):
        t_whole = t_again = 0.0
        for img1, img2 in batches:
            p = prepare_batch(img1, img2, config=cfg)  # the registration: in neither time
            t0 = time.perf_counter()
            first = analyze_batch(None, None, config=cfg, prepared=p)
            t1 = time.perf_counter()
            second = analyze_batch(None, None, prepared=p.with_decision(other))
            t2 = time.perf_counter()
            t_whole, t_again = t_whole + t1 - t0, t_again + t2 - t1
            same &= [r.estimated_delta_avg for r in first] == [r.estimated_delta_avg for r in second]
        whole.append(t_whole / a.n)
        again.append(t_again / a.n)
    out = {"pairs": a.n, "threads": a.threads, "repeats": a.repeats, "self_calibration_s_per_pair": min(whole),
           "another_decision_s_per_pair": min(again), "ratio": min(again) / min(whole), "same_estimates": same}
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        atomic_write_text(a.out, text + "\n")


if __name__ == "__main__":
    main()
