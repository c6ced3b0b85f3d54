"""Undistortion (lensdist_torch.geometry.undistort): the inverse warp of eq. 4, its mask, gradients."""

from __future__ import annotations

import numpy as np
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
    sample_at_pixels,
)
from lensdist_torch.geometry.undistort import Undistort, monotone_branch, undistort_image, undistortion_grid

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
    ideal = sample_at_pixels(scene, pixel_grid(H, W, dtype)[None] + offset)
    distorted = sample_at_pixels(scene, distortion_grid(k2t, k4t, H, W, dtype=dtype) + offset)
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
    grid, valid = undistortion_grid(k2, k4, H, W, dtype=torch.float64)
    ideal = pixel_grid(H, W, torch.float64).expand(2, H, W, 2)
    src = distort_points(ideal, k2, k4, distortion_center(H, W))
    assert torch.allclose(grid, src)
    inside = (
        (src[..., 0] >= -1e-3) & (src[..., 0] <= W - 1 + 1e-3) & (src[..., 1] >= -1e-3) & (src[..., 1] <= H - 1 + 1e-3)
    )
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


# ------------------------------------------------------------------ folded coefficients (issue 19)
def _numeric_fold_radius(k2: float, k4: float, r_max: float, step: float = 1e-4) -> float:
    """Independently of the library: the first radius where r (1 + k2 r^2 + k4 r^4) stops
    increasing, on a grid of ``step`` px (numpy, float64); inf if it increases up to r_max."""
    r = np.arange(0.0, r_max, step)
    f = r * (1 + k2 * r**2 + k4 * r**4)
    down = np.nonzero(np.diff(f) <= 0)[0]
    return float(r[down[0]]) if down.size else float("inf")


@pytest.mark.bad_input
@pytest.mark.parametrize("k2,k4", [(-1e-3, 0.0), (-1e-4, -1e-9), (-8e-6, 2e-11)])
def test_folded_coefficients_never_give_a_mirrored_or_folded_sample(k2, k4):
    # the audit's coefficients at 320 x 424: before the fix 17-20 k pixels were sampled from
    # mirrored positions (the negative Newton root, whose round trip is exact) and marked valid
    h, w = 320, 424
    grid, valid = undistortion_grid(k2, k4, h, w, dtype=torch.float64)
    c = np.array(distortion_center(h, w))
    src = grid[0].numpy() - c
    ideal = pixel_grid(h, w, torch.float64).numpy() - c
    ok = valid[0, 0].numpy() > 0
    fold = _numeric_fold_radius(k2, k4, 300.0)
    r = np.linalg.norm(src, axis=-1)
    assert fold < 265  # every case folds inside the frame's half diagonal
    assert (r[ok] < fold + 1e-3).all()  # only the monotone branch is sampled
    assert ((src * ideal).sum(-1)[ok] >= 0).all()  # never the mirrored side
    # and everything that has a preimage on the monotone branch inside the frame is kept
    rho_max = fold * (1 + k2 * fold**2 + k4 * fold**4)
    rho = np.linalg.norm(ideal, axis=-1)
    x, y = src[..., 0] + c[0], src[..., 1] + c[1]
    inside = (x >= -1e-3) & (x <= w - 1 + 1e-3) & (y >= -1e-3) & (y <= h - 1 + 1e-3)
    expected = (rho < rho_max - 1e-2) & inside
    assert (ok >= expected).all() and ok.sum() <= (rho < rho_max + 1e-2).sum()
    if (k2, k4) == (-1e-3, 0.0):
        assert 440 < ok.sum() < 480  # a disc of radius rho_max = 12.2 px: pi 12.2^2 = 466 pixels


@pytest.mark.bad_input
def test_monotone_branch_agrees_with_a_numeric_check():
    gen = torch.Generator().manual_seed(0)
    k2 = (torch.rand(400, generator=gen, dtype=torch.float64) * 2 - 1) * 1e-4
    k4 = (torch.rand(400, generator=gen, dtype=torch.float64) * 2 - 1) * 2e-9
    r = torch.rand(400, generator=gen, dtype=torch.float64) * 300
    got = monotone_branch(r * r, k2, k4)
    fold = torch.tensor([_numeric_fold_radius(float(a), float(b), 310.0, 1e-2) for a, b in zip(k2, k4)])
    want = r < fold
    near = (fold - r).abs() < 2e-2  # grid resolution of the numeric check
    assert torch.equal(got[~near], want[~near]) and int(near.sum()) < 5
    assert 50 < int(want.sum()) < 350  # both answers are well represented
    # a dip that comes back up (k2 < 0, k4 > 0): positive derivative at r, yet folded before it
    assert 1 + 3 * -8e-6 * 450.0**2 + 5 * 2e-11 * 450.0**4 > 0  # eq. 4 folds at 231 px and unfolds at 432 px
    assert not bool(monotone_branch(torch.tensor(450.0**2), -8e-6, 2e-11))
    assert bool(monotone_branch(torch.tensor(200.0**2), -8e-6, 2e-11))
