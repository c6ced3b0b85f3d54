"""Relief named by evidence (workflows/class_mass.py, decision_fit.py): the plane + parallax
answer's probability of the planar class, the rule ``analysis.relief_mass`` puts on it, and the
prior and the rule fitted on a validation split, against hand-worked values and synthetic
splits whose answer is known."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import CLASS_LABELS, class_bounds, estimated_class
from lensdist_torch.workflows import decision_fit
from lensdist_torch.workflows.class_mass import flat_or_relief, relief_agreement, rescored_relief_found
from lensdist_torch.workflows.confidence import precision_bound
from lensdist_torch.workflows.decision_fit import TARGET_PRECISION, answers, fit_decision


def _cfg(**analysis) -> LensdistConfig:
    cfg = LensdistConfig()
    return dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, **analysis))


def _phi(x: float) -> float:
    return 0.5 * (1 + math.erf(x / math.sqrt(2)))


def _label(d: float, cfg: LensdistConfig) -> str:
    t = torch.tensor([d], dtype=torch.float64)
    return CLASS_LABELS[int(estimated_class(t, t, metric="delta_avg", config=cfg)[0])]


# ------------------------------------------------------------------ the statistic and the rule
@pytest.mark.parametrize(
    "planar, relief", [(7.0, (7.6, 0.4)), (5.0, (5.3, 0.4)), (0.1, (0.4, 0.3)), (10.0, (3.0, 2.0))]
)
def test_relief_agreement_is_the_folded_normal_mass_of_the_planar_class(planar, relief):
    """P(|D| in the planar answer's class) for D ~ N(relief): the two tails of the fold by hand."""
    cfg = _cfg(selfcal_std_scale=1.3)
    lo, hi = class_bounds(_label(planar, cfg), "delta_avg", cfg)
    d, s = relief[0], 1.3 * relief[1]
    by_hand = (_phi((hi - d) / s) - _phi((lo - d) / s)) + (_phi((-lo - d) / s) - _phi((-hi - d) / s))
    assert relief_agreement(planar, relief, cfg) == pytest.approx(by_hand, abs=1e-9)
    assert math.isnan(relief_agreement(planar, (float("nan"), 0.3), cfg))


def test_relief_mass_one_is_the_classes_differ_rule_and_zero_never():
    g = torch.Generator().manual_seed(3)
    for _ in range(300):
        d0, d1 = (torch.rand(2, generator=g, dtype=torch.float64) * 14).tolist()
        s0, s1 = (0.05 + torch.rand(2, generator=g, dtype=torch.float64) * 2).tolist()
        parted = _label(d0, _cfg()) != _label(d1, _cfg())
        agreement = relief_agreement(d0, (d1, s1), _cfg())
        assert flat_or_relief(_label(d0, _cfg()), (d0, s0), (d1, s1), _cfg())[1] == parted  # the default, 1
        assert not flat_or_relief(_label(d0, _cfg()), (d0, s0), (d1, s1), _cfg(relief_mass=0.0))[1]
        assert flat_or_relief(_label(d0, _cfg()), (d0, s0), (d1, s1), _cfg(relief_mass=0.2))[1] == (
            parted and agreement < 0.2
        )
        if parted:  # the other class holds the plane + parallax answer's centre: mostly under half
            assert agreement < 0.75


def test_the_rule_does_not_change_the_confidence():
    for q in (0.0, 0.3, 1.0):
        conf = flat_or_relief("2", (7.0, 0.2), (7.6, 0.4), _cfg(relief_mass=q, flat_prior=0.8))[0]
        # 0.8 * Phi((7.18 - 7.0) / 0.2) + 0.2 * Phi((7.18 - 7.6) / 0.4), the lower bound 3.59 px far below both
        hi = class_bounds("2", "delta_avg", _cfg())[1]
        assert conf == pytest.approx(0.8 * _phi((hi - 7.0) / 0.2) + 0.2 * _phi((hi - 7.6) / 0.4), abs=1e-6)


def test_rescored_relief_keeps_the_stored_flag_without_two_answers():
    r = {"estimated_delta_avg": 5.0, "delta_avg_std": 0.2, "relief_found": True}
    assert rescored_relief_found(r, _cfg(relief_mass=0.0))  # nothing to recompute it from
    both = r | {
        "planar_delta_avg": 7.0,
        "planar_delta_avg_std": 0.2,
        "relief_delta_avg": 7.6,
        "relief_delta_avg_std": 0.4,
    }
    assert rescored_relief_found(both, _cfg()) and not rescored_relief_found(both, _cfg(relief_mass=0.1))


# ------------------------------------------------------------------ what a split can promise
def test_precision_bound_by_hand_and_its_coverage():
    """Wilson's lower end: n / (n + z^2) where every answer is right; below the true share in
    about 97.5 % of binomial draws (the lower end of a two-sided 95 % interval)."""
    z = 1.959964
    assert precision_bound(400, 400) == pytest.approx(400 / (400 + z * z), abs=1e-6)
    assert math.isnan(precision_bound(0, 0))
    g = torch.Generator().manual_seed(5)
    p, n = 0.97, 450
    draws = (torch.rand(4000, n, generator=g, dtype=torch.float64) < p).sum(1).tolist()
    below = sum(precision_bound(int(k), n) <= p for k in draws) / len(draws)
    assert 0.96 <= below <= 0.99


# ------------------------------------------------------------------ fitted on a validation split
def _split(n: int, planar_bias: float, planar_noise: float, relief_noise: float, seed: int = 0):
    """n pairs with both answers: the planar one biased by +-planar_bias, scattered and stated
    planar_noise, the plane + parallax one unbiased, scattered and stated relief_noise."""
    g = torch.Generator().manual_seed(seed)
    cfg = LensdistConfig()
    true = torch.rand(n, generator=g, dtype=torch.float64) * 13.0 + 0.5
    sign = torch.where(torch.rand(n, generator=g) < 0.5, -1.0, 1.0).double()
    planar = (true + sign * planar_bias + planar_noise * torch.randn(n, generator=g, dtype=torch.float64)).abs()
    relief = (true + relief_noise * torch.randn(n, generator=g, dtype=torch.float64)).abs()
    results = [{"in_domain": True, "estimated_delta_avg": float(p), "delta_avg_std": planar_noise, "motion_px": 10.0,
                "planar_delta_avg": float(p), "planar_delta_avg_std": planar_noise,
                "relief_delta_avg": float(r), "relief_delta_avg_std": relief_noise, "relief_found": False}
               for p, r in zip(planar, relief)]
    return results, {"class_avg": estimated_class(true, true, metric="delta_avg", config=cfg), "delta_avg": true}, cfg


def _fitted(results, data, cfg):
    fitted = fit_decision({"selfcal": results}, data, cfg)
    return fitted, _cfg(**fitted)


def test_a_flat_split_answers_at_the_least_confidence_and_trusts_the_plane():
    """Planar answers right to their std (0.05 px), the relief answers 8x noisier: the prior leans
    on the plane, the least confidence stays 0.5, and the rule that names relief is not fitted."""
    results, data, cfg = _split(600, 0.0, 0.05, 0.4)
    fitted, after = _fitted(results, data, cfg)
    assert "relief_mass" not in fitted and fitted["min_confidence"] == 0.5
    assert fitted["flat_prior"] >= 0.8
    got, never = answers(results, data, after), answers(results, data, _with_mass(after, 0.0))
    assert got["precision_bound"] >= TARGET_PRECISION
    # a user who knows the scene is flat (relief_mass 0) gets more answers, as right
    assert never["answered"] > got["answered"] and never["precision_bound"] >= TARGET_PRECISION


def _with_mass(cfg: LensdistConfig, q: float, **more) -> LensdistConfig:
    return dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, relief_mass=q, **more))


