"""A pair with nothing to measure (issue 19, item 8): no pixel of the mask valid after its 3 x 3
erosion, or every valid pixel in the risk map (both images flat: no edge whose orientation could
disagree). Its quality index must never read 1.0 (perfect): ``registration_quality`` raises naming
``valid`` or the images (NaN with ``validate=False``), the stateful metric skips the pair and counts it, and
the loss gives 0 with a zero gradient for such a batch (documented: a loss must not poison the
weights, and the masked mean leaves an empty sample out of the batch's mean)."""

from __future__ import annotations

import math

import pytest
import torch
from metric_helpers import textured

from lensdist_torch import RegistrationQuality, registration_quality, registration_quality_loss
from lensdist_torch.metric.stateful import RegistrationQualityMetric


def misregistered(b: int = 3, h: int = 32, w: int = 40, seed: int = 0):
    """b pairs shifted by 1-2 px: quality indices well below 1."""
    img1 = textured(b, h, w, seed=seed, dtype=torch.float32)
    img2 = torch.stack([torch.roll(img1[i], (1 + i % 2, 1), dims=(-2, -1)) for i in range(b)])
    return img1, img2


def index_of(img1, img2, valid=None) -> list[float]:
    return registration_quality(img1, img2, valid).quality_index.tolist()


ENTRY_POINTS = {
    "hard": lambda a, b, v, **k: registration_quality(a, b, v, **k).quality_index,
    "smooth": lambda a, b, v, **k: registration_quality(a, b, v, smooth=True, **k).quality_index,
    "pixels": lambda a, b, v, **k: registration_quality(a, b, v, return_pixels=True, **k).quality_index,
    "module": lambda a, b, v, **k: RegistrationQuality(**k)(a, b, v).quality_index,
}


class TestRegistrationQuality:
    @pytest.mark.bad_input
    @pytest.mark.parametrize("path", sorted(ENTRY_POINTS))
    def test_an_empty_mask_is_an_error_not_a_perfect_pair(self, path):
        img1, img2 = misregistered(1)
        valid = torch.zeros(1, 1, 32, 40)
        with pytest.raises(ValueError, match=r"^valid leaves no pixel to measure in the pair") as info:
            ENTRY_POINTS[path](img1, img2, valid)
        assert "\n" not in str(info.value)
        for mask in (valid.bool(), valid.to(torch.uint8), torch.full((1, 1, 32, 40), 0.49)):  # below 0.5
            with pytest.raises(ValueError, match="valid leaves no pixel"):
                ENTRY_POINTS[path](img1, img2, mask)

    @pytest.mark.bad_input
    def test_the_message_names_the_empty_sample(self):
        img1, img2 = misregistered(4)
        valid = torch.ones(4, 1, 32, 40)
        valid[2] = 0
        with pytest.raises(ValueError, match=r"valid leaves no pixel to measure in sample \[2\] of the batch of 4"):
            registration_quality(img1, img2, valid)

    @pytest.mark.bad_input
    def test_what_the_erosion_leaves(self):
        """A stripe two pixels wide leaves nothing after the 3 x 3 erosion; three pixels leave one line."""
        img1, img2 = misregistered(1)
        two = torch.zeros(1, 1, 32, 40)
        two[..., 10:12, :] = 1
        with pytest.raises(ValueError, match="valid leaves no pixel"):
            registration_quality(img1, img2, two)
        three = torch.zeros(1, 1, 32, 40)
        three[..., 10:13, :] = 1
        q = index_of(img1, img2, three)[0]
        assert 0.0 < q <= 1.0
        # on the image border the outside counts as valid: one row along the top edge is enough
        # for the eroded mask to keep row 0
        top = torch.zeros(1, 1, 32, 40)
        top[..., :2, :] = 1
        assert not math.isnan(index_of(img1, img2, top)[0])

    @pytest.mark.bad_input
    def test_an_image_of_one_row_names_img1(self):
        x = textured(1, 8, 40, seed=1, dtype=torch.float32)
        for a in (x[..., :1, :], x[..., :, :1].contiguous()):
            with pytest.raises(ValueError, match=r"^img1 is too small to measure.*2 x 2"):
                registration_quality(a, a.flip(-1))
        # two rows are enough
        assert index_of(x[..., :2, :], x[..., :2, :]) == [1.0]

    @pytest.mark.bad_input
    @pytest.mark.parametrize("path", sorted(ENTRY_POINTS))
    def test_validate_false_gives_nan_for_the_empty_sample_only(self, path):
        img1, img2 = misregistered(3)
        valid = torch.ones(3, 1, 32, 40)
        valid[..., :, : 20] = 0  # half the frame: still measured
        valid[1] = 0
        got = ENTRY_POINTS[path](img1, img2, valid, validate=False)
        assert math.isnan(float(got[1]))
        for i in (0, 2):  # the others exactly as on their own
            alone = ENTRY_POINTS[path](img1[i : i + 1], img2[i : i + 1], valid[i : i + 1])
            assert float(got[i]) == float(alone[0])
            assert 0.0 < float(got[i]) < 1.0

    def test_a_full_or_absent_mask_is_unchanged(self):
        img1, img2 = misregistered(2, 37, 45)  # padded to whole blocks
        ones = torch.ones(2, 1, 37, 45)
        assert index_of(img1, img2, ones) == index_of(img1, img2)
        res = registration_quality(img1, img2)
        assert res.quality_index.tolist() == (1.0 - res.registration_map.mean(dim=(1, 2, 3))).tolist()


