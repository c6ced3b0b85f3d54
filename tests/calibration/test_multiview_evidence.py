"""The multi-view path's lens models weighed by held-out frames (lensdist_torch.calibration.multiview_evidence):
the mixture interval against sampling, the weights' properties, the held-out density by hand."""

import math
from statistics import NormalDist

import numpy as np
import pytest

from lensdist_torch.calibration.multiview_evidence import (
    CAP,
    evidence_weights,
    mixture_interval,
    posterior_std,
    unit_log_evidence,
)


@pytest.mark.parametrize("means, stds, weights", [
    ([7.36, 6.70, 6.68], [0.3, 0.4, 0.5], [0.6, 0.3, 0.1]),
    ([4.9, 11.3], [0.1, 0.3], [0.5, 0.5]),
    ([15.0], [2.0], [1.0]),
])
def test_the_mixture_interval_is_the_central_interval_of_samples_from_the_mixture(means, stds, weights):
    rng = np.random.default_rng(0)
    pick = rng.choice(len(means), size=400_000, p=np.asarray(weights) / sum(weights))
    draws = rng.normal(np.asarray(means)[pick], np.asarray(stds)[pick])
    lo, hi = mixture_interval(means, stds, weights, 0.95)
    assert lo == pytest.approx(np.quantile(draws, 0.025), abs=0.02)
    assert hi == pytest.approx(np.quantile(draws, 0.975), abs=0.02)


def test_an_undetermined_model_spreads_its_weight_over_the_whole_line():
    # weight 0.04 anywhere: 0.02 below every value, so the 2.5 % tail is 0.005 of the other's 0.96
    z = NormalDist().inv_cdf(0.005 / 0.96)  # -2.561
    lo, hi = mixture_interval([10.0, 3.0], [1.0, math.inf], [0.96, 0.04], 0.95)
    assert lo == pytest.approx(10.0 + z, abs=1e-6) and hi == pytest.approx(10.0 - z, abs=1e-6)
    assert mixture_interval([10.0, 3.0], [1.0, math.inf], [0.9, 0.1], 0.95) == (-math.inf, math.inf)


def test_weights_are_a_distribution_that_follows_the_models_and_repeats_with_the_seed():
    rng = np.random.default_rng(1)
    e = rng.normal(0.0, 3.0, (3, 20))
    w = evidence_weights(e, 500, seed=4)
    assert w.sum() == pytest.approx(1.0) and (w >= 0).all()
    assert np.array_equal(w, evidence_weights(e, 500, seed=4))  # seeded: the same weights
    assert np.allclose(evidence_weights(e[::-1], 500, seed=4), w[::-1])  # the models' order does not matter
    assert np.allclose(evidence_weights(e + 7.0, 500, seed=4), w)  # nor a constant common to all models
    # a model ahead on every frame by far takes the weight; two models ahead on half the frames each share it
    assert evidence_weights(np.array([[0.0] * 10, [-30.0] * 10]))[0] == pytest.approx(1.0)
    split = evidence_weights(np.array([[5.0, -5.0] * 10, [-5.0, 5.0] * 10]))
    assert 0.3 < split[0] < 0.7
    assert evidence_weights(np.zeros((4, 0))).tolist() == [0.25] * 4  # no held-out frame: no preference


def test_held_out_density_by_hand_with_a_capped_outlier():
    # fold of one frame, 3 observations; errors^2 model A (1, 1, 1000), model B (2, 2, 2): median 2, cap 32;
    # the fold's s^2 = mean(1, 1, 32, 2, 2, 2) / 2 = 40 / 12
    e = unit_log_evidence([[[np.array([1.0, 1.0, 1000.0])]], [[np.array([2.0, 2.0, 2.0])]]])
    s2 = 40 / 12
    a = 3 * -math.log(2 * math.pi * s2) - (1 + 1 + CAP * 2) / (2 * s2)
    b = 3 * -math.log(2 * math.pi * s2) - 6 / (2 * s2)
    assert e.shape == (2, 1) and e[0, 0] == pytest.approx(a) and e[1, 0] == pytest.approx(b)
    with pytest.raises(ValueError, match=r"^errors must hold the same observations for every model in fold 0"):
        unit_log_evidence([[[np.ones(3)]], [[np.ones(4)]]])


def test_posterior_std_of_a_nonlinear_figure_against_its_exact_gradient():
    # f(a, b) = a^2 b over a covariance with correlation: std = sqrt(g C g), g = (2ab, a^2); b held fixed or not
    cov = np.array([[0.04, 0.01], [0.01, 0.09]])
    a, b = 3.0, 2.0
    g = np.array([2 * a * b, a * a])
    (std,) = posterior_std([a, b, 99.0], [0, 1], cov, lambda p: (p[0] ** 2 * p[1],))
    assert std == pytest.approx(math.sqrt(g @ cov @ g), rel=1e-6)
    assert posterior_std([a, b], [0, 1], None, lambda p: (p[0], p[1])) == [math.inf, math.inf]


def test_a_model_that_did_not_converge_takes_no_weight_even_with_a_known_delta():
    # a camera without distortion has Delta 0 with std 0 whatever its focal length; stopped at no minimum, its
    # held-out frames (here predicted better) are no evidence: the converged model answers alone
    from lensdist_torch.calibration.multiview_evidence import weigh_models

    pinhole = {"delta_avg_px": 0.0, "delta_avg_std_px": 0.0, "delta_max_px": 0.0, "delta_max_std_px": 0.0,
               "jackknife_std_px": 0.0, "converged": False}
    radial = {"delta_avg_px": 8.0, "delta_avg_std_px": 0.5, "delta_max_px": 20.0, "delta_max_std_px": 1.0,
              "jackknife_std_px": 0.5, "converged": True}
    errors = [[[np.full(50, 0.5)] for _ in range(3)], [[np.full(50, 1.0)] for _ in range(3)]]
    out = weigh_models([pinhole, radial], errors, checked=[True, True], confidence=0.95)
    assert out["carried"].tolist() == [False, True] and out["weights"].tolist() == [0.0, 1.0]
    lo, hi = out["intervals"][0]
    assert lo == pytest.approx(8.0 - 1.959964 * 0.5, abs=1e-4) and hi == pytest.approx(8.0 + 1.959964 * 0.5, abs=1e-4)
    both = weigh_models([{**pinhole, "converged": True}, radial], errors, checked=[True, True], confidence=0.95)
    assert both["weights"][0] > 0.99  # converged, the pinhole's better predictions would take the weight


@pytest.mark.bad_input
@pytest.mark.parametrize("threads", [0, -1, 1.5, None])
def test_verification_shards_must_be_a_positive_int(threads, tmp_path):
    from lensdist_torch.calibration.features import verify_in_shards

    with pytest.raises(ValueError, match=r"^threads must be a positive int, got "):
        verify_in_shards(tmp_path / "db.db", None, threads=threads)
