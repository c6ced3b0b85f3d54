"""Tests of the registration-quality metric, part 2: validity masks, the block floor,
invariances, the fast hard path against the pieces, smooth -> hard convergence, and batch,
dtype and device consistency (docs/method.md, sections 2-5)."""

from __future__ import annotations

import pytest
import torch
from kornia.geometry.transform import rotate, translate
from metric_helpers import (
    CFG,
    assert_in_floor_range,
    blocks,
    hard_from_pieces,
    spec_reference,
    textured,
    textured_pair,
    x_ramp,
)

from lensdist_torch import QualityConfig, load_scene, quality_map, registration_quality, registration_quality_loss
from lensdist_torch.metric import (
    block_counts,
    block_pool,
    counts_to_map,
    erode_valid,
    error_images,
    local_criteria,
    registration_error_counts,
)


class TestValidity:
    def _all_errors(self):
        # perpendicular ramps, slopes >= 0.025 > theta_G everywhere: every pixel is an error
        img1 = x_ramp(16, 16, 0.05)
        return img1, img1.transpose(-1, -2).contiguous()

    def test_full_mask_and_border(self):
        img1, img2 = self._all_errors()
        ones = torch.ones(1, 1, 16, 16, dtype=torch.float64)
        assert bool((quality_map(img1, img2, ones) == 1).all())  # the border stays valid
        assert torch.equal(erode_valid(ones), ones)
        assert bool((quality_map(img1, img2, torch.zeros_like(ones)) == 0).all())

    @pytest.mark.parametrize(
        "pixel,want_counts",
        [
            ((5, 5), [55, 64, 64, 64]),  # rows 4-6 x cols 4-6 inside TL
            ((0, 0), [60, 64, 64, 64]),  # corner: only rows 0-1 x cols 0-1
            ((0, 7), [60, 62, 64, 64]),  # rows 0-1 x cols 6-7 in TL, col 8 in TR
            ((8, 8), [63, 62, 62, 60]),  # rows 7-9 x cols 7-9 across all four blocks
        ],
    )
    def test_invalid_pixel_erodes_3x3(self, pixel, want_counts):
        img1, img2 = self._all_errors()
        valid = torch.ones(1, 1, 16, 16, dtype=torch.float64)
        valid[0, 0, pixel[0], pixel[1]] = 0
        counts = registration_error_counts(img1, img2, valid)
        assert counts.flatten().tolist() == want_counts
        e_reg = error_images(local_criteria(img1, img2), valid).e_reg
        want = torch.ones_like(valid)
        y0, x0 = pixel
        want[..., max(y0 - 1, 0) : y0 + 2, max(x0 - 1, 0) : x0 + 2] = 0
        assert torch.equal(e_reg, want)
        want_map = torch.tensor(want_counts, dtype=torch.float64).view(1, 1, 2, 2) / 64
        assert torch.equal(quality_map(img1, img2, valid), want_map)

    def test_bool_and_float_masks_agree(self):
        img1, img2 = textured_pair(2, 16, 24, seed=9)
        valid = torch.rand(2, 1, 16, 24, generator=torch.Generator().manual_seed(0)) > 0.1
        assert torch.equal(quality_map(img1, img2, valid), quality_map(img1, img2, valid.double()))
        assert torch.equal(
            registration_quality(img1, img2, valid, return_pixels=True).registration_map,
            quality_map(img1, img2, valid.float()),
        )


class TestBlockFloor:
    def test_floor_with_block_size_10(self):
        cfg = QualityConfig(block_size=10)
        e = torch.zeros(1, 1, 20, 20, dtype=torch.float64)
        e[0, 0, :1, :10] = 1  # 10 pixels in the top-left block: ratio exactly 0.1, kept
        e[0, 0, 10:11, 10:19] = 1  # 9 pixels in the bottom-right block: 0.09, set to 0
        e[0, 0, 15, 0:4] = 1  # 4 pixels: 0
        want = torch.tensor([[[[0.1, 0.0], [0.0, 0.0]]]], dtype=torch.float64)
        assert torch.equal(block_pool(e, cfg), want)
        assert torch.equal(block_pool(e.float(), cfg), want.float())
        assert torch.equal(block_counts(e, 10), torch.tensor([[[[10.0, 0.0], [4.0, 9.0]]]], dtype=torch.float64))

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_floor_end_to_end(self, dtype):
        # perpendicular ramps: every pixel errs; the eroded validity leaves exactly n of them
        cfg = QualityConfig(block_size=10)
        img1 = x_ramp(20, 20, 0.05, dtype)
        img2 = img1.transpose(-1, -2).contiguous()
        valid = torch.zeros(1, 1, 20, 20, dtype=dtype)
        valid[..., 2:6, 2:9] = 1  # 4 x 7 valid -> eroded 2 x 5 = 10 pixels -> 0.1, kept
        valid[..., 12:17, 12:17] = 1  # 5 x 5 valid -> eroded 3 x 3 = 9 pixels -> 0.09 -> 0
        counts = registration_error_counts(img1, img2, valid, config=cfg)
        assert counts.flatten().tolist() == [10, 0, 0, 9]
        want = torch.tensor([[[[0.1, 0.0], [0.0, 0.0]]]], dtype=dtype)
        assert torch.equal(quality_map(img1, img2, valid, config=cfg), want)
        for pixels in (False, True):
            res = registration_quality(img1, img2, valid, config=cfg, return_pixels=pixels)
            assert torch.equal(res.registration_map, want)

    def test_default_floor_between_6_and_7_pixels(self):
        e = torch.zeros(1, 1, 8, 16, dtype=torch.float64)
        e[0, 0, 0, :6] = 1  # 6/64 = 0.094 -> 0
        e[0, 0, 0, 8:15] = 1  # 7/64 = 0.109 -> kept
        assert block_pool(e).flatten().tolist() == [0.0, 7 / 64]


