"""Undistortion (lensdist_torch.geometry.undistort): the inverse warp of eq. 4, its mask, gradients."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from lensdist_torch.core.images import load_scene
from lensdist_torch.geometry.distortion import (
    distort_points,
    distortion_center,
    distortion_grid,
    pixel_grid,
    render_distorted,
    sample,
)
from lensdist_torch.geometry.undistort import Undistort, undistort_image, undistortion_grid

H, W = 96, 128
# The largest coefficients of docs/method.md, section 6 at 320 x 424, scaled to 96 x 128
# (k2 ~ 1 / size^2, k4 ~ 1 / size^4): the same relative distortion.
S = 424 / W
K2_MAX, K4_MAX = 2.5e-6 * S**2, 2.5e-11 * S**4


def _truth_and_distorted(k2, k4, dtype=torch.float64):
    """An ideal view of the scene and its distorted rendering, sampled from the scene itself
    (no black borders: the scene is larger than the view)."""
    scene = load_scene("gravel").to(dtype)
    offset = torch.tensor([200.0, 200.0], dtype=dtype)
    k2t, k4t = torch.tensor([k2], dtype=dtype), torch.tensor([k4], dtype=dtype)
    ideal = sample(scene, pixel_grid(H, W, dtype)[None] + offset)
    distorted = sample(scene, distortion_grid(k2t, k4t, H, W, dtype) + offset)
    return ideal, distorted, k2t, k4t


@pytest.mark.parametrize("frac", [0.25, 1.0, -0.3])
def test_round_trip_recovers_the_ideal_view(one_thread_module, frac):
    ideal, distorted, k2, k4 = _truth_and_distorted(frac * K2_MAX, frac * K4_MAX)
    out, valid = undistort_image(distorted, k2, k4)
    assert out.shape == ideal.shape and valid.shape == (1, 1, H, W)
    inner = valid.clone()
    inner[..., :2, :], inner[..., -2:, :], inner[..., :2], inner[..., -2:] = 0, 0, 0, 0
    err = ((out - ideal).abs() * inner).sum() / inner.sum()
    assert float(err) < 0.03  # two bilinear interpolations of a textured scene, compressed at the edges
    assert float(((out - ideal).abs() * inner).amax()) < 0.25
    assert bool((out * (1 - valid) == 0).all())


def test_zero_coefficients_are_the_identity():
    img = torch.rand(2, 3, H, W)
    out, valid = undistort_image(img, torch.zeros(2), torch.zeros(2))
    assert (out - img).abs().max() < 1e-4 and bool((valid == 1).all())  # float32 grid rounding


def test_mask_is_where_the_source_lies_inside():
    k2 = torch.tensor([K2_MAX, -0.5 * K2_MAX], dtype=torch.float64)
    k4 = torch.tensor([K4_MAX, 0.0], dtype=torch.float64)
    grid, valid = undistortion_grid(k2, k4, H, W, torch.float64)
    ideal = pixel_grid(H, W, torch.float64).expand(2, H, W, 2)
    src = distort_points(ideal, k2, k4, distortion_center(H, W))
    assert torch.allclose(grid, src)
    inside = (src[..., 0] >= -1e-3) & (src[..., 0] <= W - 1 + 1e-3) & (src[..., 1] >= -1e-3) & (src[..., 1] <= H - 1 + 1e-3)
    assert torch.equal(valid[:, 0].bool(), inside)
    assert bool(valid[0].all())  # barrel: every ideal pixel comes from inside the frame
    assert float(valid[1].mean()) < 0.95 and valid[1, 0, 0, 0] == 0 and valid[1, 0, H // 2, W // 2] == 1


def test_folded_model_is_masked_not_filled():
    # strongly negative coefficients: eq. 4 folds over inside the frame, no inverse there
    k2, k4 = torch.tensor([-3.0 * K2_MAX]), torch.tensor([-3.0 * K4_MAX])
    out, valid = undistort_image(torch.rand(1, 1, H, W), k2, k4)
    assert 0 < float(valid.mean()) < 1 and bool(valid[0, 0, H // 2, W // 2] == 1)
    assert bool(torch.isfinite(out).all()) and bool((out * (1 - valid) == 0).all())


def test_batched_per_image_coefficients_match_single_calls():
    img = torch.rand(3, 1, H, W)
    k2 = torch.tensor([K2_MAX, 0.0, -0.5 * K2_MAX])
    k4 = torch.tensor([0.0, K4_MAX, 0.0])
    out, valid = undistort_image(img, k2, k4)
    for i in range(3):
        o, v = undistort_image(img[i : i + 1], k2[i], k4[i])
        assert torch.allclose(out[i], o[0], atol=1e-6) and torch.equal(valid[i], v[0])


def test_uint8_and_colour():
    img = (torch.rand(1, 3, H, W) * 255).to(torch.uint8)
    out, _ = undistort_image(img, K2_MAX, K4_MAX)
    ref, _ = undistort_image(img.float() / 255, K2_MAX, K4_MAX)
    assert out.dtype == torch.float32 and out.shape == (1, 3, H, W) and torch.allclose(out, ref)


def test_gradients_reach_image_and_coefficients():
    ideal, distorted, _, _ = _truth_and_distorted(0.5 * K2_MAX, 0.5 * K4_MAX)
    img = distorted.clone().requires_grad_(True)
    k2 = torch.tensor([0.4 * K2_MAX], dtype=torch.float64, requires_grad=True)
    out, valid = undistort_image(img, k2, torch.tensor([0.5 * K4_MAX], dtype=torch.float64))
    loss = ((out - ideal) ** 2 * valid).mean()
    loss.backward()
    assert img.grad is not None and bool(torch.isfinite(img.grad).all()) and float(img.grad.abs().sum()) > 0
    assert bool(torch.isfinite(k2.grad).all())
    # the derivative in k2 agrees with a central difference (a smooth image makes it exact enough)
    smooth = torch.nn.functional.avg_pool2d(distorted, 9, 1, 4, count_include_pad=False)
    k2v, dk = 0.4 * K2_MAX, 1e-3 * K2_MAX
    kk = torch.tensor([k2v], dtype=torch.float64, requires_grad=True)
    f = undistort_image(smooth, kk, 0.0)[0].sum()
    f.backward()
    num = (undistort_image(smooth, k2v + dk, 0.0)[0].sum() - undistort_image(smooth, k2v - dk, 0.0)[0].sum()) / (2 * dk)
    assert float(kk.grad) == pytest.approx(float(num), rel=2e-2)


def test_module_matches_function_and_trains():
    img = torch.rand(2, 1, H, W)
    module = Undistort(K2_MAX, K4_MAX)
    ref = undistort_image(img, K2_MAX, K4_MAX)
    out = module(img)
    assert torch.allclose(out[0], ref[0]) and torch.equal(out[1], ref[1])
    assert set(dict(module.named_buffers())) == {"k2", "k4"} and "k2=" in repr(module)
    trainable = Undistort(nn.Parameter(torch.tensor([K2_MAX])), K4_MAX)
    trainable(img)[0].sum().backward()
    assert trainable.k2.grad is not None and [n for n, _ in trainable.named_parameters()] == ["k2"]


def test_agrees_with_render_inverse_at_float32():
    ideal, distorted, k2, k4 = _truth_and_distorted(K2_MAX, K4_MAX, torch.float32)
    again = render_distorted(undistort_image(distorted, k2, k4)[0], k2, k4)  # distorted -> ideal -> distorted
    inner = (slice(None), slice(None), slice(8, -8), slice(8, -8))
    assert float((again - distorted)[inner].abs().mean()) < 0.03


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "k2,k4,match",
    [
        (torch.zeros(3), torch.zeros(3), "1 value or one per image"),
        (torch.zeros(2), torch.zeros(1), "same number of values"),
        (float("nan"), 0.0, "k2 must be finite"),
        (torch.zeros(0), torch.zeros(0), "k2 must hold one value"),
    ],
)
def test_bad_coefficients_are_one_line_errors(k2, k4, match):
    with pytest.raises(ValueError, match=match) as err:
        undistort_image(torch.rand(2, 1, 16, 16), k2, k4)
    assert "\n" not in str(err.value)


@pytest.mark.bad_input
def test_bad_image_and_mode():
    with pytest.raises(ValueError, match="img must have shape"):
        undistort_image(torch.rand(16, 16), 0.0, 0.0)
    with pytest.raises(ValueError, match="mode must be"):
        undistort_image(torch.rand(1, 1, 16, 16), 0.0, 0.0, mode="area")
    with pytest.raises(ValueError, match="height and width"):
        undistortion_grid(0.0, 0.0, 0, 16)
