"""How a single pair weighs a flat scene against relief, chosen on validation pairs (issue 20).

For each condition (the default protocol, the planar realistic one, the relief realistic one)
the first ``--n`` distorted pairs of the validation split (the test set of
:func:`~lensdist_torch.workflows.decision_fit.validation_config`: the protocol seed moved by
``decision_fit.VALIDATION_SEED_OFFSET``) are generated and analysed as ``lensdist reproduce`` does
(:func:`~lensdist_torch.workflows.decision_fit.fit_confidence`): ``generate`` and ``load_set``,
then :func:`~lensdist_torch.workflows.evaluate.analyze_test_set`, the user's path
(``analyze_batch``: registration, self-calibration with Hausman's test choosing the kept answer,
the decision). Then, per candidate ``analysis.flat_prior`` w, each pair's confidence is what
``analyze`` would have said under w
(:func:`~lensdist_torch.workflows.class_mass.rescored_confidence`, through the config's Platt map):
w P(class | planar) + (1 - w) P(class | relief). Neither the class nor relief found depends on
w, so a pair is "cannot tell" where ``analyze`` withheld it for another reason than a low
confidence (registration, overlap, no estimate, motion, relief: outside
:func:`~lensdist_torch.workflows.decision_fit.scored_pairs`) or where its confidence under w is
below ``analysis.min_confidence``. Reported per condition and prior: right or "cannot tell",
"cannot tell", right among confident answers, confident wrong, and the ECE of the confidence over
the scored pairs, the pairs whose answer the confidence decides (as ``lensdist reproduce``
reports it; with ``--undistorted`` also each condition's class-R validation pairs: the share
answered R); the chosen prior is the one whose largest ECE over the conditions is least. Each
condition also checks itself: at the config's own prior the recomputed confidences and
"cannot tell"s must be ``analyze``'s (``check``). (The class-R pairs are left to ``lensdist
reproduce``.)

With ``--thresholds`` (and ``--undistorted``) the shipped R threshold is chosen the same way, at
the config's prior: per condition and candidate ``analysis.no_distortion_px``, the same figures
over every analysed pair, distorted and class-R together (the class of each estimate under that
threshold; ``called_r``: class-R pairs answered R), the threshold whose largest ECE over the
conditions is least chosen (``chosen_threshold``), and the self-check over every pair
(``check_all``).

    python benchmarks/bench_relief_test.py --n 400 --threads 1 --out docs/results/bench_relief_test.json
        [--set selfcal.parallax_px=0.2] [--undistorted [--thresholds 0.25 0.5 0.75 1.0]]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time

import torch

from lensdist_torch.config import LensdistConfig, apply_overrides, config_from_dict, parse_overrides, read_toml
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.data.shards import generate, load_set
from lensdist_torch.data.synthesis import draw_pairs
from lensdist_torch.geometry.distortion import CLASS_LABELS, REJECT
from lensdist_torch.workflows.confidence import expected_calibration_error
from lensdist_torch.workflows.decision_fit import confidences, outcomes, scored_pairs, validation_config
from lensdist_torch.workflows.evaluate import analyze_test_set
from lensdist_torch.workflows.reports import dumps_strict

CONDITIONS = {
    "default": None,
    "planar_realistic": "configs/realistic.toml",
    "relief_realistic": "configs/realistic_relief.toml",
}
PRIORS = (0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95, 1.0)
#: The analysis result's fields kept per pair (null where the result has none).
PER_PAIR = ("estimated_class", "estimated_delta_avg", "delta_avg_std", "planar_delta_avg", "planar_delta_avg_std",
            "relief_delta_avg", "relief_delta_avg_std", "relief_z", "relief_found", "raw_confidence", "confidence",
            "cannot_tell_reasons")


def validation_set(cfg: LensdistConfig, batch: int, limit: int | None) -> dict:
    """The validation split's test set (its first ``limit`` pairs; all if None), as ``lensdist reproduce`` makes it."""
    val = validation_config(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        generate(val, tmp, sets=["test"], batch_size=batch, limit=limit, progress=False)
        return load_set(tmp, "test")


def pairs_of(data: dict, keep: torch.Tensor) -> dict:
    """The loaded set restricted to the pairs ``keep`` (positions)."""
    n = data["index"].numel()
    return {k: (v[keep] if torch.is_tensor(v) and v.ndim and v.shape[0] == n else v) for k, v in data.items()}


def analysed(data: dict, cfg: LensdistConfig, batch: int) -> list[dict]:
    """Every pair of ``data`` as ``analyze`` (the self-calibration) answers it."""
    return analyze_test_set(data, {"selfcal": {"method": "selfcal"}}, None, config=cfg, batch_size=batch)["selfcal"]


def undistorted(results: list) -> dict:
    """The class-R pairs' answers (no lens, the protocol's perturbed registration): the share answered R (right),
    "cannot tell" by reason, and other classes."""
    reasons: dict = {}
    for r in results:
        for why in r.cannot_tell_reasons if r.cannot_tell else []:
            reasons[why] = reasons.get(why, 0) + 1
    m = max(1, len(results))
    called = [r.estimated_class for r in results if not r.cannot_tell]
    return {
        "pairs": len(results),
        "called_r": round(100 * called.count(CLASS_LABELS[REJECT]) / m, 2),
        "cannot_tell": round(100 * sum(bool(r.cannot_tell) for r in results) / m, 2),
        "cannot_tell_by_reason": reasons,
        "other_class": len(called) - called.count(CLASS_LABELS[REJECT]),
    }


def with_prior(cfg: LensdistConfig, prior: float) -> LensdistConfig:
    """``cfg`` with ``analysis.flat_prior`` = ``prior``."""
    return dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, flat_prior=prior))