# ----------------------------------------------------------------------------- invariances


class TestInvariances:
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_identical_images(self, dtype, scene):
        for x in (scene.to(dtype), textured(2, 32, 40, seed=10, dtype=dtype)):
            res = registration_quality(x, x, return_pixels=True)
            assert bool((res.registration_map == 0).all()) and bool((res.visual_map == 0).all())
            assert bool((res.quality_index == 1).all())
            assert bool((res.criteria.d == 0).all()) and bool((res.criteria.a == 1).all())
            assert bool((res.errors.e_reg == 0).all()) and bool((res.errors.e_vis == 0).all())
            assert bool((quality_map(x, x) == 0).all())

    def test_global_brightness_change(self, scene):
        # gain and offset (no clamping: 0.9 x + 0.05 stays in [0.05, 0.95]): gradients scale by
        # 0.9, orientations are kept, |D| <= 0.05 -> no registration or visual errors
        for img1 in (scene.double(), scene, textured(2, 32, 32, seed=11)):
            img2 = img1 * 0.9 + 0.05
            res = registration_quality(img1, img2)
            assert bool((res.registration_map == 0).all())
            assert bool((res.visual_map == 0).all())
            # a pure offset that never clamps
            img3 = img1 * 0.95 + 0.05
            assert bool((quality_map(img1 * 0.95, img3) == 0).all())

    @pytest.mark.parametrize("dy,dx", [(0, 1), (1, 0), (2, 1), (0, 2)])
    def test_small_shift_gives_registration_errors(self, dy, dx):
        full = load_scene("gravel")
        img1 = full[..., 40:360, 44:468]
        img2 = full[..., 40 - dy : 360 - dy, 44 - dx : 468 - dx]
        m = quality_map(img1, img2)
        assert m.shape == (1, 1, 40, 53)
        assert float((m > 0).float().mean()) > 0.6  # most blocks of the textured scene
        assert_in_floor_range(m)

    def test_symmetric(self, scene_pair):
        img1, img2 = scene_pair
        valid = torch.ones(1, 1, 320, 424)
        valid[..., :30, :] = 0
        a, b = registration_quality(img1, img2, valid), registration_quality(img2, img1, valid)
        assert torch.equal(a.registration_map, b.registration_map)
        assert torch.equal(a.visual_map, b.visual_map)
        sa = registration_quality_loss(img1, img2, valid, reduction="none")
        sb = registration_quality_loss(img2, img1, valid, reduction="none")
        assert torch.equal(sa, sb)


# ----------------------------------------------------------------------------- fast path == pieces


def rotated_with_mask(img: torch.Tensor, degrees: float):
    angle = torch.full((img.shape[0],), degrees, dtype=img.dtype)
    warped = rotate(img, angle)
    mask = rotate(torch.ones_like(img), angle)  # fractional at the edge of the content
    return warped, mask


