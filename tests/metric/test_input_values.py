"""Inputs of any size (padded to whole blocks), the value range of float images (data_range),
and the values of the validity mask."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from metric_helpers import ENTRY_POINTS, textured
from one_line import one_line_error

from lensdist_torch import quality_map, registration_quality, registration_quality_loss
from lensdist_torch.metric import error_images, local_criteria, registration_error_counts
from lensdist_torch.metric.loss import OVERSHOOT
from lensdist_torch.metric.stateful import RegistrationQualityMetric

#: The loss's entry points: they take an interpolating warp's overshoot (``metric.loss.OVERSHOOT``).
LOSSES = ("registration_quality_loss", "RegistrationQualityLoss")


def _entry_points(img1, img2, valid=None, *, losses=True, **kw):
    """Every entry point that takes a pair and a mask, but the per-pixel variant, as zero-argument calls.

    ``losses`` False: the loss's entry points left out (values within their overshoot)."""
    return [
        lambda call=call: call(img1, img2, valid, **kw)
        for name, call in ENTRY_POINTS.items()
        if name not in ("local_criteria", "registration_quality pixels") and (losses or name not in LOSSES)
    ]




# ----------------------------------------------------------------------------- any image size


class TestPadding:
    def _by_hand(self, img1, img2, valid=None):
        """37 x 61 -> 40 x 64 by hand: replicate the images, the padding invalid."""
        p1 = F.pad(img1, (0, 3, 0, 3), mode="replicate")
        p2 = F.pad(img2, (0, 3, 0, 3), mode="replicate")
        v = torch.ones_like(img1) if valid is None else valid
        return p1, p2, F.pad(v, (0, 3, 0, 3), value=0.0)

    @pytest.mark.parametrize("with_mask", [False, True])
    def test_37_by_61_equals_padding_by_hand(self, with_mask):
        big1 = textured(2, 40, 64, seed=1)
        big2 = 0.8 * torch.roll(big1, (1, 1), dims=(-2, -1)) + 0.2 * textured(2, 40, 64, seed=2)
        img1, img2 = big1[..., :37, :61], big2[..., :37, :61]
        valid = None
        if with_mask:
            valid = torch.ones(2, 1, 37, 61, dtype=torch.float64)
            valid[0, ..., 10:20, 30:] = 0
        p1, p2, pv = self._by_hand(img1, img2, valid)
        got = quality_map(img1, img2, valid)
        assert got.shape == (2, 1, 5, 8)  # ceil(37 / 8) x ceil(61 / 8)
        assert torch.equal(got, quality_map(p1, p2, pv, pad=False))
        assert float(got.sum()) > 0
        assert torch.equal(
            registration_error_counts(img1, img2, valid), registration_error_counts(p1, p2, pv, pad=False)
        )
        res, ref = registration_quality(img1, img2, valid), registration_quality(p1, p2, pv, pad=False)
        for a, b in zip(res, ref):
            if a is not None:
                assert torch.equal(a, b)
        smooth = registration_quality(img1, img2, valid, smooth=True)
        assert torch.equal(
            smooth.registration_map, registration_quality(p1, p2, pv, smooth=True, pad=False).registration_map
        )
        for reduction in ("none", "masked_mean", "mean", "sum"):
            assert torch.equal(
                registration_quality_loss(img1, img2, valid, reduction=reduction),
                registration_quality_loss(p1, p2, pv, reduction=reduction, pad=False),
            )

    def test_per_pixel_maps_keep_the_input_size(self):
        img1 = textured(1, 37, 61, seed=3)
        img2 = torch.roll(img1, 1, dims=-1)
        res = registration_quality(img1, img2, return_pixels=True)
        assert res.registration_map.shape == (1, 1, 5, 8)
        assert res.criteria.e.shape == res.errors.e_reg.shape == (1, 1, 37, 61)
        # the criteria do not depend on the padding (replicate padding = replicate border)
        crit = local_criteria(img1, img2)
        assert torch.equal(res.criteria.a, crit.a) and torch.equal(res.criteria.g1, crit.g1)
        # the hard pieces on the padded pair give the same map
        p1, p2, pv = self._by_hand(img1, img2)
        assert torch.equal(res.registration_map, quality_map(p1, p2, pv, pad=False))

    def test_multiples_of_the_block_are_not_padded(self):
        img1 = textured(1, 32, 48, seed=4)
        img2 = torch.roll(img1, 1, dims=-2)
        assert torch.equal(quality_map(img1, img2), quality_map(img1, img2, pad=False))

    def test_tiny_images(self):
        for h, w in ((1, 1), (3, 5), (8, 9)):
            img = torch.rand(1, 1, h, w)
            assert quality_map(img, img).shape == (1, 1, -(-h // 8), -(-w // 8))
            assert float(registration_quality_loss(img, img)) < 1e-3

    @pytest.mark.bad_input
    @pytest.mark.parametrize("size", [(12, 16), (16, 20), (37, 61)])
    def test_strict_mode_keeps_the_old_error(self, size):
        img = torch.rand(1, 1, *size)
        for call in _entry_points(img, img, pad=False):
            with pytest.raises(ValueError, match=f"block_size=8.*{size[0]} x {size[1]}"):
                call()


# ----------------------------------------------------------------------------- data_range


class TestDataRange:
    @pytest.mark.bad_input
    def test_0_255_floats_without_data_range(self):
        img1 = torch.rand(1, 1, 16, 16)
        img1[0, 0, 0, 0] = 1.0
        img2 = torch.roll(img1, 1, dims=-1)
        for which, pair in (("img1", (255 * img1, img2)), ("img2", (img1, 255 * img2))):
            for call in _entry_points(*pair):
                with pytest.raises(ValueError) as info:
                    call()
                msg = str(info.value)
                assert msg == f"{which} has values up to 255.0; expected [0, 1] — pass data_range=255", msg
        want = quality_map(img1, img2)
        assert torch.equal(quality_map(255 * img1, 255 * img2, data_range=255), want)

    @pytest.mark.bad_input
    @pytest.mark.parametrize(
        "scale,shift,data_range,words",
        [
            (1.0, -0.5, 1.0, ["img1", "down to -0.5", "non-negative"]),  # mean-subtracted
            (2.0, 0.0, 1.0, ["img1", "up to 2.0", "data_range"]),
            (65535.0, 0.0, 1.0, ["img1", "data_range=65535"]),
            (300.0, 0.0, 255.0, ["img1", "[0.0, 300.0]", "data_range=255.0"]),
            (1.0, -5.0, 255.0, ["img1", "-5.0", "data_range"]),  # tolerance 1 % of 255
        ],
    )
    def test_out_of_range(self, scale, shift, data_range, words):
        img = torch.zeros(1, 1, 16, 16)
        img[..., 0, 0] = 1.0
        bad = scale * img + shift
        good = torch.zeros(1, 1, 16, 16)
        beyond = float(bad.max()) > (1 + OVERSHOOT) * data_range or float(bad.min()) < -OVERSHOOT * data_range
        for call in _entry_points(bad, good, data_range=data_range, losses=beyond):
            one_line_error(ValueError, call, *words)
        with pytest.raises(ValueError, match="img1"):
            local_criteria(bad, good, data_range=data_range)

    def test_tolerance_and_uint8(self):
        img = torch.rand(1, 1, 16, 16)
        # interpolation overshoot and rounding stay within the 1 % tolerance
        assert quality_map(img * 1.005, img - 0.005).shape == (1, 1, 2, 2)
        # uint8 is divided by 255 exactly once, whatever data_range says about float inputs
        u = (img * 255).round().to(torch.uint8)
        f = u.float() / 255
        assert torch.equal(quality_map(u, u.roll(1, -1), data_range=255.0), quality_map(f, f.roll(1, -1)))
        assert torch.equal(quality_map(u, 255 * f.roll(1, -1), data_range=255.0), quality_map(f, f.roll(1, -1)))

    @pytest.mark.bad_input
    def test_non_positive_data_range(self):
        img = torch.rand(1, 1, 16, 16)
        for dr in (0, -1.0, float("nan"), float("inf"), True, "255"):
            with pytest.raises(ValueError, match="data_range"):
                quality_map(img, img, data_range=dr)
            with pytest.raises(ValueError, match="data_range"):
                RegistrationQualityMetric(data_range=dr)


# ----------------------------------------------------------------------------- the mask


class TestMaskValues:
    @pytest.mark.bad_input
    @pytest.mark.parametrize(
        "value,words",
        [
            (float("nan"), ["valid", "NaN"]),
            (float("inf"), ["valid", "Inf"]),
            (255.0, ["valid", "255.0", "[0, 1]"]),
            (2.0, ["valid", "[0, 1]"]),
            (-1.0, ["valid", "-1.0"]),
        ],
    )
    def test_bad_values(self, value, words):
        img = torch.rand(2, 1, 16, 16)
        valid = torch.ones(2, 1, 16, 16)
        valid[1, 0, 3, 4] = value
        calls = _entry_points(img, img, valid) + [lambda: error_images(local_criteria(img, img), valid)]
        for call in calls:
            one_line_error(ValueError, call, *words)
        assert quality_map(img, img, valid, validate=False).shape == (2, 1, 2, 2)

    @pytest.mark.bad_input
    def test_uint8_0_255_mask(self):
        img = torch.rand(1, 1, 16, 16)
        mask = torch.full((1, 1, 16, 16), 255, dtype=torch.uint8)
        with pytest.raises(ValueError, match="valid has values in"):
            quality_map(img, img, mask)

    def test_fractional_masks_are_binarised_at_half(self):
        img1 = textured(1, 32, 32, seed=5)
        img2 = torch.roll(img1, 1, dims=-1)
        g = torch.Generator().manual_seed(6)
        frac = torch.rand(1, 1, 32, 32, generator=g, dtype=torch.float64)
        frac[..., :4, :] = 0.5  # exactly 0.5 is valid
        binary = (frac >= 0.5).double()
        assert torch.equal(quality_map(img1, img2, frac), quality_map(img1, img2, binary))
        assert torch.equal(quality_map(img1, img2, frac), quality_map(img1, img2, frac >= 0.5))  # bool
        for reduction in ("none", "masked_mean"):
            assert torch.equal(
                registration_quality_loss(img1, img2, frac, reduction=reduction),
                registration_quality_loss(img1, img2, binary, reduction=reduction),
            )
        smooth = registration_quality(img1, img2, frac, smooth=True, return_pixels=True)
        crit = local_criteria(img1, img2, smooth=True)
        assert torch.equal(smooth.errors.e_reg, error_images(crit, binary, smooth=True).e_reg)
        # integer 0/1 masks are fine too
        assert torch.equal(quality_map(img1, img2, binary.long()), quality_map(img1, img2, binary))

    def test_mask_within_tolerance(self):
        img = torch.rand(1, 1, 16, 16)
        valid = torch.ones(1, 1, 16, 16) + 1e-6  # a warped mask's rounding
        valid[..., 0, 0] = -1e-7
        assert quality_map(img, img, valid).shape == (1, 1, 2, 2)
