"""The decision of analyze: the calibrated confidence (Platt map, ECE), the domain checks of the
learned methods (texture statistics, disagreement with the self-calibration), the fitted decision
written by fit_confidence."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from lensdist_torch.cli import main
from lensdist_torch.config import LensdistConfig, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.data.shards import load_scenes, read_manifest
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.selfcal import fit as selfcal_fit
from lensdist_torch.workflows import decision
from lensdist_torch.workflows.analyze import analyze_batch
from lensdist_torch.workflows.class_mass import flat_or_relief
from lensdist_torch.workflows.confidence import expected_calibration_error, fit_platt, platt, reliability
from lensdist_torch.workflows.decision import (
    SELFCAL_CONFIDENCE_SCALE,
    SELFCAL_CONFIDENCE_SHIFT,
    class_distance,
    decide,
    domain_checks,
)

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.usefixtures("one_thread_module")


# ------------------------------------------------------------------ confidence
def test_platt_identity_and_fit():
    c = torch.tensor([0.1, 0.5, 0.9])
    assert torch.allclose(platt(c, 1.0, 0.0), c.double())
    g = torch.Generator().manual_seed(0)
    raw = torch.rand(4000, generator=g, dtype=torch.float64).clamp(0.01, 0.99)
    truth = torch.sigmoid(0.5 * torch.log(raw / (1 - raw)) + 1.0)  # overconfident at the bottom, shifted
    right = torch.rand(4000, generator=g, dtype=torch.float64) < truth
    scale, shift = fit_platt(raw, right)
    assert scale == pytest.approx(0.5, abs=0.1) and shift == pytest.approx(1.0, abs=0.15)
    before = expected_calibration_error(raw, right)
    after = expected_calibration_error(platt(raw, scale, shift), right)
    assert after < 0.03 < before
    assert fit_platt(raw[:5], torch.ones(5, dtype=torch.bool)) == (1.0, 0.0)  # nothing to learn from


def test_reliability_by_hand():
    conf = torch.tensor([0.05, 0.15, 0.95, 0.95])
    right = torch.tensor([False, True, True, False])
    r = reliability(conf, right, n_bins=10)
    assert r["n"][0] == 1 and r["n"][1] == 1 and r["n"][9] == 2 and r["pairs"] == 4
    # |0 - 0.05| + |1 - 0.15| + 2 |0.5 - 0.95|, over 4 pairs
    assert r["ece"] == pytest.approx((0.05 + 0.85 + 2 * 0.45) / 4)
    assert math.isnan(r["accuracy"][5])


# ------------------------------------------------------------------ the answer
def _res(**kw):
    base = {"estimated_class": "3", "estimated_class_max": "3", "delta_avg": 9.0, "delta_max": 50.0, "confidence": None,
            "registration_ok": True, "overlap": 0.9}
    return {**base, **kw}


def test_decide_cannot_tell_rules():
    cfg = LensdistConfig()
    r = _res()
    decide(r, cfg)
    assert r["class"] == "3" and r["class_max"] == "3" and not r["cannot_tell"] and r["in_domain"]
    for change, warning in (({"confidence": 0.2}, "low confidence"), ({"overlap": 0.3}, "overlap"),
                            ({"registration_ok": False}, "registration failed"), ({"_diverged": True}, "diverged")):
        r = _res(**change)
        decide(r, cfg)
        assert r["class"] is None and r["cannot_tell"] and r["estimated_class"] == "3"
        assert any(warning in w for w in r["warnings"]), (change, r["warnings"])


def test_decide_names_each_reason_by_its_code():
    cfg = LensdistConfig()
    r = _res()
    decide(r, cfg)
    assert r["cannot_tell_reasons"] == []
    for change, codes in (({"confidence": 0.2}, ["low_confidence"]), ({"overlap": 0.3}, ["overlap"]),
                          ({"registration_ok": False}, ["registration"]), ({"_diverged": True}, ["no_estimate"]),
                          ({"motion_px": 0.1}, ["motion"]), ({"_far": True}, ["out_of_domain"]),
                          ({"motion_px": 0.1, "confidence": 0.2}, ["motion", "low_confidence"])):
        r = _res(**change)
        decide(r, cfg)
        assert r["cannot_tell"] and r["cannot_tell_reasons"] == codes, (change, r["cannot_tell_reasons"])


def test_relief_found_is_the_reason_and_both_answers_stay():
    """The planar and plane + parallax models answer different classes: "cannot tell", reason
    relief (not also low confidence), the planar and the relief estimates in the result and the warning."""
    cfg = LensdistConfig()
    r = _res(
        relief=True,
        relief_found=True,
        relief_z=5.0,
        relief_delta_avg=8.1,
        relief_delta_avg_interval=[7.5, 8.7],
        planar_delta_avg=9.0,
        confidence=0.3,
    )
    decide(r, cfg)
    assert r["cannot_tell"] and r["class"] is None and r["delta_avg"] is None
    assert r["cannot_tell_reasons"] == ["relief"]
    assert r["relief_delta_avg"] == 8.1 and r["planar_delta_avg"] == 9.0
    (w,) = r["warnings"]
    assert w.startswith("cannot tell: relief") and "whether the scene is flat" in w
    assert "planar model at 9.00 px" in w and "8.10 px [7.50, 8.70]" in w


def test_a_low_confidence_where_the_two_models_part_is_relief():
    """Not found by the rule (relief_mass 0), but the confidence is low and the two answers are
    in different classes: the reason is relief, with both answers; the same pair with the
    answers in one class is low confidence; a confident pair whose answers part is answered."""
    cfg = LensdistConfig()
    cfg = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, relief_mass=0.0, min_confidence=0.8))
    both = {
        "relief_delta_avg": 8.1,
        "relief_delta_avg_interval": [7.5, 8.7],
        "planar_delta_avg": 9.0,
        "relief_found": False,
    }
    r = _res(**both, relief_parted=True, confidence=0.7)
    decide(r, cfg)
    assert r["cannot_tell_reasons"] == ["relief"] and r["warnings"][0].startswith("cannot tell: relief")
    r = _res(**both, relief_parted=False, confidence=0.7)
    decide(r, cfg)
    assert r["cannot_tell_reasons"] == ["low_confidence"]
    r = _res(**both, relief_parted=True, confidence=0.85)
    decide(r, cfg)
    assert not r["cannot_tell"] and r["class"] == "3"


def test_flat_or_relief_weighs_both_models_class_masses():
    """The confidence of a class over both models: w x its folded-normal mass under the planar
    answer plus (1 - w) x under the plane + parallax one, against the normal CDF written out;
    relief found exactly where the two answers fall in different classes."""
    cfg = LensdistConfig()
    lo, hi = 3.592129565304105, 7.18425913060821  # class 2 at 320 x 424

    def mass(d, s):  # P(lo < |D| < hi), D ~ N(d, s^2)
        phi = lambda x: 0.5 * (1 + math.erf(x / math.sqrt(2)))  # noqa: E731
        return phi((hi - d) / s) - phi((lo - d) / s) + phi((-lo - d) / s) - phi((-hi - d) / s)

    for w in (0.0, 0.85, 1.0):
        c = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, flat_prior=w))
        conf, found = flat_or_relief("2", (6.9, 0.2), (7.0, 0.5), c)
        assert conf == pytest.approx(w * mass(6.9, 0.2) + (1 - w) * mass(7.0, 0.5), abs=1e-9) and not found
    assert flat_or_relief("2", (6.9, 0.2), (7.3, 0.5), cfg)[1]  # 7.3 px is class 3
    assert flat_or_relief("2", (6.9, 0.2), (7.3, 0.5), cfg)[0] < flat_or_relief("2", (6.9, 0.2), (7.0, 0.5), cfg)[0]
    with pytest.raises(ValueError, match="flat_prior"):
        dataclasses.replace(cfg.analysis, flat_prior=1.2)


def test_a_pair_of_a_scene_with_relief_says_relief():
    """Realistic test pair 9 with relief 2.7 % of the camera's height (truth 11.18 px): the planar
    model says 9.25 px, the plane + parallax model's interval holds the truth, and the answer is
    "cannot tell" for relief, with the default settings."""
    cfg = load_config(ROOT / "configs" / "realistic_relief.toml")  # the default analysis settings
    p = draw_pairs(cfg, "test", [9], len(cfg.protocol.scenes))
    img1, img2 = render_pairs([load_scene(s) for s in cfg.protocol.scenes], p, cfg)
    (r,) = analyze_batch(img1, img2, config=cfg)
    assert float(p.realism.relief[0, 0]) == pytest.approx(0.0274, abs=1e-4)
    assert r.cannot_tell and r.cannot_tell_reasons == ["relief"]
    lo, hi = r.relief_delta_avg_interval
    assert lo < 11.18 < hi and abs(r.planar_delta_avg - 11.18) > 1.5



def test_an_occluded_pair_is_registered_by_the_self_calibration():
    """Planar realistic validation pair 5 (truth 12.93 px, class 4): an occluder in I1 only fails
    the homography's residual test (RMS <= 0.5 sqrt 2 std(img1)). The self-calibration leaves the
    worst selfcal.fit.OCCLUDED_SHARE of the frame's rectangles out of the same test and registers it,
    with the right class; counting every rectangle (occluded_share 0) it is "cannot tell:
    registration", as with the homography alone."""
    from lensdist_torch.workflows.decision_fit import validation_config

    cfg = validation_config(load_config(ROOT / "configs" / "realistic.toml"))
    p = draw_pairs(cfg, "test", [5], len(cfg.protocol.scenes))
    img1, img2 = render_pairs([load_scene(s) for s in cfg.protocol.scenes], p, cfg)
    assert bool(p.realism.occluded[0]) and float(p.realism.relief[0, 0]) == 0.0
    (r,) = analyze_batch(img1, img2, config=cfg)
    assert r.registered_by == "self-calibration" and r.class_label == "4"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(selfcal_fit, "OCCLUDED_SHARE", 0.0)
        (s,) = analyze_batch(img1, img2, config=cfg)
    assert s.registered_by is None and s.cannot_tell_reasons == ["registration"]

