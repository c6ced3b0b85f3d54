"""The decision fitted on a validation split (workflows/decision_fit.py): the std scales of the
self-calibration's confidence and intervals, the pairs they are scored on, and a result's
confidence recomputed under another config as analyze computes it."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.shards import load_scenes
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.distortion import estimated_class
from lensdist_torch.workflows.analyze import analyze_pair
from lensdist_torch.workflows.class_mass import (
    flat_or_relief,
    relief_agreement,
    rescored_confidence,
    rescored_relief_found,
)
from lensdist_torch.workflows.decision_fit import fit_decision, interval_coverage, scored_pairs

pytestmark = pytest.mark.usefixtures("one_thread_module")


def _with(cfg, **analysis):
    return dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, **analysis))


def _cfg(**analysis) -> LensdistConfig:
    return _with(LensdistConfig(), **analysis)


# ------------------------------------------------------------------ the std scale in the confidence
@pytest.mark.parametrize("k", [0.5, 1.0, 2.5])
def test_std_scale_is_the_stds_multiplied(k):
    """flat_or_relief under selfcal_std_scale k equals it at 1 with every std multiplied by k."""
    for label, planar, relief in (
        ("2", (7.0, 0.2), (7.4, 0.5)),
        ("R", (0.3, 0.2), (0.9, 0.4)),
        ("3", (9.0, 1.0), (float("nan"), float("inf"))),
    ):
        scaled = flat_or_relief(label, planar, relief, _cfg(selfcal_std_scale=k))
        by_hand = flat_or_relief(label, (planar[0], k * planar[1]), (relief[0], k * relief[1]), _cfg())
        assert scaled[0] == pytest.approx(by_hand[0], abs=1e-12) and scaled[1] == by_hand[1]


def test_a_wider_std_lowers_the_confidence_of_an_estimate_near_a_boundary():
    # class 2 ends at 7.18 px: 7.0 +- 0.2 is Phi(0.92) = 0.82, +- 0.4 is Phi(0.46) = 0.68
    assert flat_or_relief("2", (7.0, 0.2), (float("nan"), float("inf")), _cfg())[0] == pytest.approx(0.8215, abs=2e-3)
    assert flat_or_relief("2", (7.0, 0.2), (float("nan"), float("inf")), _cfg(selfcal_std_scale=2.0))[
        0
    ] == pytest.approx(0.677, abs=3e-3)


@pytest.fixture(scope="module")
def analysed():
    """Test pair 7 of the protocol (answered: class 2; pair 5 until the relief prior became 0.2 px, now
    "cannot tell: relief"): the two images and the config, at 160 x 216 (a flat pair: both answers to
    rescore, the plane + parallax one a step from the planar one)."""
    cfg = LensdistConfig()
    cfg = dataclasses.replace(cfg, image=dataclasses.replace(cfg.image, height=160, width=216))
    scenes, _ = load_scenes(cfg)
    img1, img2 = render_pairs(scenes, draw_pairs(cfg, "test", [7], len(scenes)), cfg)
    return img1, img2, cfg


@pytest.mark.parametrize("k, w, q", [(1.0, 0.8, 1.0), (1.7, 0.3, 0.2)])
def test_rescored_confidence_is_what_analyze_says(analysed, k, w, q):
    """The raw confidence and the relief flag recomputed from a result's kept answers are analyze's own, under the
    same config."""
    img1, img2, base = analysed
    cfg = _with(base, selfcal_std_scale=k, flat_prior=w, relief_mass=q)
    res = analyze_pair(img1, img2, method="selfcal", config=cfg)
    assert res.estimated_delta_avg is not None and res.relief_delta_avg is not None
    assert rescored_confidence(res, cfg) == pytest.approx(res.raw_confidence, abs=1e-9)
    assert rescored_relief_found(res, cfg) == res.relief_found
    assert res.relief_agreement == pytest.approx(
        relief_agreement(res.planar_delta_avg, (res.relief_delta_avg, res.relief_delta_avg_std), cfg)
    )
    assert rescored_confidence({"estimated_delta_avg": None}, cfg) != rescored_confidence(
        {"estimated_delta_avg": None}, cfg
    )  # NaN


def test_interval_scale_widens_the_answers_interval(analysed):
    img1, img2, cfg = analysed
    one = analyze_pair(img1, img2, method="selfcal", config=cfg)
    two = analyze_pair(img1, img2, method="selfcal", config=_with(cfg, interval_std_scale=2.0))
    assert one.delta_avg_interval is not None
    assert two.delta_avg_std == pytest.approx(one.delta_avg_std)  # the fit's own std is reported as it is
    for key in ("delta_avg_interval", "planar_delta_avg_interval", "relief_delta_avg_interval"):
        mine, wider = getattr(one, key), getattr(two, key)
        if mine is None:
            continue
        mid = one.estimated_delta_avg if key == "delta_avg_interval" else getattr(one, key.replace("_interval", ""))
        if mine[0] > 0 and wider[0] > 0:  # not clipped at 0
            assert wider[1] - mid == pytest.approx(2 * (mine[1] - mid), rel=1e-9)


# ------------------------------------------------------------------ fitted on a validation split
def _validation(n: int, inflate: float, seed: int = 0):
    """n pairs whose estimates scatter ``inflate`` times their stated std about the truth."""
    g = torch.Generator().manual_seed(seed)
    cfg = LensdistConfig()
    true = torch.rand(n, generator=g, dtype=torch.float64) * 13.0 + 0.5
    std = 0.15 + 0.35 * torch.rand(n, generator=g, dtype=torch.float64)
    est = (true + inflate * std * torch.randn(n, generator=g, dtype=torch.float64)).abs()
    results = [{"in_domain": True, "estimated_delta_avg": float(e), "delta_avg_std": float(s), "motion_px": 10.0,
                "relief_found": False, "raw_confidence": 0.5} for e, s in zip(est, std)]
    data = {"class_avg": estimated_class(true, true, metric="delta_avg", config=cfg), "delta_avg": true}
    return results, data, cfg


@pytest.mark.parametrize("inflate", [1.0, 2.0])
def test_fitted_scales_recover_how_far_the_estimates_scatter(inflate):
    """Estimates scattering k times their std: both scales fitted near k (the grid steps by 9 %)."""
    results, data, cfg = _validation(1500, inflate)
    fitted = fit_decision({"selfcal": results}, data, cfg)
    assert fitted["selfcal_std_scale"] == pytest.approx(inflate, rel=0.25)
    assert fitted["interval_std_scale"] == pytest.approx(inflate, rel=0.15)
    cov = interval_coverage(results, data, _with(cfg, interval_std_scale=fitted["interval_std_scale"]))
    assert cov["pairs"] == 1500 and 0.95 <= cov["coverage"] <= 0.97


def test_a_plateau_of_r_thresholds_is_decided_by_the_confidence_not_the_shipped_value():
    """Undistorted pairs estimated at 0.02-0.2 px, distorted ones at 1.0 px and more: every threshold
    between them is as right. Before, the one nearest the config's value won (0.233 px from 0.25,
    0.632 from 0.75 on the default protocol's validation split); now the confidence decides."""
    results, data, cfg = _validation(400, 1.5, seed=3)
    g = torch.Generator().manual_seed(4)
    for r in results[:80]:  # class R: true 0, estimates a little above it
        r["estimated_delta_avg"] = float(0.02 + 0.18 * torch.rand(1, generator=g, dtype=torch.float64))
    data["delta_avg"][:80] = 0.0
    data["class_avg"] = estimated_class(data["delta_avg"], data["delta_avg"], metric="delta_avg", config=cfg)
    for r in results[80:]:
        r["estimated_delta_avg"] = max(r["estimated_delta_avg"], 1.0)
    fits = [
        fit_decision({"selfcal": results}, data, _cfg(no_distortion_px=t))["no_distortion_px"] for t in (0.25, 0.5, 0.9)
    ]
    assert fits[0] == fits[1] == fits[2] and 0.2 < fits[0] <= 1.0


