"""Gradients of the smooth registration-quality path (docs/method.md, section 5).

gradcheck runs in float64 on tiny images (8 x 8 or 16 x 16, block size 8), with respect to both
images. Where the loss is legitimately not differentiable the inputs are chosen to avoid it, and
finiteness is checked instead (see the comments at each case).

Points where the smooth loss is not differentiable, by construction of the formulas of docs/method.md:
* abs(dot) and abs(cross) at 0 (perpendicular or parallel gradients), the 3 x 3 max-pool of the
  risk map at ties. At these points the one-sided derivatives differ; gradcheck still passes
  when the kink is symmetric (a central difference of |x| at 0 is 0, as is torch's subgradient)
  or sits where the sigmoids are saturated, which is the case for the inputs below.
* The orientation of a vanishing gradient: a zero vector has none (docs/method.md, section 2:
  against a non-zero vector A = 0, against another zero vector A = 1), while a tiny non-zero
  vector has a definite direction, whatever its length. Where a gradient is exactly zero a
  neighbouring pixel moved by +-1e-6 gives it a direction and the loss jumps: there gradcheck
  must fail, and only finite gradients can be asked for (test_discontinuity_...).
"""

from __future__ import annotations

import pytest
import torch
from torch.autograd import gradcheck

from lensdist_torch import QualityConfig, RegistrationQualityLoss, registration_quality, registration_quality_loss
from lensdist_torch.metric import local_criteria

F64 = torch.float64


def _rand(shape, seed, dtype=F64):
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)


def _loss_sum(cfg=None, valid=None):
    return lambda a, b: registration_quality_loss(a, b, valid, config=cfg, reduction="sum")


def _check(img1, img2, fn=None, fast=False):
    x = img1.detach().clone().to(F64).requires_grad_()
    y = img2.detach().clone().to(F64).requires_grad_()
    assert gradcheck(fn or _loss_sum(), (x, y), eps=1e-6, atol=1e-5, rtol=1e-3, fast_mode=fast)


def _square(n=8, lo=2, hi=6):
    sq = torch.zeros(1, 1, n, n, dtype=F64)
    sq[..., lo:hi, lo:hi] = 1
    return sq


# ----------------------------------------------------------------------------- gradcheck


class TestGradcheck:
    def test_random(self):
        _check(_rand((1, 1, 8, 8), 0), _rand((1, 1, 8, 8), 1))

    def test_random_16_soft_and_sharp(self):
        a, b = _rand((1, 1, 16, 16), 2), _rand((1, 1, 16, 16), 3)
        _check(a, b, fast=True)
        _check(a, b, _loss_sum(QualityConfig().with_temperature_scale(10.0)), fast=True)

    def test_low_contrast_shifted(self):
        # gradients of the order of theta_G: the risk-map sigmoids are not saturated
        base = 0.5 + 0.05 * torch.randn(1, 1, 16, 16, generator=torch.Generator().manual_seed(4), dtype=F64)
        other = torch.roll(base, 1, -1) + 0.01 * _rand((1, 1, 16, 16), 5)
        _check(base, other, fast=True)
        _check(base[..., :8, :8], other[..., :8, :8])

    def test_constant(self):
        # all gradients zero: masked sqrt and atan2; a +-eps perturbation changes |s| the same
        # way on both sides, so the numerical derivative is 0 like the analytical one
        c1 = torch.full((1, 1, 8, 8), 0.5, dtype=F64)
        c2 = torch.full((1, 1, 8, 8), 0.3, dtype=F64)
        _check(c1, c2)
        _check(c1, c1)

    def test_identical(self):
        # cross = 0 everywhere: abs at 0 (a symmetric kink, see the module docstring)
        x = _rand((1, 1, 8, 8), 6)
        _check(x, x)
        y = _rand((1, 1, 16, 16), 7)
        _check(y, y, fast=True)

    def test_saturated(self):
        # binary 0/1 images. Random ones have (with this seed) no flat pixel next to a strong
        # gradient of the other image outside the risk map; perpendicular squares give |dot| = 0
        # kinks on saturated sigmoids.
        g = torch.Generator().manual_seed(8)
        b1 = (torch.rand(1, 1, 8, 8, generator=g) > 0.5).to(F64)
        b2 = (torch.rand(1, 1, 8, 8, generator=g) > 0.5).to(F64)
        _check(b1, b2)
        _check(b1, b1)
        sq = _square()
        _check(sq, sq.transpose(-1, -2).flip(-1))

    def test_with_valid_mask(self):
        valid = torch.ones(1, 1, 8, 8, dtype=F64)
        valid[..., :, :2] = 0
        valid[..., 5, 5] = 0.3
        _check(_rand((1, 1, 8, 8), 9), _rand((1, 1, 8, 8), 10), _loss_sum(valid=valid))

    def test_mean_and_none_reductions_batch(self):
        a, b = _rand((2, 1, 8, 16), 11), _rand((2, 1, 8, 16), 12)
        _check(a, b, lambda x, y: registration_quality_loss(x, y), fast=True)
        _check(a, b, lambda x, y: registration_quality_loss(x, y, reduction="none"), fast=True)
        _check(a, b, lambda x, y: RegistrationQualityLoss(reduction="none")(x, y), fast=True)

    def test_smooth_metric_outputs(self):
        # the visual map too: |I1 - I2| is differentiable away from I1 = I2 (random images)
        def both_maps(x, y):
            res = registration_quality(x, y, smooth=True)
            return res.registration_map, res.visual_map, res.quality_index

        _check(_rand((1, 1, 8, 8), 13), _rand((1, 1, 8, 8), 14), both_maps, fast=True)

    def test_rgb_input(self):
        a, b = _rand((1, 3, 8, 8), 15), _rand((1, 3, 8, 8), 16)
        _check(a, b, fast=True)