def test_class_distance():
    assert class_distance("R", "1") == 1 and class_distance("R", "4") == 4 and class_distance("2", "2") == 0
    assert class_distance(None, "1") is None


def test_disagreement_with_the_selfcal_is_out_of_domain():
    cfg = LensdistConfig()
    sc = {"estimated_class": "R", "delta_avg": 0.1, "raw_confidence": 0.9}
    far = _res(estimated_class="3", delta_avg=9.0)
    domain_checks(far, sc, None, {"scenes": ["gravel", "grass"]}, cfg=cfg)
    decide(far, cfg)
    assert not far["selfcal_check"]["agrees"] and not far["in_domain"] and far["class"] is None
    assert any("self-calibration disagrees" in w for w in far["warnings"]) and far["fitted_on"] == ["gravel", "grass"]
    some = _res(estimated_class="1", delta_avg=1.5)  # distortion where the self-calibration sees none
    domain_checks(some, sc, None, {}, cfg=cfg)
    decide(some, cfg)
    assert not some["selfcal_check"]["agrees"] and some["class"] is None
    near = _res(estimated_class="1", delta_avg=1.5, confidence=0.8)  # one class apart, 1.3 px: agrees (a regression)
    domain_checks(near, {**sc, "estimated_class": "2", "delta_avg": 2.8}, None, {}, cfg=cfg)
    decide(near, cfg)
    assert near["selfcal_check"]["agrees"] and near["in_domain"] and near["class"] == "1"
    apart = _res(estimated_class="1", delta_avg=1.5)  # two classes apart
    domain_checks(apart, {**sc, "estimated_class": "3", "delta_avg": 5.0}, None, {}, cfg=cfg)
    assert not apart["selfcal_check"]["agrees"]
    rejected = _res(estimated_class="R", delta_avg=6.0)  # an eigen-space R keeps its nearest class's Delta
    domain_checks(rejected, sc, None, {}, cfg=cfg)
    assert rejected["selfcal_check"]["agrees"]
    unsure = _res(confidence=0.8)
    domain_checks(unsure, {**sc, "raw_confidence": 0.1}, None, {}, cfg=cfg)  # a selfcal that cannot tell says nothing
    decide(unsure, cfg)
    assert not unsure["selfcal_check"]["usable"] and unsure["in_domain"] and unsure["class"] == "3"