class TestStatefulMetric:
    def _pairs(self):
        """Two measured pairs (the second half masked) and one pair with an empty mask."""
        img1, img2 = misregistered(3)
        valid = torch.ones(3, 1, 32, 40)
        valid[1, ..., :, 20:] = 0
        valid[2] = 0
        return img1, img2, valid

    @pytest.mark.bad_input
    @pytest.mark.parametrize("validate", [True, False])
    def test_an_empty_pair_is_skipped_and_counted(self, validate):
        img1, img2, valid = self._pairs()
        q0 = index_of(img1[:1], img2[:1], valid[:1])[0]
        q1 = index_of(img1[1:2], img2[1:2], valid[1:2])[0]
        assert 0.2 < q0 < 0.9 and 0.2 < q1 < 0.9  # a real mean, far from 1
        metric = RegistrationQualityMetric(validate=validate)
        for i in range(3):
            metric.update(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1])
        res = metric.compute_details()
        assert int(res.num_pairs) == 2 and int(res.num_skipped) == 1
        assert abs(float(res.quality_index) - (q0 + q1) / 2) < 1e-7  # not (q0 + q1 + 1) / 3
        # the same in one batch, and in the mean map
        batch = RegistrationQualityMetric(validate=validate)
        batch.update(img1, img2, valid)
        one = batch.compute_details()
        assert int(one.num_pairs) == 2 and int(one.num_skipped) == 1
        torch.testing.assert_close(one.quality_index, res.quality_index, atol=1e-12, rtol=0)
        maps = registration_quality(img1[:2], img2[:2], valid[:2]).registration_map.double()
        torch.testing.assert_close(one.registration_map, maps.mean(dim=0), atol=1e-12, rtol=0)

    @pytest.mark.bad_input
    def test_a_batch_of_empty_pairs_only(self):
        img1, img2, valid = self._pairs()
        metric = RegistrationQualityMetric()
        out = metric(img1[2:], img2[2:], valid[2:])
        assert out.shape == () and math.isnan(float(out))  # the batch's index: nothing measured
        assert int(metric.num_pairs) == 0 and int(metric.num_skipped) == 1
        with pytest.raises(RuntimeError, match="1 pair.*nothing to measure"):
            metric.compute()
        metric.update(img1[:1], img2[:1], valid[:1])
        res = metric.compute_details()
        assert float(res.quality_index) == pytest.approx(index_of(img1[:1], img2[:1], valid[:1])[0], abs=1e-7)
        metric.reset()
        assert int(metric.num_skipped) == 0


def flat(b: int = 1, h: int = 32, w: int = 40, level: float = 0.5) -> torch.Tensor:
    return torch.full((b, 1, h, w), level)


