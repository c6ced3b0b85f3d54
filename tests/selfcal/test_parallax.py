"""The plane + parallax model of the self-calibration (``SelfCalConfig.parallax``, docs/method.md,
section 10): the relief's Jacobian, its basis, and what it does on pairs of a scene with and
without relief."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from selfcal_helpers import assert_columns_match_finite_differences, central_level, relief_only_pairs

from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.selfcal import fit as selfcal_fit
from lensdist_torch.selfcal import model as selfcal_model
from lensdist_torch.selfcal import prior as selfcal_prior
from lensdist_torch.selfcal.fit import SelfCalConfig, estimate_distortion

#: (config, selfcal.fit's constants patched for the fit): the default, the relief stage fitted where the planar
#: answer's score test asks for it and one step from the planar answer elsewhere,
RELIEF = (SelfCalConfig(parallax=5), {})
PLANAR = (SelfCalConfig(parallax=0), {})
EVERY = (SelfCalConfig(parallax=5), {"PARALLAX_SCORE_LEVEL": 1.0})  # the relief stage fitted on every pair


def _with(setting, constants=None, **fields):
    """``setting`` with ``fields`` of its config replaced and ``constants`` of selfcal.fit added."""
    config, known = setting
    return dataclasses.replace(config, **fields), {**known, **(constants or {})}


def test_relief_basis_is_gaussian_bumps_on_a_grid_over_the_frame():
    h, w = 60, 80
    r = half_diagonal(h, w)
    ux = torch.tensor([[-(w - 1) / (2 * r), 0.0, 0.1]])
    uy = torch.tensor([[-(h - 1) / (2 * r), 0.0, 0.2]])
    b = selfcal_model.relief_basis(ux, uy, n=3, width=0.3, h0=h, w0=w)
    assert b.shape == (1, 9, 3)
    assert float(b[0, 0, 0]) == pytest.approx(1.0)  # the first bump sits on the top-left corner
    assert float(b[0, 4, 1]) == pytest.approx(1.0)  # the middle one on the centre
    assert float(b[0, 4, 2]) == pytest.approx(float(torch.exp(torch.tensor(-(0.01 + 0.04) / 0.18))), rel=1e-6)


def test_relief_columns_of_the_jacobian_match_finite_differences():
    """The relief's columns d r / d c_k = (d r / d v . direction) phi_k against central
    differences of the residual, on a smooth pair (as test_selfcal's check of the others)."""
    lv, n = central_level("gain_bias", relief_n=3, direction=torch.tensor([[0.6, 0.8]]))
    theta = torch.zeros(1, 12 + 9, dtype=torch.float64)
    theta[0, :12] = torch.tensor([0.01, -0.005, 0.02, 0.004, -0.01, 0.03, 0.002, -0.001, 0.05, 0.02, 1.1, -0.05])
    theta[0, 12:] = 0.002 * torch.arange(9) - 0.008
    assert selfcal_model.evaluate(theta, lv)[2].shape == (1, 21, n)
    assert_columns_match_finite_differences(theta, lv, range(12, 21))


def _errors(i1, i2, true, setting):
    config, constants = setting
    with pytest.MonkeyPatch.context() as mp:
        for name, value in constants.items():
            mp.setattr(selfcal_fit, name, value)
        k2, k4, _, info = estimate_distortion(i1, i2, config=config)
    return (delta_avg(k2, k4, *i1.shape[-2:]) - true).abs(), info


@pytest.mark.usefixtures("one_thread_module")
def test_relief_model_removes_most_of_the_parallax_error():
    """Pairs of a scene with relief (up to 6 % of the camera's height, nothing else; the parallax
    follows each pair's motion): the planar model is pulled by it (first-order confounding), the
    plane + parallax model much less (12 pairs: RMSE 1.45 -> 0.60 px, the relief kept on 9, when
    written)."""
    i1, i2, true = relief_only_pairs(0.06, 12)
    planar, _ = _errors(i1, i2, true, PLANAR)
    relief, info = _errors(i1, i2, true, RELIEF)
    assert float(planar.pow(2).mean().sqrt()) > 1.0
    assert float(relief.pow(2).mean().sqrt()) < 0.65 * float(planar.pow(2).mean().sqrt())
    assert int(info.relief.sum()) >= 4


@pytest.mark.usefixtures("one_thread_module")
def test_relief_model_leaves_a_planar_scene_nearly_as_it_was():
    """Without relief, Hausman's test keeps the planar answer on most pairs, and where it does
    not, the relief model's answer is still close."""
    i1, i2, true = relief_only_pairs(0.0, 12)
    planar, _ = _errors(i1, i2, true, PLANAR)
    relief, info = _errors(i1, i2, true, EVERY)
    assert int(info.relief.sum()) <= 3
    assert float(planar.max()) < 0.6 and float(relief.max()) < float(planar.max()) + 0.3
    assert float(relief.pow(2).mean().sqrt()) < float(planar.pow(2).mean().sqrt()) + 0.1
    off = _with(EVERY, parallax=0)
    flat = _errors(i1, i2, true, off)[1]
    assert not bool(flat.relief.any())
    # both models' coefficients travel with the answer: ab is the kept one's, the planar ones are
    # the planar model's answers, and a planar model has no relief answers
    kept = info.relief[:, None]
    assert torch.equal(torch.where(kept, info.relief_ab, info.planar_ab), info.ab)
    assert torch.allclose(info.planar_ab, flat.ab, atol=1e-9) and torch.equal(flat.planar_ab, flat.ab)
    assert bool(flat.relief_ab.isnan().all()) and bool(torch.isfinite(info.relief_ab).all())
    # and so do both models' stds: the kept one's is delta_avg_std, the planar one the planar model's
    assert torch.equal(torch.where(info.relief, info.relief_std, info.planar_std), info.delta_avg_std)
    assert torch.allclose(info.planar_std, flat.delta_avg_std) and torch.equal(flat.planar_std, flat.delta_avg_std)
    assert bool(flat.relief_std.isnan().all()) and bool((info.relief_std > 0).all())


@pytest.mark.usefixtures("one_thread_module")
def test_the_prior_narrows_the_relief_and_its_interval():
    """A tighter fixed prior on the relief (parallax_px) holds the fit nearer the planar one: the std
    of Delta_avg falls from a free relief to a tight one, and so does, on average, how far
    Delta_avg moves from the planar answer (on pairs with relief the data still move it: with
    thousands of samples they outweigh any prior)."""
    i1, i2, true = relief_only_pairs(0.06, n=4)
    planar = _errors(i1, i2, true, PLANAR)[1].delta_avg
    # the posterior std (Gauss-Newton, fit.CLUSTERS = 0, without the motion floor); the cluster-robust one may widen
    # where a tight prior leaves a smooth misfit that the relief would have taken
    infos = [_errors(i1, i2, true, _with(RELIEF, {"PARALLAX_TEST": 0.0, "CLUSTERS": 0, "SMALL_MOTION_ERROR": 0.0},
                                         parallax_px=p, parallax_evidence=False))[1]
             for p in (100.0, 1.0, 0.01)]
    stds = [i.delta_avg_std for i in infos]
    moved = [float((i.delta_avg - planar).abs().mean()) for i in infos]
    # free -> default: equal within the residual scale s_w^2, which a tighter prior raises (0.2 %);
    # -> tight: 0.111, 0.088, 0.171, 0.279 px fall to 0.029, 0.049, 0.046, 0.056
    assert bool((stds[1] <= 1.005 * stds[0]).all()) and bool((stds[2] < 0.6 * stds[1]).all())
    assert moved[0] > moved[2]


@pytest.mark.usefixtures("one_thread_module")
def test_the_evidence_holds_a_flat_pair_to_its_plane_and_frees_a_relief():
    """The prior's std re-estimated per pair (``parallax_evidence``), against the fixed 0.2 px it
    starts from, on 6 pairs each: on flat pairs the relief answer moves less off the planar one
    (mean 0.091 -> 0.073 px when written), on pairs with relief (6 %) it is nearer the truth (RMSE
    0.42 -> 0.37 px; the planar model's 1.15)."""
    fixed, free = (_with(EVERY, {"PARALLAX_TEST": 0.0}, parallax_evidence=e) for e in (False, True))
    i1, i2, true = relief_only_pairs(0.0, n=6)
    planar = _errors(i1, i2, true, PLANAR)[1].delta_avg
    moved = [float((_errors(i1, i2, true, c)[1].delta_avg - planar).abs().mean()) for c in (fixed, free)]
    assert moved[1] < 0.9 * moved[0]
    i1, i2, true = relief_only_pairs(0.06, n=6)
    rmse = [float(_errors(i1, i2, true, c)[0].pow(2).mean().sqrt()) for c in (PLANAR, fixed, free)]
    assert rmse[2] < 0.95 * rmse[1] and rmse[2] < 0.4 * rmse[0]


@pytest.mark.usefixtures("one_thread_module")
def test_the_relief_stage_runs_where_the_planar_answers_score_asks_for_it():
    """Rao's score test of the relief at the planar answer (``fit.PARALLAX_SCORE_LEVEL``): on flat pairs
    the statistic is chi-square with 25 degrees of freedom and the stage is not fitted: the plane +
    parallax answer is one Gauss-Newton step from the planar one (``prior.relief_step``), whose std
    is the fitted stage's within a factor of two (0.68-1.36 when written) and beside which Hausman's
    test keeps the planar answer; on pairs with relief (6 %) the stage is fitted. Level 1: fitted on
    every pair."""
    i1, i2, true = relief_only_pairs(0.0, 12)
    flat, planar, every = (_errors(i1, i2, true, c)[1] for c in (RELIEF, PLANAR, EVERY))
    skipped = selfcal_prior.relief_p_value(flat.relief_score, RELIEF[0]) > selfcal_fit.PARALLAX_SCORE_LEVEL
    assert int(skipped.sum()) >= 10 and 12 < float(flat.relief_score.median()) < 40
    assert torch.equal(flat.planar_ab, every.planar_ab) and torch.equal(flat.planar_std, every.planar_std)
    assert torch.equal(every.relief_score, flat.relief_score) and bool(planar.relief_score.isnan().all())
    one, fitted = flat.relief_std[skipped], every.relief_std[skipped]
    assert bool(torch.isfinite(flat.relief_ab[skipped]).all()) and bool(((one / fitted - 1).abs() < 1.0).all())
    assert bool((one > flat.planar_std[skipped]).all())  # the relief's freedom widens the answer
    assert bool(torch.isfinite(flat.relief_z[skipped]).all()) and not bool(flat.relief[skipped].any())
    assert torch.equal(flat.delta_avg[skipped], planar.delta_avg[skipped])  # Hausman keeps the planar answer
    i1, i2, true = relief_only_pairs(0.06, 12)
    info = _errors(i1, i2, true, RELIEF)[1]
    assert int(torch.isfinite(info.relief_ab).all(1).sum()) >= 10 and float(info.relief_score.median()) > 100
    i1, i2, true = relief_only_pairs(0.0, 2)  # a fixed prior: fitted on every pair, whatever its score
    fixed, fitted = (_errors(i1, i2, true, _with(c, parallax_evidence=False))[1] for c in (RELIEF, EVERY))
    assert torch.equal(fixed.relief_ab, fitted.relief_ab) and torch.equal(fixed.relief_std, fitted.relief_std)


@pytest.mark.bad_input
@pytest.mark.parametrize("field,value", [("parallax", -1), ("parallax", 2.5), ("parallax_px", 0.0),
                                         ("parallax_evidence", "yes")])
def test_relief_settings_are_checked(field, value):
    with pytest.raises(ValueError, match=field) as err:
        SelfCalConfig(**{field: value})
    assert "\n" not in str(err.value)


def _log_evidence(X, y, sigma2, tau2):
    """log N(y; 0, sigma^2 I + tau^2 X X^T), the marginal likelihood of y = X c + e, c ~ N(0, tau^2 I)."""
    cov = sigma2 * torch.eye(len(y), dtype=torch.float64) + tau2 * X @ X.T
    return float(torch.distributions.MultivariateNormal(torch.zeros(len(y), dtype=torch.float64), cov).log_prob(y))


@pytest.mark.parametrize("scale", [0.05, 0.3, 1.0])
def test_evidence_variance_fixed_point_maximises_the_marginal_likelihood(scale):
    """MacKay's update iterated on a linear Gaussian model (posterior mode and covariance in closed
    form) settles where the marginal likelihood, evaluated directly over a fine grid, peaks."""
    g = torch.Generator().manual_seed(int(scale * 100))
    n, k, sigma2 = 60, 9, 0.04
    X = torch.randn(n, k, generator=g, dtype=torch.float64)
    y = X @ (scale * torch.randn(k, generator=g, dtype=torch.float64)) + sigma2**0.5 * torch.randn(
        n, generator=g, dtype=torch.float64
    )
    tau2 = torch.tensor([1.0], dtype=torch.float64)
    for _ in range(500):
        cov = sigma2 * torch.linalg.inv(X.T @ X + sigma2 / tau2 * torch.eye(k, dtype=torch.float64))
        c = cov @ X.T @ y / sigma2
        tau2 = selfcal_prior.evidence_variance(c[None], cov.trace()[None], tau2)
    grid = torch.logspace(-5, 1, 2401, dtype=torch.float64)
    best = grid[int(torch.tensor([_log_evidence(X, y, sigma2, float(t)) for t in grid]).argmax())]
    assert float(tau2) == pytest.approx(float(best), rel=0.02)
    assert 0.2 * scale**2 < float(tau2) < 5 * scale**2  # and near the variance the coefficients were drawn with
