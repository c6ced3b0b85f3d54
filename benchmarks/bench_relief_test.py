"""The plane + parallax test's threshold for single pairs, chosen on validation pairs (issue 20).

For each condition (the default protocol, the planar realistic one, the relief realistic one;
validation split: the protocol seed moved by ``analysis.validation_seed_offset``) every pair is
prepared as ``analyze`` prepares it (registration, analysis size) and self-calibrated twice, as
:func:`~lensdist_torch.geometry.selfcal.estimate_distortion` does with ``selfcal.parallax``: the
planar model (d0, s0) and the plane + parallax model; ``SelfCalInfo.relief_z``, Hausman's
statistic of their difference, is what ``selfcal.parallax_test`` thresholds (a threshold of 1e9
keeps every planar answer, so one call gives both). Reported per condition and threshold: the share of pairs
the test flags (on a planar scene, false alarms: each one a "cannot tell" for relief), and on
the relief condition how many wrong planar answers it catches; and the same for the rule
"the two models' answers fall in different classes" (``classes_differ``).

    python benchmarks/bench_relief_test.py --n 96 --threads 2 --out docs/results/bench_relief_test.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry import delta_avg, estimate_distortion, estimated_class
from lensdist_torch.geometry.distortion import from_normalized
from lensdist_torch.workflows import prepare_batch
from lensdist_torch.workflows.evaluate import validation_config

CONDITIONS = {"default": None, "planar_realistic": "configs/realistic.toml", "relief_realistic": "configs/realistic_relief.toml"}
THRESHOLDS = (2.0, 2.5, 3.0, 3.5, 4.0, 5.0)


def condition(cfg: LensdistConfig, n: int, batch: int) -> dict:
    """Per pair: truth, relief fraction, the planar answer (Delta_avg, std) and Hausman's z."""
    val = validation_config(cfg)
    scenes = [load_scene(s) for s in val.protocol.scenes]
    idx = list(range(0, val.protocol.n_test_distorted, max(1, val.protocol.n_test_distorted // n)))[:n]
    params = draw_pairs(val, "test", idx, len(scenes))
    img1, img2 = render_pairs(scenes, params, val)
    true = delta_avg(params.k2, params.k4, *val.image.size).double()
    rows = {"true": true.tolist(), "d0": [], "s0": [], "z": [], "d1": []}
    rows["relief"] = params.realism.relief[:, 0].tolist() if params.realism is not None else [0.0] * len(idx)
    test_only = dataclasses.replace(val.selfcal, parallax=5, parallax_test=1e9)  # the statistic, planar answers kept
    for s in range(0, len(idx), batch):
        p = prepare_batch(img1[s : s + batch], img2[s : s + batch], val)
        for j in range(p.img1.shape[0]):
            one = slice(j, j + 1)
            init = p.H[one] if bool(p.registration_ok[j]) else None
            *_, info = estimate_distortion(p.img1[one], p.img2[one], init=init, config=test_only, validate=False)
            rows["d0"].append(float(info.delta_avg[0]))
            rows["s0"].append(float(info.delta_avg_std[0]))
            rows["z"].append(float(info.relief_z[0]))
            ab = torch.nan_to_num(info.relief_ab.cpu(), nan=0.0)  # the relief model's answer, kept or not
            rows["d1"].append(float(delta_avg(*from_normalized(ab, *val.image.size), *val.image.size)[0]))
    return rows


def summary(rows: dict, cfg: LensdistConfig) -> dict:
    d0, s0, z, true = (torch.tensor(rows[k], dtype=torch.float64) for k in ("d0", "s0", "z", "true"))
    right = estimated_class(d0, d0, "delta_avg", cfg) == estimated_class(true, true, "delta_avg", cfg)
    wrong_planar = ~right & torch.isfinite(d0)
    out = {"pairs": len(rows["z"]), "planar_wrong_class": int(wrong_planar.sum())}
    d1 = torch.tensor(rows["d1"], dtype=torch.float64)
    differ = estimated_class(d0, d0, "delta_avg", cfg) != estimated_class(d1, d1, "delta_avg", cfg)
    out["classes_differ"] = {"flagged": int(differ.sum()), "flagged_share": round(float(differ.double().mean()), 4),
                             "planar_wrong_caught": int((differ & wrong_planar).sum())}
    for t in THRESHOLDS:
        flag = torch.nan_to_num(z, nan=0.0) >= t
        out[f"z>={t:g}"] = {"flagged": int(flag.sum()), "flagged_share": round(float(flag.double().mean()), 4),
                           "planar_wrong_caught": int((flag & wrong_planar).sum())}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=96, help="validation pairs per condition (distorted ones)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    out = {"thresholds": list(THRESHOLDS), "conditions": {}}
    for name, path in CONDITIONS.items():
        cfg = load_config(path)
        t0 = time.perf_counter()
        rows = condition(cfg, a.n, a.batch)
        out["conditions"][name] = {"config": path, "seconds": round(time.perf_counter() - t0, 1),
                                   **summary(rows, cfg), "per_pair": rows}
        print(name, json.dumps({k: v for k, v in out["conditions"][name].items() if k != "per_pair"}), flush=True)
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