@pytest.mark.bad_input
def test_an_eigenspace_class_stands_only_where_the_selfcal_confirms_it():
    """The re-audit's case: the eigen-space (no confidence) answered an adjacent wrong class, which the
    cross-check tolerated (one class apart); on rendered pairs 30 of its 75 answers were wrong."""
    cfg = LensdistConfig()
    sc = {"estimated_class": "2", "delta_avg": 6.2, "raw_confidence": 0.99}
    adjacent = _res(estimated_class="3", delta_avg=8.3)  # confidence None: the eigen-space
    domain_checks(adjacent, sc, None, {}, cfg=cfg)
    decide(adjacent, cfg)
    assert adjacent["selfcal_check"]["agrees"] and not adjacent["selfcal_check"]["confirms"]
    assert adjacent["class"] is None and adjacent["cannot_tell"] and adjacent["delta_avg"] is None
    assert adjacent["estimated_class"] == "3" and adjacent["in_domain"]  # not out of domain: unconfirmed
    assert "the self-calibration finds class 2 (Delta_avg 6.20 px), not 3" in " ".join(adjacent["warnings"])
    same = _res(estimated_class="2", delta_avg=5.9)
    domain_checks(same, sc, None, {}, cfg=cfg)
    decide(same, cfg)
    assert same["selfcal_check"]["confirms"] and same["class"] == "2" and same["delta_avg"] == 5.9
    unsure = _res(estimated_class="2", delta_avg=5.9)  # a self-calibration that cannot tell confirms nothing
    domain_checks(unsure, {**sc, "raw_confidence": 0.3}, None, {}, cfg=cfg)
    decide(unsure, cfg)
    assert unsure["class"] is None and "the self-calibration cannot tell from this pair" in " ".join(unsure["warnings"])
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(decision, "EIGENSPACE_MAX_CLASS_DISAGREEMENT", 1)
        adjacent = _res(estimated_class="3", delta_avg=8.3)
        domain_checks(adjacent, sc, None, {}, cfg=cfg)
        decide(adjacent, cfg)
    assert adjacent["class"] == "3"  # the constant at 1: one class apart tolerated
    regression = _res(estimated_class="3", delta_avg=8.3, confidence=0.9)  # a confidence: the gate applies instead
    domain_checks(regression, sc, None, {}, cfg=cfg)
    decide(regression, cfg)
    assert "confirms" not in regression["selfcal_check"] and regression["class"] == "3"


