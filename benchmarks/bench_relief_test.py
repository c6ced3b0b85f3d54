"""How a single pair weighs a flat scene against relief, chosen on validation pairs (issue 20).

For each condition (the default protocol, the planar realistic one, the relief realistic one;
validation split: the protocol seed moved by ``analysis.validation_seed_offset``) every
distorted pair is prepared as ``analyze`` prepares it (registration, analysis size) and
self-calibrated as ``analyze`` does (the planar model, then the plane + parallax one, Hausman's
test ``selfcal.parallax_test`` choosing the kept answer). Then, per candidate
``analysis.flat_prior`` w, the shipped rule (:func:`~lensdist_torch.workflows.prepare.flat_or_relief`):
the confidence w P(class | planar) + (1 - w) P(class | relief), "cannot tell" for relief where
the two answers fall in different classes, for a low confidence below ``analysis.min_confidence``.
Reported per condition and prior: right or "cannot tell", "cannot tell", right among
confident answers, confident wrong, and the ECE of the confidence over the pairs not withheld
for relief; the chosen prior is the one whose largest ECE over the conditions is least.
(Registration failures and the class-R pairs are left to ``lensdist reproduce``.)

    python benchmarks/bench_relief_test.py --n 400 --threads 2 --out docs/results/bench_relief_test.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

import torch

from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry import delta_avg, estimate_distortion, estimated_class
from lensdist_torch.geometry.distortion import CLASS_LABELS, from_normalized
from lensdist_torch.workflows import prepare_batch
from lensdist_torch.workflows.confidence import expected_calibration_error
from lensdist_torch.workflows.decision_fit import validation_config
from lensdist_torch.workflows.prepare import flat_or_relief

CONDITIONS = {"default": None, "planar_realistic": "configs/realistic.toml", "relief_realistic": "configs/realistic_relief.toml"}
PRIORS = (0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)


def condition(cfg: LensdistConfig, n: int, batch: int) -> dict:
    """Per pair: truth, relief fraction, the kept answer, both models' answers (Delta_avg, std) and Hausman's z."""
    val = validation_config(cfg)
    scenes = [load_scene(s) for s in val.protocol.scenes]
    idx = list(range(0, val.protocol.n_test_distorted, max(1, val.protocol.n_test_distorted // n)))[:n]
    params = draw_pairs(val, "test", idx, len(scenes))
    img1, img2 = render_pairs(scenes, params, val)
    true = delta_avg(params.k2, params.k4, *val.image.size).double()
    keys = ("d", "s", "d0", "s0", "d1", "s1", "z")
    rows = {"true": true.tolist(), **{k: [] for k in keys}}
    rows["relief"] = params.realism.relief[:, 0].tolist() if params.realism is not None else [0.0] * len(idx)
    size = val.image.size
    for s in range(0, len(idx), batch):
        p = prepare_batch(img1[s : s + batch], img2[s : s + batch], val)
        for j in range(p.img1.shape[0]):
            one = slice(j, j + 1)
            init = p.H[one] if bool(p.registration_ok[j]) else None
            *_, info = estimate_distortion(p.img1[one], p.img2[one], init=init, config=val.selfcal, validate=False)
            d0, d1 = (float(delta_avg(*from_normalized(ab, *size), *size)[0]) for ab in (info.planar_ab, info.relief_ab))
            for k, v in zip(keys, (info.delta_avg[0], info.delta_avg_std[0], d0, info.planar_std[0], d1, info.relief_std[0], info.relief_z[0])):
                rows[k].append(float(v))
    return rows


def summary(rows: dict, cfg: LensdistConfig, prior: float) -> dict:
    """The shipped rule with ``analysis.flat_prior`` = ``prior`` on one condition's pairs."""
    cfg = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, flat_prior=prior))
    t = torch.tensor(rows["true"], dtype=torch.float64)
    truth = estimated_class(t, t, "delta_avg", cfg).tolist()
    right = cannot = wrong = 0
    conf, ok = [], []
    for i, true_class in enumerate(truth):
        d = torch.tensor([rows["d"][i]], dtype=torch.float64)
        if not math.isfinite(rows["d"][i]):
            cannot += 1
            continue
        label = int(estimated_class(d, d, "delta_avg", cfg)[0])
        c, found = flat_or_relief(CLASS_LABELS[label], (rows["d0"][i], rows["s0"][i]), (rows["d1"][i], rows["s1"][i]), cfg)
        if not found:
            conf.append(c)
            ok.append(label == true_class)
        if found or c < cfg.analysis.min_confidence:
            cannot += 1
        elif label == true_class:
            right += 1
        else:
            wrong += 1
    n = len(truth)
    return {"right_or_cannot_tell": round(100 * (right + cannot) / n, 2), "cannot_tell": round(100 * cannot / n, 2),
            "right_among_confident": round(100 * right / max(1, right + wrong), 2), "confident_wrong": wrong,
            "ece": round(100 * expected_calibration_error(torch.tensor(conf, dtype=torch.float64), torch.tensor(ok)), 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=96, help="validation pairs per condition (distorted ones)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    out = {"priors": list(PRIORS), "conditions": {}}
    for name, path in CONDITIONS.items():
        cfg = load_config(path)
        t0 = time.perf_counter()
        rows = condition(cfg, a.n, a.batch)
        by_prior = {f"{w:g}": summary(rows, cfg, w) for w in PRIORS}
        out["conditions"][name] = {"config": path, "seconds": round(time.perf_counter() - t0, 1), "pairs": len(rows["d"]),
                                   "by_prior": by_prior, "per_pair": rows}
        print(name, json.dumps(by_prior), flush=True)
    worst = {f"{w:g}": max(c["by_prior"][f"{w:g}"]["ece"] for c in out["conditions"].values()) for w in PRIORS}
    out["largest_ece_by_prior"] = worst
    out["chosen_prior"] = float(min(worst, key=lambda k: (worst[k], -float(k))))
    print("largest ECE by prior", json.dumps(worst), "chosen", out["chosen_prior"], flush=True)
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
