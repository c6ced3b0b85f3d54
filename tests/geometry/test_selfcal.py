"""Self-calibration (lensdist_torch.geometry.selfcal): eq. 4 inverse, recovery, confidence, flags,
gradients, input checks."""

from __future__ import annotations

import math

import pytest
import torch

from lensdist_torch.core.images import load_scene
from lensdist_torch.geometry.distortion import delta_avg, distort_points, distortion_grid, sample, undistort_points
from lensdist_torch.geometry.selfcal import (
    SelfCalConfig,
    distort_normalized,
    estimate_distortion,
    selfcal_residual,
    undistort_normalized,
)

# Stated tolerances of the recovery on noiseless pairs with enough motion (normalised units,
# a = k2 R^2, b = k4 R^4, R the half diagonal; the largest coefficients of docs/method.md,
# section 6 are a = 0.18, b = 0.12).
TOL_A, TOL_B, TOL_DELTA_AVG_PX = 0.03, 0.05, 0.3


def _pair(h, w, k2, k4, shift, offset=(40.0, 44.0)):
    """Two views of the gravel scene, translated by `shift` (x, y) px, same distortion:
    I(p_d) = S(p(p_d) + o). True H (img1 -> img2, ideal coords) = translation by -shift."""
    s = load_scene("gravel").double()
    k2 = torch.tensor([k2], dtype=torch.float64)
    k4 = torch.tensor([k4], dtype=torch.float64)
    g = distortion_grid(k2, k4, h, w, dtype=torch.float64)
    o = torch.tensor([offset[1], offset[0]], dtype=torch.float64)
    i1 = sample(s, g + o).float()
    i2 = sample(s, g + o + torch.tensor(shift, dtype=torch.float64)).float()
    return i1, i2


def _norm(h, w):
    return 0.5 * math.hypot(w - 1, h - 1)


@pytest.mark.parametrize("k2,k4", [(2.5e-6, 2.5e-11), (1e-6, 0.0), (-1.0e-6, -2e-12), (3e-7, 1.7e-11)])
def test_newton_inverse_matches_eq4(k2, k4):
    h, w = 320, 424
    c = ((w - 1) / 2, (h - 1) / 2)
    pd = torch.stack(torch.meshgrid(torch.linspace(0, w - 1, 41), torch.linspace(0, h - 1, 33), indexing="xy"), -1)
    pd = pd.double().reshape(1, -1, 2)
    p = undistort_points(pd, [k2], [k4], c)
    assert (distort_points(p, [k2], [k4], c) - pd).abs().max() < 1e-6
    r = _norm(h, w)
    a, b = torch.tensor([k2 * r**2]).double(), torch.tensor([k4 * r**4]).double()
    ud = (pd - torch.tensor(c).double()) / r
    back = distort_normalized(undistort_normalized(ud, a, b), a, b, iterations=8)
    assert ((back - ud).abs() * r).max() < 1e-6


def test_recovers_known_coefficients_at_spec_size():
    h, w = 320, 424
    r = _norm(h, w)
    k2, k4 = 1.4e-6, 1.2e-11
    i1, i2 = _pair(h, w, k2, k4, (2.0, 18.0))
    k2h, k4h, H, info = estimate_distortion(i1, i2)
    assert bool(info.converged[0]) and bool(info.confident[0])
    assert abs(float(k2h[0]) - k2) * r**2 < TOL_A
    assert abs(float(k4h[0]) - k4) * r**4 < TOL_B
    true = float(delta_avg([k2], [k4], 320, 424)[0])
    assert abs(float(info.delta_avg[0]) - true) < TOL_DELTA_AVG_PX
    assert torch.allclose(H[0, :2, 2], torch.tensor([-2.0, -18.0], dtype=H.dtype), atol=0.3)


def test_pincushion_negative_coefficients():
    h, w = 160, 212
    r = _norm(h, w)
    a, b = -0.12, -0.03
    i1, i2 = _pair(h, w, a / r**2, b / r**4, (1.0, 9.0))
    k2h, k4h, _, info = estimate_distortion(i1, i2, config=SelfCalConfig(levels=2, iterations=(12, 6), sample_block=(1, 2)))
    assert bool(info.converged[0])
    assert abs(float(k2h[0]) * r**2 - a) < TOL_A and abs(float(k4h[0]) * r**4 - b) < TOL_B