def _unseen_pairs(cfg, n=2):
    """Pairs of gravel at a third of its contrast: a scene the shipped checkpoints never saw."""
    scene = 0.5 + 0.3 * (load_scene("gravel") - 0.5)
    return render_pairs([scene], draw_pairs(cfg, "test", list(range(n)), 1), cfg)


@pytest.mark.parametrize("method", ["regression", "eigenspace"])
def test_shipped_checkpoints_flag_an_unseen_texture(method):
    cfg = LensdistConfig()
    a, b = _unseen_pairs(cfg)
    for r in analyze_batch(a, b, method=method):
        assert r.fitted_on == ["gravel", "grass"]
        assert r.texture_distance > r.texture_limit and not r.in_domain
        assert r.class_label is None and r.cannot_tell and any("texture is unlike" in w for w in r.warnings)
    scenes, _ = load_scenes(cfg)  # the training scenes stay in domain
    a, b = render_pairs(scenes, draw_pairs(cfg, "test", [1, 2, 3], len(scenes)), cfg)
    for r in analyze_batch(a, b, method=method):
        assert r.texture_distance <= r.texture_limit


def test_cli_says_what_the_checkpoint_was_fitted_on(tmp_path, capsys):
    from kornia.io import write_image

    s = load_scene("gravel")[0, 0]
    for name, img in (("a.png", s[10:330, 20:444]), ("b.png", s[30:350, 22:446])):
        write_image(str(tmp_path / name), (img * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous())
    assert main(["analyze", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--method", "eigenspace"]) == 0
    assert "fitted on: gravel, grass" in capsys.readouterr().out


# ------------------------------------------------------------------ fit_confidence
def test_calibration_is_fitted_on_a_validation_split(tiny_run):
    out, _ = tiny_run
    cal = json.loads((out / "calibration.json").read_text())
    test_seed = read_manifest(out / "data")["config"]["protocol"]["seed"]
    val = read_manifest(out / "validation")
    assert val["config"]["protocol"]["seed"] == cal["validation_seed"] != test_seed
    assert set(val["sets"]) == {"test"}
    fitted = cal["analysis"]
    assert 0.02 <= fitted["no_distortion_px"] <= 2.0 and fitted["regression_confidence_scale"] > 0
    # the self-calibration's confidence is a probability already: no map is fitted for it
    assert "selfcal_confidence_scale" not in fitted and "selfcal_confidence_shift" not in fitted
    cfg = load_config(out / "calibration.toml")
    assert "selfcal_confidence" not in (out / "calibration.toml").read_text()  # a constant of the method now
    assert float(platt(0.7, SELFCAL_CONFIDENCE_SCALE, SELFCAL_CONFIDENCE_SHIFT)) == pytest.approx(0.7)  # the identity
    for key, value in fitted.items():
        assert getattr(cfg.analysis, key) == pytest.approx(value)
    assert cfg.image.size == (96, 128)
    rows = {(r["method"], r["split"]) for r in cal["ece"]}
    assert rows == {("selfcal", "validation"), ("regression", "validation")}
    pytest.importorskip("matplotlib")
    for name in ("reliability_validation.png", "reliability_test.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"


def _results(raws, deltas):
    return [
        {"in_domain": True, "estimated_delta_avg": d, "raw_confidence": c, "delta_avg_std": 0.3}
        for c, d in zip(raws, deltas)
    ]


def test_a_refit_that_raises_the_ece_is_not_kept():
    """Issue 19: on a --quick split the regression's refit fell back to the identity and raised the
    ECE from 2.8 % to 8.3 %: the config's map must stay then."""
    from lensdist_torch.workflows.decision_fit import fit_decision

    cfg = LensdistConfig()
    # every pair right (class 2 at 5 px): fit_platt has nothing to fit and answers the identity,
    # which maps raw 0.6 to 0.6, while the config's map (0.69, 1.0) maps it near 0.8: closer to 1
    raws = [0.6] * 20
    results = {"selfcal": _results(raws, [5.0] * 20), "regression": _results(raws, [5.0] * 20)}
    data = {"class_avg": torch.full((20,), 1), "delta_avg": torch.full((20,), 5.0, dtype=torch.float64)}
    fitted = fit_decision(results, data, cfg)
    assert (fitted["regression_confidence_scale"], fitted["regression_confidence_shift"]) == (
        cfg.analysis.regression_confidence_scale, cfg.analysis.regression_confidence_shift)
    # where the refit does lower the ECE it is kept: half right at raw 0.9 -> a map towards 0.5
    results["regression"] = _results([0.9] * 20, [5.0] * 10 + [9.0] * 10)
    fitted = fit_decision(results, data, cfg)
    from lensdist_torch.workflows.confidence import platt

    mapped = float(platt(torch.tensor([0.9], dtype=torch.float64), fitted["regression_confidence_scale"],
                         fitted["regression_confidence_shift"])[0])
    assert abs(mapped - 0.5) < abs(float(platt(torch.tensor([0.9], dtype=torch.float64),
                                               cfg.analysis.regression_confidence_scale,
                                               cfg.analysis.regression_confidence_shift)[0]) - 0.5)