class TestFastPath:
    def _check(self, img1, img2, valid=None, cfg=CFG):
        fast = quality_map(img1, img2, valid, config=cfg)
        reg, vis, errs = hard_from_pieces(img1, img2, valid, cfg)
        assert torch.equal(fast, reg)
        res = registration_quality(img1, img2, valid, config=cfg)
        assert torch.equal(res.registration_map, fast)
        assert torch.equal(res.visual_map, vis)
        torch.testing.assert_close(res.quality_index, 1 - fast.mean(dim=(1, 2, 3)))
        full = registration_quality(img1, img2, valid, config=cfg, return_pixels=True)
        assert torch.equal(full.registration_map, fast)
        assert torch.equal(full.visual_map, vis)
        assert torch.equal(full.errors.e_reg, errs.e_reg)
        counts = registration_error_counts(img1, img2, valid, config=cfg)
        assert torch.equal(counts, block_counts(errs.e_reg, cfg.block_size).to(torch.uint8))
        return fast

    @pytest.mark.parametrize("seed", [0, 1, 2, 3])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_random_textures(self, seed, dtype):
        img1, img2 = textured_pair(3, 40, 56, seed, dtype)
        m = self._check(img1, img2)
        assert float(m.sum()) > 0
        g = torch.Generator().manual_seed(seed)
        r1 = torch.rand(2, 1, 16, 24, generator=g).to(dtype)
        r2 = torch.rand(2, 1, 16, 24, generator=g).to(dtype)
        self._check(r1, r2)

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_scene_shifts_and_rotations(self, scene, dtype):
        x = scene[..., :160, :216].to(dtype)
        pairs = []
        for t in ((1.0, 0.0), (0.4, -1.7)):  # whole and sub-pixel translations
            shift = torch.tensor([t], dtype=dtype)
            pairs.append((x, translate(x, shift), translate(torch.ones_like(x), shift)))
        for deg in (0.5, -2.0):
            warped, mask = rotated_with_mask(x, deg)
            pairs.append((x, warped, mask))
        for img1, img2, mask in pairs:
            m = self._check(img1, img2, None)
            assert float((m > 0).float().mean()) > 0.5
            assert float(mask.min()) < 0.5  # some content left the frame
            self._check(img1, img2, mask)  # a fractional mask: valid where >= 0.5
            self._check(img1, img2, (mask > 0.999).to(dtype))

    def test_stored_counts_and_feature_vector(self, scene_pair):
        img1, img2 = scene_pair
        counts = registration_error_counts(img1, img2)
        m = quality_map(img1, img2)
        assert torch.equal(counts_to_map(counts), m)
        assert torch.equal(counts_to_map(registration_error_counts(img1.double(), img2.double())), m.double().float())
        # blocks whose count is below 6.4 are floored, the others are count / 64
        assert torch.equal(m, torch.where(counts < 7, 0.0, counts.float() / 64))
        # docs/method.md, section 4: the feature vector is the map's rows concatenated, 40 x 53 = 2120 at 320 x 424
        feat = m.flatten(1)
        assert feat.shape == (1, 2120)
        assert torch.equal(feat[0, 53:106], m[0, 0, 1])

    @pytest.mark.parametrize(
        "cfg",
        [
            QualityConfig(theta_e=0.98),  # above E(A=1): every structured pixel errs
            QualityConfig(theta_e=1e-9),  # below E(A=0): no pixel errs
            QualityConfig(theta_g=0.1, theta_d=0.05),
            QualityConfig(block_size=4, min_block_ratio=0.0),
        ],
    )
    def test_other_configs(self, cfg):
        img1, img2 = textured_pair(2, 32, 48, seed=12)
        m = self._check(img1, img2, None, cfg)
        ref = spec_reference(img1, img2, None, cfg)
        assert torch.equal(m, ref["reg"])
        if cfg.theta_e == 0.98:  # E <= 0.976 < theta_E: e_reg = 1 - R
            want = blocks(1 - local_criteria(img1, img2, config=cfg).r, 8) / 64
            assert torch.equal(m, torch.where(want < 0.1, 0.0, want))
        if cfg.theta_e == 1e-9:
            assert bool((m == 0).all())


# ----------------------------------------------------------------------------- smooth -> hard


