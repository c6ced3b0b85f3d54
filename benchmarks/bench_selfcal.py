"""Benchmark of the beyond-the-paper estimators on the test pairs (docs/method.md, section 10).

Self-calibration (lensdist_torch.selfcal.fit.estimate_distortion) on N distorted test
pairs (indices < 400 of the 'test' set), drawn and rendered as the data sets are
(draw_pairs + render_pairs). Figures: class rate via distortion_class(delta_avg_hat,
delta_top('delta_avg')), RMSE of Delta_avg per class (px and % of the 14.4 px range), bias,
accuracy by t_y (< 10, >= 10 px), share of confident pairs and their accuracy, pairs/s
(estimation only: rendering and registration excluded). Two cases: ``selfcal`` (no init:
phase correlation) and, with ``--init``, ``selfcal_init`` (started from
estimate_homography's H as ``analyze`` does; both starts fitted).

Before/after: ``--baseline DIR`` also runs the ``lensdist_torch`` package found in DIR (e.g.
``git archive OLD lensdist_torch | tar -x -C DIR``) with its own defaults, in the same run, each
case in a fresh process, current and baseline alternating (``--repeats`` rounds; the best
pairs/s of each is reported) and prints current / baseline per case: the machine is shared
and noisy, the ratios are what to compare. ``--realistic`` renders the realistic protocol
(gain, gamma, illumination, noise, JPEG, parallax, occluders) instead of the clean one.

Regression (lensdist_torch.classify.regression.DeltaRegressor): if --data points to a
generated set, fitted on its training set, evaluated on its distorted test pairs, beside the
eigen-space 4-NN of the same set; skipped otherwise.

    python benchmarks/bench_selfcal.py --n 96 --threads 2 [--init] [--baseline DIR] [--repeats 3]
        [--realistic] [--data DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import os
import time

import torch


def figures(est, true, ty, top, confident=None) -> dict:
    from lensdist_torch.geometry.distortion import distortion_class

    est, true = est.double(), true.double()
    ok = torch.isfinite(est)
    c_true = distortion_class(true, top)
    c_est = torch.full_like(c_true, -1)
    c_est[ok] = distortion_class(est[ok].clamp_min(0), top)
    out = {"n": int(len(est)), "flagged": int((~ok).sum()), "class_rate": float((c_est == c_true).double().mean())}
    err = torch.where(ok, est - true, torch.zeros_like(est))
    out["rmse_px"] = float(err[ok].pow(2).mean().sqrt())
    out["bias_px"] = float(err[ok].mean())
    out["per_class"] = {}
    for c in range(4):
        m = (c_true == c) & ok
        if m.any():
            rm = float(err[m].pow(2).mean().sqrt())
            out["per_class"][str(c + 1)] = {
                "n": int(m.sum()),
                "rmse_px": rm,
                "rmse_pct": 100 * rm / top,
                "bias_px": float(err[m].mean()),
                "class_rate": float((c_est[m] == c).double().mean()),
            }
    for name, m in (("t_y < 10", ty < 10), ("t_y >= 10", ty >= 10)):
        out[name] = {
            "n": int(m.sum()),
            "class_rate": float((c_est[m] == c_true[m]).double().mean()) if m.any() else None,
            "rmse_px": float(err[m & ok].pow(2).mean().sqrt()) if (m & ok).any() else None,
        }
    if confident is not None:
        out["confident_share"] = float(confident.double().mean())
        out["confident_class_rate"] = (
            float((c_est[confident] == c_true[confident]).double().mean()) if confident.any() else None
        )
        out["unconfident_class_rate"] = (
            float((c_est[~confident] == c_true[~confident]).double().mean()) if (~confident).any() else None
        )
        out["confident_rmse_px"] = float(err[confident & ok].pow(2).mean().sqrt()) if (confident & ok).any() else None
    return out


def _case(args) -> dict:
    """One timed run in a fresh process: (code, n, batch, threads, use_init, realistic) -> figures."""
    code, n, batch, threads, use_init, realistic = args
    if code != "current":  # a baseline checkout: its package shadows the installed one
        import sys

        sys.path.insert(0, code)
    torch.set_num_threads(threads)
    # module paths, not the subpackages' exports: a baseline checkout may predate them
    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data.shards import load_scenes
    from lensdist_torch.data.synthesis import draw_pairs, render_pairs
    from lensdist_torch.geometry.distortion import delta_avg, delta_top
    from lensdist_torch.registration.direct import estimate_homography
    from lensdist_torch.selfcal.fit import estimate_distortion

    config = LensdistConfig()
    if realistic:
        config = dataclasses.replace(config, protocol=dataclasses.replace(config.protocol, realistic=True))
    scenes, _ = load_scenes(config)
    h, w = config.image.height, config.image.width
    batches = []
    for s in range(0, n, batch):
        p = draw_pairs(config, "test", list(range(s, min(n, s + batch))), len(scenes))
        i1, i2 = render_pairs(scenes, p, config)
        init = estimate_homography(i1, i2)[0] if use_init else None
        batches.append((i1, i2, init, delta_avg(p.k2, p.k4, h, w), p.motion[:, 0]))
    estimate_distortion(batches[0][0][:2], batches[0][1][:2])  # warm-up
    ests, confs, t_est = [], [], 0.0
    for i1, i2, init, _, _ in batches:
        t0 = time.perf_counter()
        _, _, _, info = estimate_distortion(i1, i2, init=init)
        t_est += time.perf_counter() - t0
        ests.append(info.delta_avg)
        confs.append(info.confident)
    out = figures(torch.cat(ests), torch.cat([b[3] for b in batches]), torch.cat([b[4] for b in batches]),
                  delta_top("delta_avg", config), torch.cat(confs))
    out["pairs_per_s"] = n / t_est
    return out


def bench_selfcal(n: int, batch: int, threads: int, cases, baseline: str | None, repeats: int, realistic: bool) -> dict:
    codes = ["current"] + ([baseline] if baseline else [])
    ctx = mp.get_context("spawn")
    best: dict = {}
    for _ in range(repeats):
        for name, use_init in cases:
            for code in codes:
                with ctx.Pool(1) as pool:
                    r = pool.apply(_case, ((code, n, batch, threads, use_init, realistic),))
                key = (name, "current" if code == "current" else "baseline")
                if key not in best or r["pairs_per_s"] > best[key]["pairs_per_s"]:
                    best[key] = r
    out = {}
    for name, _ in cases:
        out[name] = best[(name, "current")]
        if baseline:
            old = best[(name, "baseline")]
            out[name + " (baseline)"] = old
            out[name]["speed_ratio_to_baseline"] = out[name]["pairs_per_s"] / old["pairs_per_s"]
    return out


def bench_regression(data: str, config) -> dict | None:
    from lensdist_torch.data.shards import load_set, read_manifest
    from lensdist_torch.geometry import delta_top
    from lensdist_torch.workflows.evaluate import features_of, fit_classifier

    if not data or not os.path.isdir(data):
        return None
    from lensdist_torch.classify import DeltaRegressor

    try:
        read_manifest(data)
        train, test = load_set(data, "train"), load_set(data, "test")
    except Exception as exc:  # no usable set
        print(f"regression skipped: {exc}")
        return None
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


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=96, help="test pairs (at most 400)")
    ap.add_argument("--batch", type=int, default=32, help="pairs per call of estimate_distortion")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of each timed process")
    ap.add_argument("--init", action="store_true", help="also time the start from estimate_homography's H (as analyze)")
    ap.add_argument("--baseline", default=None, help="directory holding another lensdist_torch to compare with")
    ap.add_argument("--repeats", type=int, default=1, help="rounds per case; the best pairs/s is reported")
    ap.add_argument("--realistic", action="store_true", help="render the realistic protocol's test pairs")
    ap.add_argument("--data", default="", help="a generated data set for the regression benchmark")
    ap.add_argument("--skip-selfcal", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from lensdist_torch.config import LensdistConfig

    res = {"threads": a.threads, "load_average_before": os.getloadavg()}
    if not a.skip_selfcal:
        cases = [("selfcal", False)] + ([("selfcal_init", True)] if a.init else [])
        res["selfcal"] = bench_selfcal(min(a.n, 400), a.batch, a.threads, cases, a.baseline, a.repeats, a.realistic)
    reg = bench_regression(a.data, LensdistConfig())
    res["regression"] = reg if reg is not None else "skipped (no --data set)"
    res["load_average_after"] = os.getloadavg()
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
