"""Tests of the registration-quality metric (docs/method.md, sections 2-5), part 1: smoke,
cardinality, values worked out by hand, agreement with a literal transcription of the method,
orientation and the risk map. Part 2 (test_quality_paths.py): validity, floor, invariances,
fast path, smooth -> hard, consistency; part 3 (test_quality_inputs.py): modules, inputs and
properties. The structure follows kornia's test classes. Gradients: test_quality_gradients.py.
"""

from __future__ import annotations

import math

import pytest
import torch
from kornia.filters import spatial_gradient
from metric_helpers import (
    CFG,
    HALF_PI,
    angle_ramp,
    spec_reference,
    textured,
    textured_pair,
    x_ramp,
)

from lensdist_torch import (
    QualityConfig,
    RegistrationQuality,
    RegistrationQualityLoss,
    quality_map,
    registration_quality,
    registration_quality_loss,
)
from lensdist_torch.metric import error_images, local_criteria, registration_error_counts

# ----------------------------------------------------------------------------- smoke, cardinality


class TestSmoke:
    @pytest.mark.parametrize("b,h,w", [(1, 8, 8), (2, 16, 24), (3, 32, 8)])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_cardinality(self, b, h, w, dtype):
        img1, img2 = textured_pair(b, h, w, seed=1, dtype=dtype)
        res = registration_quality(img1, img2, return_pixels=True)
        assert res.registration_map.shape == (b, 1, h // 8, w // 8)
        assert res.visual_map.shape == (b, 1, h // 8, w // 8)
        assert res.quality_index.shape == (b,)
        assert res.registration_map.dtype == dtype
        for t in (*res.criteria, *res.errors):
            assert t.shape == (b, 1, h, w) and t.dtype == dtype
        assert quality_map(img1, img2).shape == (b, 1, h // 8, w // 8)
        counts = registration_error_counts(img1, img2)
        assert counts.shape == (b, 1, h // 8, w // 8) and counts.dtype == torch.uint8
        loss = registration_quality_loss(img1, img2)
        assert loss.shape == () and loss.dtype == dtype
        assert registration_quality_loss(img1, img2, reduction="none").shape == (b, 1, h // 8, w // 8)

    def test_block_size_changes_cardinality(self):
        img1, img2 = textured_pair(2, 24, 36, seed=2)
        cfg = QualityConfig(block_size=12)
        assert quality_map(img1, img2, config=cfg).shape == (2, 1, 2, 3)
        assert registration_quality_loss(img1, img2, config=cfg, reduction="none").shape == (2, 1, 2, 3)

    def test_module_repr(self):
        assert "smooth=True" in repr(RegistrationQuality(smooth=True))
        assert "reduction='sum'" in repr(RegistrationQualityLoss(reduction="sum"))


# ----------------------------------------------------------------------------- a hand-worked example
#
# 16 x 16, four 8 x 8 blocks. img1 = 0.25 + a(x) / 16 varies along x only, img2 = 0.25 + d(y) / 16
# along y only; all values are multiples of 1/16, so every number below is exact in binary.
#
#   x or y     0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15
#   a(x)       0 0 0 1 2 3 3 3 3 3  3  4  4  4  4  4      (a ramp at x = 2..5, a step at 10|11)
#   d(y)       0 0 0 0 0 1 2 3 4 5  6  7  8  8  8  8      (a ramp at y = 4..12)
#
# Normalised Sobel = kernel / 8 with replicate border. For an image constant along y the
# [1, 2, 1] smoothing sums to 4, so s_x(x) = 4 (I(x+1) - I(x-1)) / 8 = (I(x+1) - I(x-1)) / 2
# (I(-1) = I(0), I(16) = I(15)) and s_y = 0 exactly. In units of 1/32:
#   G1 = |s_x1|   per column x: 0 0 1 2 2 1 0 0 0 0 1 1 0 0 0 0
#   G2 = |s_y2|   per row    y: 0 0 0 0 1 2 2 2 2 2 2 2 1 0 0 0
# theta_G = 0.02 < 1/32 = 0.03125, so the structured columns are Cx = {2, 3, 4, 5, 10, 11}
# and the structured rows are Ry = {4, ..., 12}.
#
# A: where both gradients are non-zero (x in Cx, y in Ry) they are perpendicular: dot = 0,
#    cross != 0, dalpha = pi / 2, A = 0. Where exactly one is the zero vector it has no
#    orientation to agree with: A = 0 too (docs/method.md, section 2). Where both vanish
#    (x not in Cx, y not in Ry) u1 = u2 = 0, dalpha = 0.5 atan2(0, 0) = 0, A = 1.
#    So A = 0 exactly where x in Cx or y in Ry.
# E = gamma / (1 + exp(k (A - sigma))): E(0) = 0.9879 / (1 + e^17.6) ~ 2e-8, E(1) ~ 0.976.
# R0 = [x not in Cx and y not in Ry]. A pixel escapes the 3 x 3 dilation iff all its
#    neighbours are structured, i.e. iff its three columns lie in Cx (x in {3, 4}) or its
#    three rows lie in Ry (y in {5, ..., 11}). So R = [x not in {3, 4}] * [y not in {5..11}].
# e_reg = (1 - R) [E < 0.5] = [x in {3, 4} or y in {5..11}] (a risk-free pixel always has
#    x in Cx or y in Ry, so A = 0 there):
#    TL (rows 0-7, cols 0-7): cols 3, 4 (16) + rows 5-7, the other six cols (18)       = 34
#    TR (rows 0-7, cols 8-15): rows 5-7 (24)                                           = 24
#    BL (rows 8-15, cols 0-7): cols 3, 4 (16) + rows 8-11, the other six cols (24)     = 40
#    BR (rows 8-15, cols 8-15): rows 8-11 (32)                                         = 32
# e_vis = R [D > 0.1], D = |a(x) - d(y)| / 16: 1/16 = 0.0625 is below 0.1, 2/16 is above,
#    so D > 0.1 iff |a - d| >= 2 units. R = 1 only on rows 0-4 (d = 0) and 12-15 (d = 8),
#    columns other than 3 and 4:
#    TL: rows 0-4, cols {0,1,2,5,6,7}: a = 0 0 0 3 3 3 -> cols 5-7       -> 3 x 5 = 15
#    TR: rows 0-4, cols 8-15: a >= 3 everywhere                          -> 8 x 5 = 40
#    BL: rows 12-15, cols {0,1,2,5,6,7}: |a - 8| >= 5                     -> 6 x 4 = 24
#    BR: rows 12-15, cols 8-15: |a - 8| >= 4                              -> 8 x 4 = 32

A_UNITS = [0, 0, 0, 1, 2, 3, 3, 3, 3, 3, 3, 4, 4, 4, 4, 4]
D_UNITS = [0, 0, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 8, 8, 8]
G1_COLS_32 = [0, 0, 1, 2, 2, 1, 0, 0, 0, 0, 1, 1, 0, 0, 0, 0]
G2_ROWS_32 = [0, 0, 0, 0, 1, 2, 2, 2, 2, 2, 2, 2, 1, 0, 0, 0]
CX = [2, 3, 4, 5, 10, 11]
RY = list(range(4, 13))
RISK_FREE_COLS = [3, 4]
RISK_FREE_ROWS = list(range(5, 12))
HAND_REG_COUNTS = [[34, 24], [40, 32]]
HAND_REG_MAP = [[34 / 64, 24 / 64], [40 / 64, 32 / 64]]
HAND_VIS_MAP = [[15 / 64, 40 / 64], [24 / 64, 32 / 64]]


def hand_pair(dtype=torch.float64):
    a = torch.tensor(A_UNITS, dtype=dtype) / 16
    d = torch.tensor(D_UNITS, dtype=dtype) / 16
    img1 = (0.25 + a)[None, :].expand(16, 16)[None, None].clone()
    img2 = (0.25 + d)[:, None].expand(16, 16)[None, None].clone()
    return img1, img2


def indicator(indices, n=16, dtype=torch.float64):
    v = torch.zeros(n, dtype=dtype)
    v[indices] = 1
    return v


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
class TestHandWorked:
    def test_criteria(self, dtype):
        img1, img2 = hand_pair(dtype)
        c = local_criteria(img1, img2)
        g1 = (torch.tensor(G1_COLS_32, dtype=dtype) / 32)[None, :].expand(16, 16)
        g2 = (torch.tensor(G2_ROWS_32, dtype=dtype) / 32)[:, None].expand(16, 16)
        assert torch.equal(c.g1[0, 0], g1)
        assert torch.equal(c.g2[0, 0], g2)
        a_units = torch.tensor(A_UNITS, dtype=dtype)[None, :]
        d_units = torch.tensor(D_UNITS, dtype=dtype)[:, None]
        assert torch.equal(c.d[0, 0], (a_units - d_units).abs() / 16)
        neither = (1 - indicator(RY, dtype=dtype))[:, None] * (1 - indicator(CX, dtype=dtype))[None, :]
        torch.testing.assert_close(c.a[0, 0], neither, atol=1e-6, rtol=0)
        assert float(c.e[0, 0][neither == 0].max()) < 1e-7  # E(A=0) ~ 2.2e-8
        e_one = c.e[0, 0][neither == 1]
        torch.testing.assert_close(e_one, torch.full_like(e_one, 0.97592), atol=1e-5, rtol=0)
        risky_rows = 1 - indicator(RISK_FREE_ROWS, dtype=dtype)
        risky_cols = 1 - indicator(RISK_FREE_COLS, dtype=dtype)
        r = risky_rows[:, None] * risky_cols[None, :]
        assert torch.equal(c.r[0, 0], r)

    def test_error_images(self, dtype):
        img1, img2 = hand_pair(dtype)
        errs = error_images(local_criteria(img1, img2))
        risky_rows = 1 - indicator(RISK_FREE_ROWS, dtype=dtype)
        risky_cols = 1 - indicator(RISK_FREE_COLS, dtype=dtype)
        free = 1 - risky_rows[:, None] * risky_cols[None, :]
        assert torch.equal(errs.e_reg[0, 0], free)
        a_units = torch.tensor(A_UNITS, dtype=dtype)[None, :]
        d_units = torch.tensor(D_UNITS, dtype=dtype)[:, None]
        assert torch.equal(errs.e_vis[0, 0], (1 - free) * ((a_units - d_units).abs() >= 2).to(dtype))

    def test_block_ratios_and_floor(self, dtype):
        img1, img2 = hand_pair(dtype)
        want_reg = torch.tensor(HAND_REG_MAP, dtype=dtype)[None, None]
        want_vis = torch.tensor(HAND_VIS_MAP, dtype=dtype)[None, None]
        assert torch.equal(quality_map(img1, img2), want_reg)
        want_counts = torch.tensor(HAND_REG_COUNTS, dtype=torch.uint8)[None, None]
        assert torch.equal(registration_error_counts(img1, img2), want_counts)
        for pixels in (False, True):
            res = registration_quality(img1, img2, return_pixels=pixels)
            assert torch.equal(res.registration_map, want_reg)
            assert torch.equal(res.visual_map, want_vis)
            torch.testing.assert_close(res.quality_index, torch.tensor([1 - (34 + 24 + 40 + 32) / 64 / 4], dtype=dtype))

    def test_invalid_pixel_removes_its_neighbourhood(self, dtype):
        # (6, 9) and (6, 13) invalid: erosion removes rows 5-7 x cols 8-10 and 12-14, 18 of TR's
        # 24 registration errors (rows 5-7 are risk-free) -> 6 < 6.4 -> floored to 0.
        img1, img2 = hand_pair(dtype)
        valid = torch.ones(1, 1, 16, 16, dtype=dtype)
        valid[..., 6, 9] = 0
        valid[..., 6, 13] = 0
        counts = registration_error_counts(img1, img2, valid)
        assert counts.flatten().tolist() == [34, 6, 40, 32]
        res = registration_quality(img1, img2, valid)
        assert torch.equal(res.registration_map, torch.tensor([[[[34 / 64, 0.0], [40 / 64, 32 / 64]]]], dtype=dtype))
        # no visual errors in rows 5-7 (risk-free), so the visual map is unchanged
        assert torch.equal(res.visual_map, torch.tensor(HAND_VIS_MAP, dtype=dtype)[None, None])

    def test_risk_threshold_is_inclusive(self, dtype):
        # R0 = [G <= theta_G]. With theta_G = 1/32 (exact in binary) the ramp ends, whose G is
        # exactly 1/32, become weak: the structured columns are {3, 4} (none has both
        # neighbours structured) and the structured rows {5..11}, interior rows {6..10}. So
        # R = 0 exactly on rows 6-10. A does not depend on theta_G (A = 0 wherever x in Cx or
        # y in Ry, rows 6-10 included), so e_reg = rows 6-10, every column:
        # TL 2 x 8 = 16, TR 16, BL 3 x 8 = 24, BR 24.
        img1, img2 = hand_pair(dtype)
        at = QualityConfig(theta_g=1 / 32)
        assert registration_error_counts(img1, img2, config=at).flatten().tolist() == [16, 16, 24, 24]
        want = torch.tensor([[[[16 / 64, 16 / 64], [24 / 64, 24 / 64]]]], dtype=dtype)
        assert torch.equal(quality_map(img1, img2, config=at), want)
        e_reg = error_images(local_criteria(img1, img2, config=at), config=at).e_reg
        cols = torch.ones(16, dtype=dtype)
        assert torch.equal(e_reg[0, 0], indicator(range(6, 11), dtype=dtype)[:, None] * cols[None, :])
        assert torch.equal(registration_quality(img1, img2, config=at, return_pixels=True).registration_map, want)
        # just below 1/32 the ends are structured again: the counts of the default threshold
        below = QualityConfig(theta_g=1 / 32 - 1e-6)
        assert registration_error_counts(img1, img2, config=below).tolist() == [[HAND_REG_COUNTS]]

    def test_smooth_orientation_matches(self, dtype):
        img1, img2 = hand_pair(dtype)
        hard, smooth = local_criteria(img1, img2), local_criteria(img1, img2, smooth=True)
        torch.testing.assert_close(smooth.a, hard.a, atol=1e-6, rtol=0)
        torch.testing.assert_close(smooth.g1, hard.g1)


# ----------------------------------------------------------------------------- docs/method.md, literally


class TestAgainstSpec:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_double_angle_formula(self, seed):
        """local_criteria's A (atan2(|g1 x g2|, |g1 . g2|)) == the double-angle form of docs/method.md."""
        g = torch.Generator().manual_seed(seed)
        img1 = torch.rand(2, 1, 24, 32, generator=g, dtype=torch.float64)
        img2 = torch.rand(2, 1, 24, 32, generator=g, dtype=torch.float64)
        s1 = spatial_gradient(img1, mode="sobel", order=1, normalized=True)
        s2 = spatial_gradient(img2, mode="sobel", order=1, normalized=True)
        u1 = torch.stack([s1[:, :, 0] ** 2 - s1[:, :, 1] ** 2, 2 * s1[:, :, 0] * s1[:, :, 1]])
        u2 = torch.stack([s2[:, :, 0] ** 2 - s2[:, :, 1] ** 2, 2 * s2[:, :, 0] * s2[:, :, 1]])
        cross = (u1[0] * u2[1] - u1[1] * u2[0]).abs()
        dot = u1[0] * u2[0] + u1[1] * u2[1]
        want = 1 - (0.5 * torch.atan2(cross, dot)) / HALF_PI
        for smooth in (False, True):
            got = local_criteria(img1, img2, smooth=smooth).a
            torch.testing.assert_close(got, want, atol=1e-10, rtol=0)
        # and the wrap-around form min(|a1 - a2|, pi - |a1 - a2|), a = atan(s_y / s_x)
        a1 = torch.atan(s1[:, :, 1] / s1[:, :, 0])
        a2 = torch.atan(s2[:, :, 1] / s2[:, :, 0])
        diff = (a1 - a2).abs()
        wrap = torch.minimum(diff, math.pi - diff)
        torch.testing.assert_close(local_criteria(img1, img2).a, 1 - wrap / HALF_PI, atol=1e-9, rtol=0)

    @pytest.mark.parametrize("seed", [3, 4])
    def test_every_step_matches_reference(self, seed):
        img1, img2 = textured_pair(2, 32, 48, seed)
        valid = torch.ones(2, 1, 32, 48, dtype=torch.float64)
        valid[0, :, :, :5] = 0
        valid[1, :, 20:, 30:] = 0
        ref = spec_reference(img1, img2, valid)
        c = local_criteria(img1, img2)
        torch.testing.assert_close(c.a, ref["a"], atol=1e-10, rtol=0)
        torch.testing.assert_close(c.e, ref["e"], atol=1e-10, rtol=0)
        torch.testing.assert_close(c.g1, ref["g1"], atol=1e-12, rtol=0)
        torch.testing.assert_close(c.g2, ref["g2"], atol=1e-12, rtol=0)
        assert torch.equal(c.d, ref["d"])
        assert torch.equal(c.r, ref["r"])
        errs = error_images(c, valid)
        assert torch.equal(errs.e_reg, ref["e_reg"])
        assert torch.equal(errs.e_vis, ref["e_vis"])
        res = registration_quality(img1, img2, valid)
        assert torch.equal(res.registration_map, ref["reg"])
        assert torch.equal(res.visual_map, ref["vis"])
        assert torch.equal(quality_map(img1, img2, valid), ref["reg"])
        # the pair is built to exercise every branch
        assert 0 < float(ref["r"].mean()) < 1
        assert float(ref["e_reg"].sum()) > 0 and float(ref["e_vis"].sum()) > 0
        assert float((ref["reg"] > 0).float().mean()) > 0.2

    def test_scene_matches_reference(self, scene_pair):
        img1, img2 = (t.double() for t in scene_pair)
        ref = spec_reference(img1, img2)
        assert torch.equal(quality_map(img1, img2), ref["reg"])
        assert torch.equal(registration_quality(img1, img2).visual_map, ref["vis"])

    def test_edge_preservation_values(self):
        """E(A=1) = 0.976, E(A=0.8) = 0.494, E(A=0) ~ 0 (docs/method.md, section 2)."""
        x = textured(1, 16, 16, seed=5)
        c = local_criteria(x, x)
        assert bool((c.a == 1).all())
        torch.testing.assert_close(c.e, torch.full_like(c.e, 0.976), atol=1e-3, rtol=0)
        # gradient directions 10 and 28 degrees: dalpha = 18 degrees = 0.2 * pi / 2, A = 0.8
        c = local_criteria(angle_ramp(16, 16, 0.04, 10.0), angle_ramp(16, 16, 0.04, 28.0))
        inner_a, inner_e = c.a[..., 1:-1, 1:-1], c.e[..., 1:-1, 1:-1]
        torch.testing.assert_close(inner_a, torch.full_like(inner_a, 0.8), atol=1e-9, rtol=0)
        torch.testing.assert_close(inner_e, torch.full_like(inner_e, 0.494), atol=1e-3, rtol=0)
        # E is the sigmoid of A of docs/method.md on arbitrary pairs
        img1, img2 = textured_pair(1, 32, 32, seed=6)
        c = local_criteria(img1, img2)
        torch.testing.assert_close(c.e, CFG.gamma / (1 + torch.exp(CFG.k * (c.a - CFG.sigma))), atol=1e-12, rtol=0)
        assert float(c.e.min()) >= 0 and float(c.e.max()) <= CFG.gamma
        assert float(c.a.min()) >= 0 and float(c.a.max()) <= 1


# ----------------------------------------------------------------------------- orientation


class TestOrientation:
    def test_perpendicular_gradients(self):
        img1 = x_ramp(16, 16, 0.05)
        img2 = img1.transpose(-1, -2).contiguous()  # a y-ramp: s_x = 0 exactly
        c = local_criteria(img1, img2)
        assert bool((c.a == 0).all())
        assert float(c.e.max()) < 1e-7
        # slopes 0.05 (0.025 on the border) > theta_G: no risk anywhere, every pixel errs
        assert bool((c.r == 0).all())
        assert bool((error_images(c).e_reg == 1).all())
        assert bool((quality_map(img1, img2) == 1).all())
        assert bool((registration_error_counts(img1, img2) == 64).all())

    def test_near_vertical_wrap_around(self):
        """Gradient directions +89.5 and -89.5 degrees: atan(s_y / s_x) = +-89.5 degrees differ by
        179 degrees, but as axes they are 1 degree apart (the wrap-around of docs/method.md)."""
        img1 = angle_ramp(16, 16, 0.05, 89.5)
        img2 = angle_ramp(16, 16, 0.05, -89.5)
        c = local_criteria(img1, img2)
        inner = c.a[..., 1:-1, 1:-1]
        torch.testing.assert_close(inner, torch.full_like(inner, 1 - 1 / 90), atol=1e-9, rtol=0)
        # border pixels: replicate padding halves one Sobel component -> at most 2 degrees apart
        assert float(c.a.min()) >= 1 - 2 / 90 - 1e-9
        assert float(c.e.min()) > 0.9
        assert bool((quality_map(img1, img2) == 0).all())
        # contrast: a nearly perpendicular pair (89.5 vs -0.5 degrees) is an error everywhere
        c = local_criteria(img1, angle_ramp(16, 16, 0.05, -0.5))
        torch.testing.assert_close(c.a[..., 1:-1, 1:-1], torch.full_like(inner, 0.0), atol=1e-9, rtol=0)
        assert bool((quality_map(img1, angle_ramp(16, 16, 0.05, -0.5)) == 1).all())

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_contrast_reversal(self, dtype):
        # multiples of 1/64: 1 - x and every Sobel sum are exact, so s2 = -s1 exactly
        g = torch.Generator().manual_seed(7)
        img1 = (torch.randint(0, 65, (2, 1, 24, 24), generator=g) / 64).to(dtype)
        img2 = 1 - img1
        for smooth in (False, True):
            c = local_criteria(img1, img2, smooth=smooth)
            assert bool((c.a == 1).all())
        assert bool((quality_map(img1, img2) == 0).all())

    def test_rotation_by_90_degrees_is_an_error(self):
        x = textured(1, 32, 32, seed=8)
        res = registration_quality(x, x.transpose(-1, -2))
        assert float((res.registration_map > 0).float().mean()) > 0.5


# ----------------------------------------------------------------------------- risk map and validity


class TestRiskMap:
    def test_single_weak_pixel_dilates_3x3(self):
        # f = c ((x - 5)^2 + (y - 2)^2): the Sobel gradient is 2 c (x - 5, y - 2) inside (the
        # central difference of a quadratic is exact), non-zero on the border; c = 0.015 makes
        # every pixel but (2, 5) stronger than 2 c = 0.03 > theta_G.
        y = torch.arange(8, dtype=torch.float64)[:, None]
        x = torch.arange(8, dtype=torch.float64)[None, :]
        img = (0.015 * ((x - 5) ** 2 + (y - 2) ** 2))[None, None]
        c = local_criteria(img, img)
        assert float(c.g1[0, 0, 2, 5]) == 0.0
        assert int((c.g1 <= CFG.theta_g).sum()) == 1
        want = torch.zeros(1, 1, 8, 8, dtype=torch.float64)
        want[..., 1:4, 4:7] = 1
        assert torch.equal(c.r, want)

    def test_weak_corner_pixel_dilates_2x2(self):
        # f = c (x^2 + y^2): at (0, 0) replicate padding gives s = (c/2, c/2), weak; every other
        # pixel has a component of at least 2 c = 0.0204 > theta_G.
        y = torch.arange(8, dtype=torch.float64)[:, None]
        x = torch.arange(8, dtype=torch.float64)[None, :]
        img = (0.0102 * (x**2 + y**2))[None, None]
        c = local_criteria(img, img)
        want = torch.zeros(1, 1, 8, 8, dtype=torch.float64)
        want[..., :2, :2] = 1
        assert torch.equal(c.r, want)

    def test_both_gradients_must_be_weak(self):
        # img1 flat, img2 a strong ramp: R0 = [G1 <= theta and G2 <= theta] = 0 everywhere
        flat = torch.full((1, 1, 16, 16), 0.5, dtype=torch.float64)
        c = local_criteria(flat, x_ramp(16, 16, 0.05))
        assert bool((c.r == 0).all())
        # the zero vector of img1 has no orientation to agree with the ramp's: A = 0, every
        # pixel a registration error (the edge of img2 is lost in img1)
        assert bool((c.a == 0).all())
        assert bool((quality_map(flat, x_ramp(16, 16, 0.05)) == 1).all())