class TestSmoothConvergence:
    @pytest.mark.parametrize("which", ["textures", "scene"])
    def test_smooth_converges_to_hard(self, which, scene_pair):
        if which == "textures":
            img1, img2 = textured_pair(2, 48, 64, seed=13)
        else:
            img1, img2 = (t[..., :96, :128].double() for t in scene_pair)
        hard = registration_quality(img1, img2)
        diffs_reg, diffs_vis = [], []
        for scale in (1.0, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6):
            cfg = CFG.with_temperature_scale(scale)
            smooth = registration_quality(img1, img2, config=cfg, smooth=True)
            diffs_reg.append(float((smooth.registration_map - hard.registration_map).abs().max()))
            diffs_vis.append(float((smooth.visual_map - hard.visual_map).abs().max()))
            # (at 1e-4 a pixel of the float64 noise texture can still lie within a few
            # temperatures of a threshold: tau_g is then 4e-7)
            if scale <= 1e-5:
                assert diffs_reg[-1] < 1e-3 and diffs_vis[-1] < 1e-3, (scale, diffs_reg, diffs_vis)
                loss = registration_quality_loss(img1, img2, config=cfg, reduction="none")
                assert float((loss - hard.registration_map).abs().max()) < 1e-3
        assert diffs_reg[0] > 1e-2  # the default temperatures are not a hard threshold
        for a, b in zip(diffs_reg, diffs_reg[1:]):
            assert b <= a + 1e-12, diffs_reg
        for a, b in zip(diffs_vis, diffs_vis[1:]):
            assert b <= a + 1e-12, diffs_vis

    def test_smooth_criteria_converge(self):
        img1, img2 = textured_pair(1, 32, 32, seed=14)
        hard = local_criteria(img1, img2)
        smooth = local_criteria(img1, img2, config=CFG.with_temperature_scale(1e-6), smooth=True)
        torch.testing.assert_close(smooth.a, hard.a, atol=1e-12, rtol=0)
        torch.testing.assert_close(smooth.e, hard.e, atol=1e-12, rtol=0)
        assert float((smooth.r - hard.r).abs().max()) < 1e-3
        errs_h = error_images(hard)
        errs_s = error_images(smooth, config=CFG.with_temperature_scale(1e-6), smooth=True)
        assert float((errs_s.e_reg - errs_h.e_reg).abs().max()) < 1e-3
        assert float((errs_s.e_vis - errs_h.e_vis).abs().max()) < 1e-3

    def test_smooth_block_floor(self):
        cfg = QualityConfig(block_size=10, temperature=5e-3)  # tau_b 1e-4
        e = torch.zeros(1, 1, 10, 20, dtype=torch.float64)
        e[0, 0, 0, :5] = 1  # 0.05: far below the floor
        e[0, 0, 0, 10:20] = 1
        e[0, 0, 1, 10:15] = 1  # 0.15
        got = block_pool(e, cfg, smooth=True)
        torch.testing.assert_close(got, torch.tensor([[[[0.0, 0.15]]]], dtype=torch.float64), atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- batches, dtypes, devices


class TestConsistency:
    def test_batch_and_chunks(self):
        img1, img2 = textured_pair(5, 24, 32, seed=15)
        valid = (torch.rand(5, 1, 24, 32, generator=torch.Generator().manual_seed(1)) > 0.05).double()
        alone = torch.cat([quality_map(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1]) for i in range(5)])
        alone_counts = torch.cat(
            [registration_error_counts(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1]) for i in range(5)]
        )
        alone_vis = torch.cat(
            [registration_quality(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1]).visual_map for i in range(5)]
        )
        for chunk in (1, 2, 3, 5, 8):
            cfg = QualityConfig(chunk_size=chunk)
            assert torch.equal(quality_map(img1, img2, valid, config=cfg), alone)
            assert torch.equal(registration_quality(img1, img2, valid, config=cfg).visual_map, alone_vis)
            assert torch.equal(registration_error_counts(img1, img2, valid, config=cfg), alone_counts)
        smooth_alone = torch.cat(
            [
                registration_quality_loss(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1], reduction="none")
                for i in range(5)
            ]
        )
        smooth = registration_quality_loss(img1, img2, valid, reduction="none")
        torch.testing.assert_close(smooth, smooth_alone, atol=1e-14, rtol=0)

    def test_float32_agrees_with_float64(self, scene_pair):
        img1, img2 = scene_pair
        m32 = quality_map(img1, img2)
        m64 = quality_map(img1.double(), img2.double())
        assert float((m32.double() != m64).float().mean()) < 0.01
        assert float((m32.double() - m64).abs().mean()) < 1e-3
        t1, t2 = textured_pair(2, 32, 48, seed=16)
        assert float((quality_map(t1.float(), t2.float()).double() != quality_map(t1, t2)).float().mean()) < 0.02
        l32 = registration_quality_loss(t1.float(), t2.float(), reduction="none")
        l64 = registration_quality_loss(t1, t2, reduction="none")
        torch.testing.assert_close(l32.double(), l64, atol=1e-4, rtol=0)

    def test_mixed_dtypes_promote(self):
        t1, t2 = textured_pair(1, 16, 16, seed=17)
        assert quality_map(t1.float(), t2).dtype == torch.float64

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda_matches_cpu(self, scene_pair):
        img1, img2 = scene_pair
        cpu = registration_quality(img1, img2)
        gpu = registration_quality(img1.cuda(), img2.cuda())
        assert gpu.registration_map.device.type == "cuda"
        assert float((gpu.registration_map.cpu() != cpu.registration_map).float().mean()) < 0.01
        assert float((gpu.visual_map.cpu() != cpu.visual_map).float().mean()) < 0.01
        x = img1[..., :64, :64].cuda().requires_grad_()
        loss = registration_quality_loss(x, img2[..., :64, :64].cuda())
        loss.backward()
        assert bool(torch.isfinite(x.grad).all())
        cpu_loss = registration_quality_loss(img1[..., :64, :64], img2[..., :64, :64])
        torch.testing.assert_close(loss.cpu(), cpu_loss, atol=1e-4, rtol=0)