def test_a_split_with_relief_trusts_the_relief_model_and_withholds_what_it_must():
    """Planar answers biased by 0.4 px (8 times their std), the plane + parallax ones right: the
    prior leans on the relief model, and a higher least confidence brings the answers' share right
    up, within the "cannot tell" limit."""
    results, data, cfg = _split(1200, 0.4, 0.05, 0.3)
    fitted, after = _fitted(results, data, cfg)
    assert fitted["flat_prior"] <= 0.5 and fitted["min_confidence"] > 0.5
    got, every = answers(results, data, after), answers(results, data, _with_mass(after, 1.0, min_confidence=0.5))
    assert got["precision_bound"] > every["precision_bound"] and got["answered"] < every["answered"]
    assert got["cannot_tell"] <= decision_fit.MAX_CANNOT_TELL


def test_the_fitted_decision_stays_within_the_cannot_tell_limit(monkeypatch):
    """The split above withholds at some "cannot tell" cost; a tighter limit fits a decision within it."""
    results, data, _ = _split(1200, 0.4, 0.05, 0.3)
    free, after = _fitted(results, data, _cfg())
    cost = answers(results, data, after)["cannot_tell"]
    limit = cost - 0.004  # five pairs fewer
    monkeypatch.setattr(decision_fit, "MAX_CANNOT_TELL", limit)
    fitted, tight = _fitted(results, data, _cfg())
    assert answers(results, data, tight)["cannot_tell"] <= limit
    assert fitted["min_confidence"] < free["min_confidence"]
    monkeypatch.setattr(decision_fit, "MAX_CANNOT_TELL", 0.0)
    none_within = fit_decision({"selfcal": results}, data, _cfg())  # none: the config's
    assert none_within["min_confidence"] == 0.5
