"""Tests of the registration-quality metric, part 3: modules == functions, the loss's
reductions, inputs (dtypes, channels, bad inputs) and property-based checks."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from kornia.color import rgb_to_grayscale
from metric_helpers import (
    assert_in_floor_range,
    hard_from_pieces,
    spec_reference,
    textured,
    textured_pair,
)
from one_line import one_line_error

from lensdist_torch.metric import (
    QualityConfig,
    RegistrationQuality,
    RegistrationQualityLoss,
    block_counts,
    error_images,
    local_criteria,
    quality_map,
    registration_error_counts,
    registration_quality,
    registration_quality_loss,
)

# ----------------------------------------------------------------------------- modules and the loss


class TestModules:
    def test_module_equals_function(self):
        img1, img2 = textured_pair(2, 16, 24, seed=18)
        valid = torch.ones(2, 1, 16, 24, dtype=torch.float64)
        valid[..., :3] = 0
        cfg = QualityConfig(theta_g=0.03)
        for smooth in (False, True):
            for pixels in (False, True):
                mod = RegistrationQuality(cfg, smooth=smooth, return_pixels=pixels)(img1, img2, valid)
                fun = registration_quality(img1, img2, valid, config=cfg, smooth=smooth, return_pixels=pixels)
                assert torch.equal(mod.registration_map, fun.registration_map)
                assert torch.equal(mod.visual_map, fun.visual_map)
                assert torch.equal(mod.quality_index, fun.quality_index)
                assert (mod.criteria is None) == (not pixels)
        for reduction in ("mean", "sum", "none"):
            mod = RegistrationQualityLoss(cfg, reduction=reduction)(img1, img2, valid)
            fun = registration_quality_loss(img1, img2, valid, config=cfg, reduction=reduction)
            assert torch.equal(mod, fun)
        assert torch.equal(RegistrationQualityLoss()(img1, img2), registration_quality_loss(img1, img2))

    def test_data_range(self):
        img1, img2 = textured_pair(1, 16, 16, seed=19)
        m = quality_map(img1, img2)
        # scaling by 2 is exact in binary, so the maps are identical
        assert torch.equal(quality_map(2 * img1, 2 * img2, data_range=2.0), m)
        assert torch.equal(RegistrationQuality(data_range=2.0)(2 * img1, 2 * img2).registration_map, m)
        assert torch.equal(
            RegistrationQualityLoss(data_range=2.0, reduction="none")(2 * img1, 2 * img2),
            registration_quality_loss(img1, img2, reduction="none"),
        )

    def test_loss_reductions(self):
        img1, img2 = textured_pair(3, 16, 24, seed=20)
        none = registration_quality_loss(img1, img2, reduction="none")
        assert none.shape == (3, 1, 2, 3)
        assert float(none.min()) >= 0 and float(none.max()) <= 1
        torch.testing.assert_close(registration_quality_loss(img1, img2), none.mean())
        torch.testing.assert_close(registration_quality_loss(img1, img2, reduction="sum"), none.sum())
        torch.testing.assert_close(registration_quality_loss(img1, img2, reduction="sum"), none.mean() * 18)
        assert torch.equal(none, registration_quality(img1, img2, smooth=True).registration_map)
        # lower is better: identical images give a loss far below a misregistered pair
        assert float(registration_quality_loss(img1, img1)) < 1e-3 < float(none.mean())

    def test_loss_valid_mask(self):
        img1, img2 = textured_pair(1, 16, 32, seed=21)
        free = registration_quality_loss(img1, img2, reduction="none")
        assert float(registration_quality_loss(img1, img2, torch.zeros(1, 1, 16, 32), reduction="sum")) == 0.0
        valid = torch.ones(1, 1, 16, 32, dtype=torch.float64)
        valid[..., :16] = 0  # block columns 0-1 invalid; erosion also removes x = 16 (column 2)
        masked = registration_quality_loss(img1, img2, valid, reduction="none")
        assert bool((masked[..., :2] == 0).all())
        assert torch.equal(masked[..., 3], free[..., 3])
        assert bool((masked[..., 2] <= free[..., 2] + 1e-12).all())
        x = img1.clone().requires_grad_()
        registration_quality_loss(x, img2, valid).backward()
        assert bool((x.grad[..., :, :14] == 0).all())  # no gradient through invalid pixels' errors


# ----------------------------------------------------------------------------- inputs


def _zeros(dtype):
    return torch.zeros(1, 1, 16, 16, dtype=dtype)


class TestInputs:
    def test_uint8_equals_float(self):
        g = torch.Generator().manual_seed(22)
        u1 = torch.randint(0, 256, (2, 1, 16, 24), generator=g, dtype=torch.uint8)
        u2 = torch.roll(u1, 1, dims=-1)
        f1, f2 = u1.float() / 255, u2.float() / 255
        assert torch.equal(quality_map(u1, u2), quality_map(f1, f2))
        assert torch.equal(registration_quality(u1, u2).visual_map, registration_quality(f1, f2).visual_map)
        assert torch.equal(
            registration_quality_loss(u1, u2, reduction="none"), registration_quality_loss(f1, f2, reduction="none")
        )
        assert float((quality_map(u1, u2) > 0).float().mean()) > 0.5
        # data_range describes float inputs only; uint8 is always / 255 (docs/method.md, section 1)
        assert torch.equal(quality_map(u1, u2, data_range=255.0), quality_map(f1, f2))
        assert torch.equal(quality_map(u1, f2 * 2, data_range=2.0), quality_map(f1, f2))

    def test_rgb_equals_grayscale(self):
        g = torch.Generator().manual_seed(23)
        base = textured(2, 16, 24, seed=24)
        rgb1 = (base + 0.1 * torch.rand(2, 3, 16, 24, generator=g, dtype=torch.float64)).clamp(0, 1)
        rgb2 = torch.roll(rgb1, 1, dims=-2)
        grey1, grey2 = rgb_to_grayscale(rgb1), rgb_to_grayscale(rgb2)
        assert torch.equal(quality_map(rgb1, rgb2), quality_map(grey1, grey2))
        a = registration_quality(rgb1, rgb2, return_pixels=True)
        b = registration_quality(grey1, grey2, return_pixels=True)
        assert torch.equal(a.visual_map, b.visual_map)
        assert torch.equal(a.criteria.a, b.criteria.a)
        ug = torch.randint(0, 256, (1, 3, 8, 8), generator=g, dtype=torch.uint8)
        ug2 = ug.flip(-1)
        want = quality_map(rgb_to_grayscale(ug.float() / 255), rgb_to_grayscale(ug2.float() / 255))
        assert torch.equal(quality_map(ug, ug2), want)

    @pytest.mark.bad_input
    @pytest.mark.parametrize(
        "img1,img2,exc,words",
        [
            (torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 24), ValueError, ["img1", "img2", "same shape"]),
            (torch.rand(1, 16, 16), torch.rand(1, 16, 16), ValueError, ["img1", "(B, C, H, W)"]),
            (torch.rand(1, 1, 1, 16, 16), torch.rand(1, 1, 1, 16, 16), ValueError, ["img1"]),
            (torch.rand(0, 1, 16, 16), torch.rand(0, 1, 16, 16), ValueError, ["img1", "empty"]),
            (torch.rand(1, 2, 16, 16), torch.rand(1, 2, 16, 16), ValueError, ["img1", "channels"]),
            (torch.rand(1, 4, 16, 16), torch.rand(1, 4, 16, 16), ValueError, ["channels"]),
            (_zeros(torch.int32), _zeros(torch.int32), TypeError, ["img1", "int32"]),
            (_zeros(torch.int64), _zeros(torch.int64), TypeError, ["img1", "dtype"]),
            (_zeros(torch.bool), _zeros(torch.bool), TypeError, ["img1"]),
            (torch.rand(1, 1, 16, 16), _zeros(torch.int16), TypeError, ["img2"]),
            (torch.rand(1, 1, 16, 16).numpy(), torch.rand(1, 1, 16, 16), TypeError, ["img1", "Tensor"]),
            (torch.rand(1, 1, 16, 16), [[0.0]], TypeError, ["img2"]),
        ],
    )
    def test_bad_images(self, img1, img2, exc, words):
        for call in (
            lambda: quality_map(img1, img2),
            lambda: registration_quality(img1, img2),
            lambda: registration_quality(img1, img2, smooth=True),
            lambda: registration_quality_loss(img1, img2),
            lambda: local_criteria(img1, img2),
            lambda: registration_error_counts(img1, img2),
        ):
            with pytest.raises(exc) as info:
                call()
            for w in words:
                assert w in str(info.value), (w, str(info.value))

    @pytest.mark.bad_input
    @pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
    @pytest.mark.parametrize("which", ["img1", "img2"])
    def test_non_finite(self, bad, which):
        good = torch.rand(1, 1, 16, 16)
        broken = good.clone()
        broken[0, 0, 3, 4] = bad
        pair = (broken, good) if which == "img1" else (good, broken)
        for call in (quality_map, registration_quality, registration_quality_loss, local_criteria):
            with pytest.raises(ValueError, match=f"{which}.*(NaN|Inf)"):
                call(*pair)

    @pytest.mark.bad_input
    def test_bad_valid_mask(self):
        img = torch.rand(2, 1, 16, 16)
        for shape in ((1, 1, 16, 16), (2, 16, 16), (2, 1, 8, 16), (2, 3, 16, 16)):
            valid = torch.ones(shape)
            for call in (quality_map, registration_quality, registration_quality_loss, registration_error_counts):
                with pytest.raises(ValueError, match="valid"):
                    call(img, img, valid)
            with pytest.raises(ValueError, match="valid"):
                error_images(local_criteria(img, img), valid)
        with pytest.raises(TypeError, match="valid"):
            quality_map(img, img, [[1.0]])

    @pytest.mark.bad_input
    def test_bad_settings(self):
        img = torch.rand(1, 1, 16, 16)
        one_line_error(ValueError, lambda: registration_quality_loss(img, img, reduction="max"), "reduction")
        one_line_error(ValueError, lambda: RegistrationQualityLoss(reduction="avg"), "reduction")
        one_line_error(TypeError, lambda: quality_map(img, img, config={"theta_g": 0.02}), "config")
        for dr in (0, -1.0, "1"):
            one_line_error(ValueError, lambda dr=dr: quality_map(img, img, data_range=dr), "data_range")
        one_line_error(ValueError, lambda: block_counts(torch.zeros(1, 1, 12, 16), 8), "block_size")
        cfg16 = QualityConfig(block_size=16)
        one_line_error(ValueError, lambda: registration_error_counts(img, img, config=cfg16), "block_size")

    @pytest.mark.bad_input
    def test_validate_false_skips_only_the_finite_check(self):
        img = torch.rand(1, 1, 16, 16)
        assert quality_map(img, img, validate=False).shape == (1, 1, 2, 2)
        with pytest.raises(ValueError, match="block_size"):
            quality_map(torch.rand(1, 1, 12, 16), torch.rand(1, 1, 12, 16), validate=False, pad=False)

    def test_bfloat16_input(self):
        x = textured(1, 16, 16, seed=25)
        m = quality_map(x.to(torch.bfloat16), torch.roll(x, 1, -1).to(torch.bfloat16))
        assert m.shape == (1, 1, 2, 2)
        assert_in_floor_range(m.float())

    def test_float16_input(self, scene):
        m = quality_map(scene.half(), scene.half())
        assert bool((m == 0).all())


# ----------------------------------------------------------------------------- properties


@st.composite
def image_pairs(draw):
    b = draw(st.integers(1, 2))
    h = 8 * draw(st.integers(1, 4))
    w = 8 * draw(st.integers(1, 4))
    seed = draw(st.integers(0, 2**31 - 1))
    kind = draw(st.sampled_from(["noise", "texture", "shifted", "dyadic"]))
    g = torch.Generator().manual_seed(seed)
    if kind == "noise":
        scale = draw(st.sampled_from([1.0, 0.1, 0.01]))
        img1 = 0.5 + scale * (torch.rand(b, 1, h, w, generator=g, dtype=torch.float64) - 0.5)
        img2 = 0.5 + scale * (torch.rand(b, 1, h, w, generator=g, dtype=torch.float64) - 0.5)
    elif kind == "texture":
        img1, img2 = textured_pair(b, h, w, seed % 10_000)
    elif kind == "shifted":
        img1 = textured(b, h, w, seed % 10_000)
        img2 = torch.roll(img1, shifts=(draw(st.integers(-2, 2)), draw(st.integers(-2, 2))), dims=(-2, -1))
    else:
        img1 = torch.randint(0, 3, (b, 1, h, w), generator=g).double() / 2
        img2 = torch.randint(0, 3, (b, 1, h, w), generator=g).double() / 2
    valid = None
    if draw(st.booleans()):
        valid = (torch.rand(b, 1, h, w, generator=g) > 0.1).double()
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    return img1.to(dtype), img2.to(dtype), valid


class TestProperties:
    @settings(max_examples=25, deadline=None)
    @given(image_pairs())
    def test_map_range_shape_and_symmetry(self, pair):
        img1, img2, valid = pair
        b, _, h, w = img1.shape
        # validate=False: a drawn pair may have nothing to measure (every pixel at risk): NaN
        res = registration_quality(img1, img2, valid, validate=False)
        for m in (res.registration_map, res.visual_map):
            assert m.shape == (b, 1, h // 8, w // 8)
            assert_in_floor_range(m)
            # every value is a count / 64
            assert torch.equal(m * 64, (m * 64).round())
        q, none = res.quality_index, torch.isnan(res.quality_index)
        assert bool(((q[~none] >= 0) & (q[~none] <= 1)).all())
        assert float(res.registration_map[none].sum()) == 0  # nothing measured, no error seen
        # symmetric: D, |dot|, |cross|, the product of the two risk tests and V do not depend
        # on the order of the images (cross only changes sign, exactly, in IEEE arithmetic)
        swapped = registration_quality(img2, img1, valid, validate=False)
        assert torch.equal(torch.isnan(swapped.quality_index), none)
        assert torch.equal(swapped.registration_map, res.registration_map)
        assert torch.equal(swapped.visual_map, res.visual_map)
        assert torch.equal(quality_map(img1, img2, valid), res.registration_map)
        reg, vis, _ = hard_from_pieces(img1, img2, valid)
        assert torch.equal(reg, res.registration_map) and torch.equal(vis, res.visual_map)

    @settings(max_examples=25, deadline=None)
    @given(image_pairs())
    def test_smooth_map_range_and_identity(self, pair):
        img1, img2, valid = pair
        smooth = registration_quality_loss(img1, img2, valid, reduction="none")
        assert bool(torch.isfinite(smooth).all())
        assert float(smooth.min()) >= 0 and float(smooth.max()) <= 1
        swapped = registration_quality_loss(img2, img1, valid, reduction="none")
        torch.testing.assert_close(swapped, smooth, atol=1e-12, rtol=0)
        assert bool((quality_map(img1, img1, valid) == 0).all())

    @settings(max_examples=25, deadline=None)
    @given(image_pairs())
    def test_matches_spec_reference(self, pair):
        img1, img2, valid = pair
        img1, img2 = img1.double(), img2.double()
        ref = spec_reference(img1, img2, valid)
        # validate=False: the maps exist also for a pair with nothing to measure (all at risk)
        res = registration_quality(img1, img2, valid, validate=False)
        # float64, exact formulas: the only possible disagreement is a pixel within rounding of
        # a threshold; allow one differing block in the rare case it happens
        assert int((res.registration_map != ref["reg"]).sum()) <= 1
        assert int((res.visual_map != ref["vis"]).sum()) <= 1
