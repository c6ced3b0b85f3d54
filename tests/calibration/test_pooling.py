"""How a sequence's pairs pool (lensdist_torch.calibration.pooling): the good-and-bad mixture by hand.

With every pair good and consistent, the mixture's mean is the inverse-variance mean and kappa is
1; a failure, however tight, gets no weight; the good pairs' scatter beyond their stds is the
maximum-likelihood kappa^2 = mean((d - mu)^2) / sigma^2 for equal sigma; the fit moves with the
data (shift) and scales with it (units).
"""

from __future__ import annotations

import math

import pytest
import torch

from lensdist_torch.calibration.pooling import good_and_bad

F64 = torch.float64


def test_consistent_pairs_give_the_inverse_variance_mean():
    d = torch.tensor([2.00, 2.03, 1.98, 2.01, 1.99], dtype=F64)
    s = torch.tensor([0.02, 0.03, 0.02, 0.04, 0.03], dtype=F64)
    fit = good_and_bad(d, s, width=57.6)
    w = 1 / s**2
    assert fit.mean == pytest.approx(float((w * d).sum() / w.sum()), abs=1e-9)
    assert fit.kappa == 1.0 and bool((fit.p_good > 0.99).all())
    assert torch.allclose(fit.weights / fit.weights.sum(), w / w.sum(), atol=1e-6)


def test_a_tight_failure_gets_no_weight():
    # ten pairs about 6 px scattering by 0.5 beyond their 0.3 px stds, one confident pair at 0 (a failure)
    g = torch.Generator().manual_seed(0)
    good = 6.0 + 0.5 * torch.randn(10, generator=g, dtype=F64) + 0.3 * torch.randn(10, generator=g, dtype=F64)
    d = torch.cat([good, torch.tensor([0.0], dtype=F64)])
    s = torch.cat([torch.full((10,), 0.3, dtype=F64), torch.tensor([0.08], dtype=F64)])
    ivw = float((d / s**2).sum() / (1 / s**2).sum())
    fit = good_and_bad(d, s, width=57.6)
    assert ivw < 3.0  # the inverse-variance mean follows the tight failure
    assert abs(fit.mean - float(good.mean())) < 0.1 and float(fit.p_good[-1]) < 1e-6
    assert 1.3 < fit.kappa < 4.0  # the good pairs scatter beyond their stds


def test_kappa_is_the_maximum_likelihood_scale():
    d = torch.tensor([3.0, 3.4, 2.6, 3.2, 2.8], dtype=F64)  # mean 3, mean square deviation 0.08
    fit = good_and_bad(d, torch.full((5,), 0.1, dtype=F64), width=1e6)
    assert fit.mean == pytest.approx(3.0, abs=1e-9) and fit.kappa == pytest.approx(math.sqrt(0.08 / 0.01), abs=1e-4)
    assert good_and_bad(d, torch.full((5,), 1.0, dtype=F64), width=1e6).kappa == 1.0  # stds too large: kept


def test_failures_may_outnumber_the_good_pairs():
    # 8 good pairs near 12 px and 11 failures near 0 with wide stds (values like those of real views far
    # apart, docs/method.md section 10): the median is no start; those that cannot tell weigh little
    good = torch.tensor([12.28, 12.48, 13.16, 11.67, 10.62, 12.02, 11.19, 13.73], dtype=F64)
    good_s = torch.tensor([0.48, 0.42, 0.62, 0.32, 0.36, 0.80, 0.38, 0.45], dtype=F64)
    bad = torch.tensor([0.22, 0.94, 0.09, 1.87, 0.34, 0.02, 0.45, 1.22, 0.38, 0.62, 0.32], dtype=F64)
    bad_s = torch.tensor([1.92, 1.86, 3.68, 2.92, 3.53, 1.93, 3.38, 2.92, 3.15, 5.52, 0.94], dtype=F64)
    d, s = torch.cat([good, bad]), torch.cat([good_s, bad_s])
    fit = good_and_bad(d, s, width=57.6)
    w = 1 / s**2
    assert float(d.median()) < 2 and float((w * d).sum() / w.sum()) < 11.5  # the loose pairs pull both down
    assert abs(fit.mean - float(good.mean())) < 1.0 and fit.kappa > 2


@pytest.mark.parametrize("shift, scale", [(5.0, 1.0), (0.0, 3.0), (-2.0, 0.5)])
def test_the_fit_moves_and_scales_with_the_data(shift, scale):
    g = torch.Generator().manual_seed(1)
    d = torch.cat([1.0 + 0.2 * torch.randn(8, generator=g, dtype=F64), torch.tensor([9.0, -7.0], dtype=F64)])
    s = 0.1 + 0.1 * torch.rand(10, generator=g, dtype=F64)
    base = good_and_bad(d, s, width=40.0)
    moved = good_and_bad(scale * d + shift, scale * s, width=40.0 * scale)
    assert moved.mean == pytest.approx(scale * base.mean + shift, abs=1e-6 * scale)
    assert moved.kappa == pytest.approx(base.kappa, abs=1e-6)
    assert torch.allclose(moved.p_good, base.p_good, atol=1e-6)


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "values, std, width, match",
    [
        ([1.0, 2.0], [0.1], 10.0, "values and std"),
        ([], [], 10.0, "values and std"),
        ([1.0, float("nan")], [0.1, 0.1], 10.0, "finite"),
        ([1.0, 2.0], [0.1, 0.0], 10.0, "std"),
        ([1.0, 2.0], [0.1, 0.1], 0.0, "width"),
        ([1.0, 2.0], [0.1, 0.1], float("inf"), "width"),
    ],
)
def test_bad_arguments_are_named(values, std, width, match):
    with pytest.raises(ValueError, match=match):
        good_and_bad(torch.tensor(values, dtype=F64), torch.tensor(std, dtype=F64), width)
