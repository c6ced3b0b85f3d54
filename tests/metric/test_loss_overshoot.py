"""The loss takes what an interpolating warp produces: a bicubic warp's overshoot is measured, not refused."""

import pytest
import torch
import torch.nn.functional as F
from one_line import one_line_error

from lensdist_torch import quality_map, registration_quality_loss
from lensdist_torch.metric.loss import OVERSHOOT


def _bicubic_shift(x: torch.Tensor) -> torch.Tensor:
    """x moved by half a pixel with PyTorch's bicubic kernel: a binary image overshoots [0, 1]."""
    theta = torch.tensor([[[1.0, 0, 1.0 / x.shape[-1]], [0, 1.0, 1.0 / x.shape[-2]]]])
    grid = F.affine_grid(theta.expand(x.shape[0], -1, -1), list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bicubic", align_corners=False, padding_mode="border")


@pytest.fixture
def pair():
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(2, 1, 64, 64, generator=g) > 0.5).float()
    return x, _bicubic_shift(x)


def test_a_bicubic_overshoot_is_measured_with_its_gradient(pair):
    x, warped = pair
    assert warped.min() < -0.2 and warped.max() > 1.2  # the overshoot that used to raise
    warped.requires_grad_()
    loss = registration_quality_loss(warped, x)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(warped.grad).all() and warped.grad.abs().sum() > 0
    # the same images in 0-255 with data_range=255: the same loss (the overshoot is in units of white)
    assert float(registration_quality_loss(255 * warped.detach(), 255 * x, data_range=255)) == pytest.approx(
        float(loss)
    )


def test_bicubic_overshoot_is_bounded_by_the_constant():
    """The worst pattern for a half-pixel bicubic shift (a = -0.75): +1 under positive taps, 0 under the negative."""
    w = torch.tensor([-0.09375, 0.59375, 0.59375, -0.09375])  # the kernel at t = 0.5
    w2 = w[:, None] * w[None, :]
    over = float(w2.clamp_min(0).sum()) - 1
    assert over == pytest.approx(0.4453125) and over < OVERSHOOT


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "scale,words", [(255.0, ("img1", "data_range=255")), (1.0 + 1.5 * OVERSHOOT, ("img1", "expected [0, 1]"))]
)
def test_farther_out_is_still_a_one_line_error(pair, scale, words):
    x, _ = pair
    one_line_error(ValueError, lambda: registration_quality_loss(x * scale, x), *words)


def test_the_metric_itself_stays_strict(pair):
    """The paper's metric counts error blocks: an image outside [0, 1] is the caller's to fix there."""
    x, warped = pair
    one_line_error(ValueError, lambda: quality_map(warped, x), "img1")