# ----------------------------------------------------------------------------- finite gradients


def _grads(img1, img2, dtype, **kw):
    x = img1.detach().clone().to(dtype).requires_grad_()
    y = img2.detach().clone().to(dtype).requires_grad_()
    loss = registration_quality_loss(x, y, **kw)
    loss.backward()
    return loss, x.grad, y.grad


def _finite(img1, img2, dtype, **kw):
    loss, gx, gy = _grads(img1, img2, dtype, **kw)
    assert bool(torch.isfinite(loss).all())
    assert gx is not None and gy is not None
    assert bool(torch.isfinite(gx).all()), gx
    assert bool(torch.isfinite(gy).all()), gy
    return gx, gy


_SPECIAL = {
    "constant": lambda: (torch.full((2, 1, 16, 16), 0.5, dtype=F64), torch.full((2, 1, 16, 16), 0.25, dtype=F64)),
    "zeros": lambda: (torch.zeros(1, 1, 16, 16, dtype=F64), torch.zeros(1, 1, 16, 16, dtype=F64)),
    "ones_vs_zeros": lambda: (torch.ones(1, 1, 16, 16, dtype=F64), torch.zeros(1, 1, 16, 16, dtype=F64)),
    "identical": lambda: (_rand((2, 1, 16, 16), 20),) * 2,
    "saturated": lambda: ((_rand((2, 1, 16, 16), 21) > 0.5).to(F64), (_rand((2, 1, 16, 16), 22) > 0.5).to(F64)),
    "saturated_square_shift": lambda: (_square(16, 4, 12), torch.roll(_square(16, 4, 12), 1, -1)),
    "half_flat": lambda: (
        torch.cat([_rand((1, 1, 16, 8), 23), torch.full((1, 1, 16, 8), 1.0, dtype=F64)], -1),
        _rand((1, 1, 16, 16), 24),
    ),
}