def test_scales_stay_where_there_is_nothing_to_score():
    results, data, cfg = _validation(50, 1.0)
    data["class_avg"] = estimated_class(
        torch.tensor([r["estimated_delta_avg"] for r in results]),
        torch.tensor([r["estimated_delta_avg"] for r in results]),
        metric="delta_avg",
        config=cfg,
    )
    fitted = fit_decision({"selfcal": results}, data, _cfg(selfcal_std_scale=1.3))
    assert fitted["selfcal_std_scale"] == 1.3  # every class right: the sharpest scale would always win


def test_pairs_withheld_for_another_reason_are_not_scored():
    results, data, cfg = _validation(6, 1.0)
    results[1]["relief_found"] = True
    results[2]["motion_px"] = 0.5
    results[3]["in_domain"] = False
    results[4]["estimated_delta_avg"] = None
    assert scored_pairs(results, cfg) == [0, 5]


def test_reproduce_reports_the_fitted_scales_and_the_coverage(tiny_run):
    out, _ = tiny_run
    cal = json.loads((out / "calibration.json").read_text())
    assert {"selfcal_std_scale", "interval_std_scale", "flat_prior", "min_confidence"} <= set(cal["analysis"])
    chosen = [c for c in cal["withholding"] if c["min_confidence"] == cal["analysis"]["min_confidence"]]
    assert len(cal["withholding"]) == 5 and len(chosen) == 1  # every candidate, the chosen one among them
    assert chosen[0]["selfcal_std_scale"] == cal["analysis"]["selfcal_std_scale"]
    assert all(0.5 - 1e-9 <= cal["analysis"][k] <= 4 + 1e-9 for k in ("selfcal_std_scale", "interval_std_scale"))
    (row,) = cal["intervals"]
    assert row["split"] == "validation" and row["nominal"] == 0.95 and 0 <= row["after"] <= 1
    report = json.loads((out / "reproduce.json").read_text())
    assert [r["split"] for r in report["calibration"]["intervals"]] == ["validation", "test"]
    assert "coverage after" in (out / "reproduce.md").read_text()