def with_threshold(cfg: LensdistConfig, threshold: float) -> LensdistConfig:
    """``cfg`` with ``analysis.no_distortion_px`` = ``threshold``."""
    return dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, no_distortion_px=threshold))


def called_r(results: list, data: dict, cfg: LensdistConfig) -> int:
    """How many class-R pairs ``analyze``'s decision under ``cfg`` answers R (right, confident)."""
    keep = scored_pairs(results, cfg)
    conf, right = outcomes(results, data, config=cfg, method="selfcal", calibrated=True)
    is_r = (data["class_avg"][keep] == REJECT) if keep else torch.zeros(0, dtype=torch.bool)
    return int((is_r & right & (conf >= cfg.analysis.min_confidence)).sum())


def summary(results: list, data: dict, cfg: LensdistConfig) -> tuple[dict, set[int]]:
    """The figures of ``analyze``'s decision under ``cfg`` on one condition's pairs, and the pairs it cannot tell."""
    keep = scored_pairs(results, cfg)  # the other pairs are "cannot tell" whatever the prior
    conf, right = outcomes(results, data, config=cfg, method="selfcal", calibrated=True)
    sure = conf >= cfg.analysis.min_confidence
    cannot = set(range(len(results))) - {i for i, s in zip(keep, sure.tolist()) if s}
    n, r, wrong = len(results), int((right & sure).sum()), int((~right & sure).sum())
    return {
        "right_or_cannot_tell": round(100 * (r + len(cannot)) / n, 2),
        "cannot_tell": round(100 * len(cannot) / n, 2),
        "right_among_confident": round(100 * r / max(1, r + wrong), 2),
        "confident_wrong": wrong,
        "scored_pairs": len(keep),
        "ece": round(100 * expected_calibration_error(conf, right), 2),
    }, cannot


def self_check(results: list, cfg: LensdistConfig, cannot: set[int]) -> dict:
    """At the config's own prior: the largest difference between the recomputed and ``analyze``'s confidences
    (raw and calibrated, over the pairs with an estimate), and the pairs whose "cannot tell" differs."""
    keep = [i for i, r in enumerate(results) if r.estimated_delta_avg is not None]
    diff = 0.0
    for field, calibrated in (("raw_confidence", False), ("confidence", True)):
        mine = confidences(results, keep, config=cfg, method="selfcal", calibrated=calibrated)
        theirs = torch.tensor([getattr(results[i], field) for i in keep], dtype=torch.float64)
        diff = max([diff, *(mine - theirs).abs().tolist()])
    return {"flat_prior": cfg.analysis.flat_prior, "max_confidence_difference": diff,
            "cannot_tell_mismatches": sum((i in cannot) != bool(r.cannot_tell) for i, r in enumerate(results))}


def per_pair(results: list, data: dict) -> dict:
    """The pairs' truth (index, Delta_avg, class, the relief's largest height) and their analysis results."""
    params = draw_pairs(data["config"], "test", data["index"].tolist(), len(data["config"].protocol.scenes))
    height = params.realism.relief[:, 0].tolist() if params.realism is not None else [0.0] * len(results)
    return {"index": data["index"].tolist(), "true_delta_avg": data["delta_avg"].tolist(),
            "true_class": [CLASS_LABELS[c] for c in data["class_avg"].tolist()], "relief_height": height,
            **{k: [getattr(r, k) for r in results] for k in PER_PAIR}}