class TestFiniteGradients:
    @pytest.mark.parametrize("name", sorted(_SPECIAL))
    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    @pytest.mark.parametrize("reduction", ["mean", "sum"])
    def test_special_inputs(self, name, dtype, reduction):
        img1, img2 = _SPECIAL[name]()
        _finite(img1, img2, dtype, reduction=reduction)
        valid = torch.ones(img1.shape[0], 1, 16, 16)
        valid[..., 3:7, 3:7] = 0
        _finite(img1, img2, dtype, valid=valid, reduction=reduction)
        _finite(img1, img2, dtype, config=QualityConfig().with_temperature_scale(1e-3), reduction=reduction)

    def test_constant_gives_zero_gradient(self):
        img1, img2 = _SPECIAL["constant"]()
        for dtype in (torch.float32, F64):
            _, gx, gy = _grads(img1, img2, dtype)
            assert bool((gx == 0).all()) and bool((gy == 0).all())

    @pytest.mark.parametrize(
        "base,noise",
        [
            (0.5, 1e-9),  # the brief's case; in float32 0.5 + 1e-9 rounds to exactly 0.5
            (0.5, 1e-7),  # a few float32 ulps around 0.5
            (0.01, 1e-9),  # gradients ~1e-10: dot, cross ~1e-20 (used to give NaN in float32)
            (0.001, 1e-10),
            (0.001, 1e-11),
            (1e-6, 1e-12),
        ],
    )
    @pytest.mark.parametrize("dtype", [torch.float32, F64])
    def test_nearly_flat(self, base, noise, dtype):
        g = torch.Generator().manual_seed(25)
        img1 = base + noise * torch.randn(2, 1, 16, 16, generator=g, dtype=F64)
        img2 = base + noise * torch.randn(2, 1, 16, 16, generator=g, dtype=F64)
        for reduction in ("mean", "sum", "none"):
            x = img1.to(dtype).requires_grad_()
            y = img2.to(dtype).requires_grad_()
            out = registration_quality_loss(x, y, reduction=reduction)
            out.sum().backward()
            assert bool(torch.isfinite(out).all())
            assert bool(torch.isfinite(x.grad).all()) and bool(torch.isfinite(y.grad).all())
        assert bool(torch.isfinite(_finite(img1, img1 * 0.999, dtype)[0]).all())

    def test_flat_images_keep_their_orientation_values(self):
        # "Guards must not move the values" (docs/method.md, section 5): the smooth path's A equals the hard one
        # even when the gradients are tiny (no eps swamps the angle)
        g = torch.Generator().manual_seed(26)
        for noise in (1e-3, 1e-6, 1e-9):
            img1 = 0.5 + noise * torch.randn(1, 1, 16, 16, generator=g, dtype=F64)
            img2 = 0.5 + noise * torch.randn(1, 1, 16, 16, generator=g, dtype=F64)
            hard = local_criteria(img1, img2)
            smooth = local_criteria(img1, img2, smooth=True)
            torch.testing.assert_close(smooth.a, hard.a, atol=1e-9, rtol=0)
            assert 0.05 < float(hard.a.std())  # the angles are real, not masked to 1
        img1 = (0.01 + 1e-7 * torch.randn(1, 1, 16, 16, generator=g, dtype=F64)).float()
        img2 = (0.01 + 1e-7 * torch.randn(1, 1, 16, 16, generator=g, dtype=F64)).float()
        smooth_a = local_criteria(img1, img2, smooth=True).a
        torch.testing.assert_close(smooth_a, local_criteria(img1, img2).a, atol=1e-5, rtol=0)

    def test_discontinuity_at_vanishing_gradient(self):
        """Why gradcheck cannot pass on every saturated input (module docstring, last point).

        img1 is a square, img2 the square moved right by one pixel. Column 7 of img1 is flat
        (zero gradient) while img2 has its strong edge there. Moving img1[1, 6] by +-1e-6 gives
        the zero vectors around it a tiny gradient with a definite direction, so the loss jumps
        by about the same amount either way: the difference quotients exceed 1e3.
        """
        sq = _square()
        img2 = torch.roll(sq, 1, -1)
        f = _loss_sum()
        f0 = float(f(sq, img2))
        up, down = sq.clone(), sq.clone()
        up[0, 0, 1, 6] += 1e-6
        down[0, 0, 1, 6] -= 1e-6
        assert (float(f(up, img2)) - f0) / 1e-6 > 1e3
        assert (float(f(down, img2)) - f0) / 1e-6 > 1e3
        # ... yet the analytical gradient exists and is finite in both dtypes
        for dtype in (torch.float32, F64):
            _finite(sq, img2, dtype, reduction="sum")

    def test_gradients_reach_both_images(self):
        a, b = _rand((1, 1, 16, 16), 27), _rand((1, 1, 16, 16), 28)
        _, gx, gy = _grads(0.5 + 0.1 * a, 0.5 + 0.1 * b, F64)
        assert float(gx.abs().sum()) > 0 and float(gy.abs().sum()) > 0

    def test_uint8_input_is_not_differentiable_but_works(self):
        u = (torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(29)) * 255).to(torch.uint8)
        y = torch.rand(1, 1, 8, 8, requires_grad=True)
        registration_quality_loss(u, y).backward()
        assert bool(torch.isfinite(y.grad).all())

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda_finite(self):
        for name in ("constant", "identical", "saturated", "half_flat"):
            img1, img2 = _SPECIAL[name]()
            _finite(img1.cuda(), img2.cuda(), torch.float32)
        img1 = (0.01 + 1e-9 * torch.randn(1, 1, 16, 16, dtype=F64)).cuda()
        _finite(img1, img1.flip(-1), torch.float32)
