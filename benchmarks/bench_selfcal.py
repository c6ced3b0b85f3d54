"""Benchmark of the beyond-the-paper estimators on SPEC test pairs.

Self-calibration (lensdist_torch.selfcal.estimate_distortion) on N distorted test pairs
(indices < 400 of the 'test' set). The pairs are drawn and rendered exactly as make_pairs does
(draw_pairs + render_pairs; make_pairs' registration and quality map are not needed here).
Figures: class rate via distortion_class(delta_avg_hat, delta_top('delta_avg')), RMSE of
Delta_avg per class (px and % of the 14.4 px range), bias, accuracy by t_y (< 10, >= 10 px),
share of confident pairs and their accuracy, pairs/s (estimation only, rendering excluded).

Regression (lensdist_torch.regression.DeltaRegressor): if --data points to a generated set
(lensdist_torch.dataset.generate), fitted on its training set, evaluated on its distorted test
pairs, beside the eigen-space 4-NN of the same set; skipped otherwise.

    python benchmarks/bench_selfcal.py --n 96 --threads 2 [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.shards import load_scenes
from lensdist_torch.geometry.distortion import delta_avg, delta_top, distortion_class
from lensdist_torch.geometry.selfcal import estimate_distortion
from lensdist_torch.data.synthesis import draw_pairs, render_pairs


def figures(est, true, ty, top, confident=None) -> dict:
    est, true = est.double(), true.double()
    ok = torch.isfinite(est)
    c_true = distortion_class(true, top)
    c_est = torch.full_like(c_true, -1)
    c_est[ok] = distortion_class(est[ok], top)
    out = {"n": int(len(est)), "flagged": int((~ok).sum()), "class_rate": float((c_est == c_true).double().mean())}
    err = torch.where(ok, est - true, torch.zeros_like(est))
    out["rmse_px"] = float(err[ok].pow(2).mean().sqrt())
    out["bias_px"] = float(err[ok].mean())
    out["per_class"] = {}
    for c in range(4):
        m = (c_true == c) & ok
        if m.any():
            rm = float(err[m].pow(2).mean().sqrt())
            out["per_class"][str(c + 1)] = {"n": int(m.sum()), "rmse_px": rm, "rmse_pct": 100 * rm / top,
                                            "bias_px": float(err[m].mean()), "class_rate": float((c_est[m] == c).double().mean())}
    for name, m in (("t_y < 10", ty < 10), ("t_y >= 10", ty >= 10)):
        out[name] = {"n": int(m.sum()), "class_rate": float((c_est[m] == c_true[m]).double().mean()) if m.any() else None,
                     "rmse_px": float(err[m & ok].pow(2).mean().sqrt()) if (m & ok).any() else None}
    if confident is not None:
        out["confident_share"] = float(confident.double().mean())
        out["confident_class_rate"] = float((c_est[confident] == c_true[confident]).double().mean()) if confident.any() else None
        out["unconfident_class_rate"] = float((c_est[~confident] == c_true[~confident]).double().mean()) if (~confident).any() else None
        out["confident_rmse_px"] = float(err[confident & ok].pow(2).mean().sqrt()) if (confident & ok).any() else None
    return out


def bench_selfcal(n: int, batch: int, config: LensdistConfig) -> dict:
    scenes, _ = load_scenes(config)
    h, w = config.image.height, config.image.width
    top = delta_top("delta_avg", config)
    ests, trues, tys, confs, t_est = [], [], [], [], 0.0
    for s in range(0, n, batch):
        idx = list(range(s, min(n, s + batch)))
        p = draw_pairs(config, "test", idx, len(scenes))
        i1, i2 = render_pairs(scenes, p, config)
        t0 = time.perf_counter()
        _, _, _, info = estimate_distortion(i1, i2)
        t_est += time.perf_counter() - t0
        ests.append(info.delta_avg)
        confs.append(info.confident)
        trues.append(delta_avg(p.k2, p.k4, h, w))
        tys.append(p.motion[:, 0])
    out = figures(torch.cat(ests), torch.cat(trues), torch.cat(tys), top, torch.cat(confs))
    out["pairs_per_s"] = n / t_est
    return out


def bench_regression(data: str, config: LensdistConfig) -> dict | None:
    from lensdist_torch.data.shards import load_set, read_manifest
    from lensdist_torch.workflows.evaluate import features_of, fit_classifier
    if not data or not os.path.isdir(data):
        return None
    from lensdist_torch.classify.regression import DeltaRegressor

    try:
        read_manifest(data)
        train, test = load_set(data, "train"), load_set(data, "test")
    except Exception as exc:  # no usable set
        print(f"regression skipped: {exc}")
        return None
    h, w = config.image.height, config.image.width
    out = {}
    ok = train["converged"]
    x = features_of(train, config)
    reg = DeltaRegressor(x.shape[1], config).fit(x[ok], train["delta_avg"][ok], train["delta_max"][ok])
    xt = features_of(test, config)
    dist = test["class_avg"] != 4
    ty = test["motion"][:, 0]
    with torch.no_grad():
        r = reg(xt)
    for metric in ("delta_avg", "delta_max"):
        top = delta_top(metric, config)
        est = getattr(r, metric).clamp_min(1e-6)
        out[f"regression_{metric}"] = figures(est[dist], test[metric][dist], ty[dist], top, r.confident[dist])
        clf = fit_classifier(train, config, n_eigenvectors=10, metric=metric)
        with torch.no_grad():
            cr = clf(xt)
        out[f"eigen4nn_{metric}"] = figures(cr.delta[dist].double().clamp_min(1e-6), test[metric][dist], ty[dist], top)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=96)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", default="")
    ap.add_argument("--skip-selfcal", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    config = LensdistConfig()
    res = {"threads": a.threads, "load_average": os.getloadavg()}
    if not a.skip_selfcal:
        res["selfcal"] = bench_selfcal(min(a.n, 400), a.batch, config)
    reg = bench_regression(a.data, config)
    res["regression"] = reg if reg is not None else "skipped (no --data set)"
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