def test_no_motion_is_low_confidence():
    h, w = 160, 212
    r = _norm(h, w)
    i1, _ = _pair(h, w, 0.15 / r**2, 0.05 / r**4, (0.0, 0.0))
    cfg = SelfCalConfig(levels=2, iterations=(8, 4), sample_block=(1, 2))
    _, _, _, info = estimate_distortion(i1, i1.clone(), config=cfg)
    assert float(info.confidence[0]) < cfg.confidence_threshold and not bool(info.confident[0])
    # a textureless pair: never confident
    flat = torch.full((1, 1, h, w), 0.5)
    _, _, _, info = estimate_distortion(flat, flat.clone(), config=cfg)
    assert not bool(info.confident[0])


def test_divergent_pair_is_flagged_not_returned():
    h, w = 160, 212
    r = _norm(h, w)
    i1, i2 = _pair(h, w, 0.1 / r**2, 0.05 / r**4, (0.0, 8.0))
    far = torch.eye(3, dtype=torch.float64)[None].repeat(2, 1, 1)
    far[0, 0, 2] = 5000.0  # maps img1 entirely outside img2: no overlap
    far[1, 1, 2] = -8.0  # a sane one beside it
    cfg = SelfCalConfig(levels=2, iterations=(8, 4), sample_block=(1, 2))
    k2, k4, H, info = estimate_distortion(i1.repeat(2, 1, 1, 1), i2.repeat(2, 1, 1, 1), init=far, config=cfg)
    assert not bool(info.converged[0]) and not bool(info.confident[0])
    assert math.isnan(float(k2[0])) and math.isnan(float(k4[0])) and torch.isnan(H[0]).all()
    assert math.isnan(float(info.delta_avg[0]))
    assert bool(info.converged[1]) and math.isfinite(float(k2[1]))


def test_gradients_through_the_model_are_finite():
    h, w = 64, 80
    i1, i2 = _pair(h, w, 2e-5, 1e-9, (0.5, 3.0))
    H = torch.eye(3, dtype=torch.float64)
    H[1, 2] = -3.0
    H = H[None].clone().requires_grad_(True)
    k2 = torch.tensor([1e-5], dtype=torch.float64, requires_grad=True)
    k4 = torch.tensor([1e-10], dtype=torch.float64, requires_grad=True)
    res, valid = selfcal_residual(i1, i2, H, k2, k4)
    loss = (res**2).sum() / valid.sum()
    loss.backward()
    for g in (H.grad, k2.grad, k4.grad):
        assert g is not None and torch.isfinite(g).all()
    assert float(k2.grad.abs()) > 0


@pytest.mark.bad_input
@pytest.mark.parametrize("h,w,levels", [(1, 1, 3), (4, 4, 3), (7, 40, 3), (15, 40, 3), (40, 15, 3), (31, 40, 5)])
def test_too_small_images_raise_one_line(h, w, levels):
    """Below 16 x 16 (and 2^levels) a one-line ValueError naming img1/img2 and the minimum."""
    cfg = SelfCalConfig(levels=levels, iterations=(2,) * levels, sample_block=(1,) * levels)
    least = max(16, 2**levels)
    x = torch.rand(1, 1, h, w)
    with pytest.raises(ValueError, match=rf"^img1 and img2 must be at least {least} x {least} pixels, got {h} x {w}$"):
        estimate_distortion(x, x.clone(), config=cfg)


def test_smallest_accepted_size_runs():
    i1, i2 = _pair(16, 16, 0.0, 0.0, (1.0, 0.0))
    cfg = SelfCalConfig(levels=2, iterations=(2, 2), sample_block=(1, 1))
    k2, _, _, info = estimate_distortion(i1, i2, config=cfg)
    assert k2.shape == (1,) and info.converged.shape == (1,)


def test_public_exports():
    import lensdist_torch

    assert lensdist_torch.estimate_distortion is estimate_distortion
    assert lensdist_torch.DeltaRegressor.__name__ == "DeltaRegressor"