def condition_config(path: str | None, overrides: list[str]) -> LensdistConfig:
    """The condition's config with ``--set`` SECTION.FIELD=VALUE items applied (the config layer's own parsing and
    checks)."""
    try:
        return config_from_dict(apply_overrides(read_toml(path) if path else {}, parse_overrides(overrides)))
    except ValueError as exc:
        raise SystemExit(f"error: {exc}" if str(exc).startswith("--set") else f"error: --set: {exc}") from exc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=96, help="the first N distorted validation pairs per condition")
    ap.add_argument("--batch", type=int, default=8, help="pairs rendered and registered together")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="a setting changed in every condition's config (e.g. selfcal.parallax_px=0.2)")
    ap.add_argument("--undistorted", action="store_true",
                    help="also analyse each condition's class-R validation pairs (share answered R)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=None, metavar="PX",
                    help="candidate analysis.no_distortion_px, scored over every pair (needs --undistorted)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    if a.n < 1 or a.batch < 1 or a.threads < 1:
        ap.error("--n, --batch and --threads must be positive")
    if a.thresholds and (not a.undistorted or min(a.thresholds) <= 0):
        ap.error("--thresholds needs --undistorted and positive thresholds (px)")
    torch.set_num_threads(a.threads)
    out = {"priors": list(PRIORS), "settings": list(a.set), "conditions": {}}
    for name, path in CONDITIONS.items():
        cfg = condition_config(path, a.set)
        t0 = time.perf_counter()
        n_distorted = validation_config(cfg).protocol.n_test_distorted  # the test set holds its distorted pairs first
        every = validation_set(cfg, a.batch, None if a.undistorted else min(a.n, n_distorted))
        data = pairs_of(every, torch.arange(min(a.n, n_distorted)))
        results = analysed(data, cfg, a.batch)
        by_prior, cannot = {}, {}
        for w in PRIORS:
            by_prior[f"{w:g}"], cannot[w] = summary(results, data, with_prior(cfg, w))
        w0 = cfg.analysis.flat_prior  # the prior analyze ran with
        own = cannot[w0] if w0 in cannot else summary(results, data, cfg)[1]
        check = self_check(results, cfg, own)
        out["conditions"][name] = {"config": path, "seconds": round(time.perf_counter() - t0, 1), "pairs": len(results),
                                   "by_prior": by_prior, "check": check, "per_pair": per_pair(results, data)}
        print(name, dumps_strict(by_prior), "check", dumps_strict(check), flush=True)
        if a.undistorted:
            rest = pairs_of(every, torch.arange(n_distorted, every["index"].numel()))
            rest_results = analysed(rest, cfg, a.batch)
            out["conditions"][name]["undistorted"] = undistorted(rest_results)
            print(name, "class-R pairs", dumps_strict(out["conditions"][name]["undistorted"]), flush=True)
            if a.thresholds:  # every pair, distorted and class-R, under each R threshold at the config's prior
                both = pairs_of(every, torch.cat([torch.arange(min(a.n, n_distorted)),
                                                  torch.arange(n_distorted, every["index"].numel())]))
                everything = results + rest_results
                by_t = {}
                for t in a.thresholds:
                    got, _ = summary(everything, both, with_threshold(cfg, t))
                    by_t[f"{t:g}"] = got | {"called_r": called_r(everything, both, with_threshold(cfg, t))}
                out["conditions"][name]["by_threshold"] = by_t
                out["conditions"][name]["check_all"] = self_check(everything, cfg, summary(everything, both, cfg)[1])
                print(name, "by R threshold", dumps_strict(by_t), flush=True)
    worst = {f"{w:g}": max(c["by_prior"][f"{w:g}"]["ece"] for c in out["conditions"].values()) for w in PRIORS}
    out["largest_ece_by_prior"] = worst
    out["chosen_prior"] = float(min(worst, key=lambda k: (worst[k], -float(k))))
    print("largest ECE by prior", dumps_strict(worst), "chosen", out["chosen_prior"], flush=True)
    if a.thresholds:
        worst_t = {
            f"{t:g}": max(c["by_threshold"][f"{t:g}"]["ece"] for c in out["conditions"].values()) for t in a.thresholds
        }
        out["thresholds"], out["largest_ece_by_threshold"] = list(a.thresholds), worst_t
        out["chosen_threshold"] = float(min(worst_t, key=lambda k: (worst_t[k], float(k))))
        print("largest ECE by R threshold", dumps_strict(worst_t), "chosen", out["chosen_threshold"], flush=True)
    if a.out:
        atomic_write_text(a.out, dumps_strict(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
