"""The loss and the validity mask: the plain mean rewards masking, the masked mean does not.

``reduction="mean"`` counts invalid blocks as error-free, so a warp that pushes the image out of
the frame lowers it (the README's snippet: 0.598 with a full mask, 0.149 with a quarter, 0 with
none). ``"masked_mean"`` (the default) averages over the valid blocks only, with the mask
binarised at 0.5 and detached; no valid block gives 0 with a zero gradient.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from metric_helpers import textured
from one_line import one_line_error

from lensdist_torch import RegistrationQualityLoss, registration_quality_loss
from lensdist_torch.metric.loss import REDUCTIONS


def periodic_pair(h: int = 64, w: int = 96, seed: int = 0):
    """An 8-periodic texture and its copy shifted by 1 px (circularly): every interior block holds
    the same content and the same misregistration, so any mean over interior blocks is equal."""
    g = torch.Generator().manual_seed(seed)
    tile = torch.rand(1, 1, 8, 8, generator=g, dtype=torch.float64)
    img1 = tile.repeat(1, 1, h // 8, w // 8)
    return img1, torch.roll(img1, 1, dims=-1)


def rect_mask(h, w, y0, y1, x0, x1, dtype=torch.float64):
    v = torch.zeros(1, 1, h, w, dtype=dtype)
    v[..., y0:y1, x0:x1] = 1
    return v


class TestPlainMeanRewardsMasking:
    def test_the_three_numbers(self, scene_pair):
        a, b = (t[..., :160, :216].contiguous() for t in scene_pair)
        full = torch.ones_like(a)
        quarter = rect_mask(160, 216, 0, 80, 0, 108, a.dtype)
        none = torch.zeros_like(a)
        mean = [float(registration_quality_loss(a, b, v, reduction="mean")) for v in (full, quarter, none)]
        masked = [float(registration_quality_loss(a, b, v)) for v in (full, quarter, none)]
        # the old default: a quarter of the frame gives about a quarter of the loss, none gives 0
        assert mean[0] > 0.2
        assert 0.15 * mean[0] < mean[1] < 0.35 * mean[0]
        assert mean[2] == 0.0
        # the masked mean (the default now): the same misregistration gives about the same loss
        assert masked[0] == pytest.approx(mean[0], abs=1e-6)  # everything valid: the plain mean
        assert masked[1] == pytest.approx(masked[0], rel=0.15)
        assert masked[2] == 0.0
        assert torch.equal(RegistrationQualityLoss()(a, b, quarter), registration_quality_loss(a, b, quarter))

    def test_masked_mean_does_not_decrease_when_the_mask_shrinks(self):
        img1, img2 = periodic_pair()
        h, w = img1.shape[-2:]
        # interior windows, shrinking; the edges of the smaller ones are not block-aligned
        masks = [
            rect_mask(h, w, 8, 56, 8, 88),
            rect_mask(h, w, 8, 40, 8, 64),
            rect_mask(h, w, 13, 45, 21, 70),
            rect_mask(h, w, 16, 33, 16, 35),
        ]
        masked = [float(registration_quality_loss(img1, img2, v)) for v in masks]
        plain = [float(registration_quality_loss(img1, img2, v, reduction="mean")) for v in masks]
        assert masked[0] > 0.3
        for m in masked[1:]:
            assert m >= masked[0] - 1e-9
            assert m == pytest.approx(masked[0], abs=1e-9)
        assert plain == sorted(plain, reverse=True) and plain[-1] < 0.2 * plain[0]

    def test_partially_valid_blocks_are_left_out(self):
        img1, img2 = periodic_pair()
        ref = float(registration_quality_loss(img1, img2, rect_mask(64, 96, 8, 56, 8, 88)))
        # cut every interior block in half: only blocks whose pixels all stay valid after the
        # 3 x 3 erosion count, so the loss keeps the value of the whole blocks
        v = rect_mask(64, 96, 8, 56, 8, 88)
        v[..., 8:56, 60:] = 0
        assert float(registration_quality_loss(img1, img2, v)) == pytest.approx(ref, abs=1e-9)


class TestMaskedMean:
    def test_definition(self):
        img1 = textured(2, 32, 48, seed=1)
        img2 = torch.roll(img1, (1, 1), dims=(-2, -1))
        v = torch.ones(2, 1, 32, 48, dtype=torch.float64)
        v[0, ..., :, 20:] = 0
        v[1, ..., 3, 3] = 0
        full = torch.ones(2, 1, 4, 6, dtype=torch.bool)
        full[0, ..., :, 2:] = False  # columns 16-23 hold x = 19 (eroded by x = 20): out
        full[1, ..., 0, 0] = False  # the block of the invalid pixel
        per_block = registration_quality_loss(img1, img2, v, reduction="none")
        want = per_block[full].mean()
        torch.testing.assert_close(registration_quality_loss(img1, img2, v), want, rtol=1e-12, atol=0)

    def test_no_mask_equals_mean(self):
        img1 = textured(2, 32, 48, seed=2)
        img2 = torch.roll(img1, 1, dims=-1)
        mean = registration_quality_loss(img1, img2, reduction="mean")
        assert torch.equal(registration_quality_loss(img1, img2), mean)
        ones = torch.ones(2, 1, 32, 48, dtype=torch.float64)
        torch.testing.assert_close(registration_quality_loss(img1, img2, ones), mean, rtol=1e-12, atol=0)

    @pytest.mark.parametrize("reduction", REDUCTIONS)
    def test_no_gradient_reaches_valid(self, reduction):
        img1 = textured(1, 32, 32, seed=3).requires_grad_()
        img2 = torch.roll(img1.detach(), 1, dims=-1)
        valid = torch.ones(1, 1, 32, 32, dtype=torch.float64)
        valid[..., 20:, :] = 0.3  # fractional: binarised at 0.5
        valid.requires_grad_()
        loss = registration_quality_loss(img1, img2, valid, reduction=reduction)
        loss.sum().backward()
        assert valid.grad is None
        assert bool(torch.isfinite(img1.grad).all()) and float(img1.grad.abs().sum()) > 0
        binary = (valid.detach() >= 0.5).double()
        assert torch.equal(loss.detach(), registration_quality_loss(img1.detach(), img2, binary, reduction=reduction))

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_no_valid_block_gives_zero_and_zero_gradient(self, dtype):
        img1 = textured(2, 32, 32, seed=4, dtype=dtype).requires_grad_()
        img2 = torch.roll(img1.detach(), 1, dims=-1)
        # every block holds an invalid pixel, so no block is wholly valid
        scattered = torch.ones(2, 1, 32, 32, dtype=dtype)
        scattered[..., 4::8, 4::8] = 0
        for valid in (torch.zeros(2, 1, 32, 32, dtype=dtype), scattered):
            img1.grad = None
            loss = registration_quality_loss(img1, img2, valid)
            loss.backward()
            assert float(loss.detach()) == 0.0
            assert bool((img1.grad == 0).all())
        assert float(registration_quality_loss(img1, img2, scattered, reduction="mean").detach()) > 0

    def test_padding_blocks_are_invalid(self):
        img1 = textured(1, 37, 61, seed=5)
        img2 = torch.roll(img1, 1, dims=-1)
        per_block = registration_quality_loss(img1, img2, reduction="none")
        assert per_block.shape == (1, 1, 5, 8)
        # whole blocks: rows 0-31 and columns 0-55 (the last row and column of blocks is padded)
        torch.testing.assert_close(
            registration_quality_loss(img1, img2), per_block[..., :4, :7].mean(), rtol=1e-12, atol=0
        )

    def test_reduction_names(self):
        assert REDUCTIONS[0] == "masked_mean"
        assert RegistrationQualityLoss().reduction == "masked_mean"
        assert "masked_mean" in repr(RegistrationQualityLoss())

    @pytest.mark.bad_input
    def test_unknown_reduction(self):
        img = torch.rand(1, 1, 16, 16)
        one_line_error(ValueError, lambda: registration_quality_loss(img, img, reduction="masked"), "masked_mean")
        one_line_error(ValueError, lambda: RegistrationQualityLoss(reduction="avg"), "reduction")


@pytest.mark.bad_input
class TestPairsWithNothingToMeasure:
    """Flat pairs (every valid pixel in the risk map) are left out of the masked mean, as the
    hard metric and the stateful one skip them: they used to count their blocks in the
    denominator (three flat pairs beside a misregistered one: its loss 0.457 read 0.114)."""

    def batch(self, n_flat=3, dtype=torch.float64):
        img1 = textured(1, 64, 64, seed=1, dtype=dtype)
        flat = torch.full((n_flat, 1, 64, 64), 0.5, dtype=dtype)
        return torch.cat([img1, flat]), torch.cat([torch.roll(img1, 1, dims=-1), flat])

    @pytest.mark.parametrize("with_mask", [False, True])
    def test_flat_pairs_do_not_dilute_the_mean(self, with_mask):
        x1, x2 = self.batch()
        valid = torch.ones(4, 1, 64, 64, dtype=torch.float64) if with_mask else None
        alone = float(registration_quality_loss(x1[:1], x2[:1]))
        assert alone > 0.4
        assert float(registration_quality_loss(x1, x2, valid)) == pytest.approx(alone, rel=1e-12)
        per = registration_quality_loss(x1, x2, valid, reduction="per_sample")
        assert float(per[0]) == pytest.approx(alone, rel=1e-12)
        assert per[1:].tolist() == [0.0, 0.0, 0.0]
        # the plain mean keeps its documented meaning: every block counts
        plain = float(registration_quality_loss(x1, x2, valid, reduction="mean"))
        assert plain == pytest.approx(alone / 4, rel=1e-6)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_gradients_are_the_measurable_pairs_alone(self, dtype):
        x1, x2 = self.batch(dtype=dtype)
        x1.requires_grad_()
        registration_quality_loss(x1, x2).backward()
        one = x1.detach()[:1].clone().requires_grad_()
        registration_quality_loss(one, x2[:1]).backward()
        assert bool(torch.isfinite(x1.grad).all())
        torch.testing.assert_close(x1.grad[:1], one.grad)
        assert bool((x1.grad[1:] == 0).all())

    @pytest.mark.parametrize("reduction", ["masked_mean", "per_sample"])
    def test_a_batch_with_nothing_to_measure_gives_zero(self, reduction):
        # the documented rule of a batch with no valid block: 0 and a zero gradient, no NaN
        flat = torch.full((2, 1, 32, 32), 0.5, dtype=torch.float64, requires_grad=True)
        loss = registration_quality_loss(flat, flat.detach() + 0.001, reduction=reduction)
        loss.sum().backward()
        assert loss.detach().tolist() == (0.0 if reduction == "masked_mean" else [0.0, 0.0])
        assert bool((flat.grad == 0).all())


def test_max_pool_block_validity_matches_a_loop():
    """The block validity used by the masked mean, against a loop over blocks."""
    g = torch.Generator().manual_seed(6)
    v = (torch.rand(1, 1, 24, 32, generator=g) > 0.02).double()
    eroded = -F.max_pool2d(-v, 3, 1, 1)
    full = -F.max_pool2d(-eroded, 8, 8)
    for i in range(3):
        for j in range(4):
            assert bool(full[0, 0, i, j] == 1) == bool((eroded[0, 0, 8 * i : 8 * i + 8, 8 * j : 8 * j + 8] == 1).all())