class TestFlatImages:
    """Every valid pixel at risk (both gradients <= theta_G nearby): nothing to measure. An edge
    against a vanishing gradient is an error (docs/method.md, section 2), not a perfect pixel."""

    @pytest.mark.bad_input
    @pytest.mark.parametrize("path", sorted(ENTRY_POINTS))
    def test_two_flat_images_have_no_index(self, path):
        # identical, and two different grey levels (a visual error, no edge to compare)
        for a, b in ((flat(), flat()), (flat(), flat(level=0.8))):
            with pytest.raises(ValueError, match=r"^img1 and img2 leave no edge to measure in the pair") as info:
                ENTRY_POINTS[path](a, b, None)
            assert "\n" not in str(info.value)
            assert math.isnan(float(ENTRY_POINTS[path](a, b, None, validate=False)[0]))

    @pytest.mark.bad_input
    def test_weak_texture_below_theta_g_is_flat_too(self):
        # a ramp of 0.01 per pixel: normalised Sobel G = 0.01 <= theta_G = 0.02 everywhere
        ramp = (torch.arange(40.0) * 0.01)[None, None, None, :].expand(1, 1, 32, 40).contiguous()
        with pytest.raises(ValueError, match="no edge to measure"):
            registration_quality(ramp, ramp.flip(-1))
        # 0.03 per pixel is above theta_G: measured, and the opposite ramps agree axially
        steep = ramp * 3 / 1.2
        assert index_of(steep, steep.flip(-1)) == [1.0]

    @pytest.mark.bad_input
    @pytest.mark.parametrize("path", sorted(ENTRY_POINTS))
    def test_texture_against_a_flat_image_is_an_error(self, path):
        img1, _ = misregistered(1)
        for a, b in ((img1, flat()), (flat(), img1)):
            q = float(ENTRY_POINTS[path](a, b, None)[0])
            # about a third of the texture is weak (in the risk map); every other pixel is an
            # error: far from the 1.0 a zero vector used to give
            assert q < 0.4, (path, q)
            res = registration_quality(a, b, return_pixels=True)
            assert torch.equal(res.errors.e_reg, 1 - res.criteria.r)  # every risk-free pixel errs
            c = res.criteria  # A = 0 wherever the texture has a gradient (its flat patch: A = 1)
            assert float(c.a[(c.g1 + c.g2) > 0].max()) == 0.0 and float(c.a[(c.g1 + c.g2) == 0].min()) == 1.0

    @pytest.mark.bad_input
    def test_the_message_names_the_flat_sample_and_the_metric_skips_it(self):
        img1, img2 = misregistered(3)
        img1[1], img2[1] = 0.3, 0.3
        with pytest.raises(ValueError, match=r"no edge to measure in sample \[1\] of the batch of 3"):
            registration_quality(img1, img2)
        q = registration_quality(img1, img2, validate=False).quality_index
        assert math.isnan(float(q[1])) and 0.2 < float(q[0]) < 0.9 and 0.2 < float(q[2]) < 0.9
        metric = RegistrationQualityMetric()
        metric.update(img1, img2)
        res = metric.compute_details()
        assert int(res.num_pairs) == 2 and int(res.num_skipped) == 1
        assert float(res.quality_index) == pytest.approx((float(q[0]) + float(q[2])) / 2, abs=1e-7)

    @pytest.mark.bad_input
    def test_a_metric_of_flat_pairs_only_says_so(self):
        # the third issue-19 audit: the message named only the mask, which was full
        metric = RegistrationQualityMetric()
        metric.update(flat(), flat())
        with pytest.raises(RuntimeError, match=r"1 pair\(s\) added had nothing to measure .*flat images"):
            metric.compute()

    def test_a_flat_half_is_still_measured(self):
        # sky above, texture below: the texture's pixels are measured, the sky's are not errors
        img1, img2 = misregistered(1)
        a, b = img1.clone(), img1.clone()
        a[..., :16, :], b[..., :16, :] = 0.7, 0.7
        assert index_of(a, b) == [1.0]
        c = b.clone()
        c[..., 16:, :] = img2[..., 16:, :]
        assert index_of(a, c)[0] < index_of(img1, img2)[0] + 0.5 * (1 - index_of(img1, img2)[0])


class TestLoss:
    """The loss keeps its documented contract: an empty sample adds no block to the masked
    mean, and a batch with no valid block gives 0 with a zero gradient."""

    @pytest.mark.bad_input
    def test_an_empty_sample_leaves_the_masked_mean_of_the_others(self):
        img1, img2 = misregistered(2)
        valid = torch.ones(2, 1, 32, 40)
        valid[1] = 0
        x = img1.clone().requires_grad_()
        both = registration_quality_loss(x, img2, valid)
        alone = registration_quality_loss(img1[:1], img2[:1], valid[:1])
        assert float(alone) > 0.05
        torch.testing.assert_close(both.detach(), alone, atol=1e-7, rtol=0)
        both.backward()
        assert bool((x.grad[1] == 0).all()) and bool(x.grad[0].abs().sum() > 0)
        # "mean" counts the empty sample's blocks as error-free: half the loss (documented)
        mean = registration_quality_loss(img1, img2, valid, reduction="mean")
        torch.testing.assert_close(mean, alone / 2, atol=1e-7, rtol=0)
