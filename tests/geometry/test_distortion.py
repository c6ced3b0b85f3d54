"""Tests of the radial distortion model (docs/method.md, section 6) in lensdist_torch/geometry/distortion.py.

Values worked out by hand, the method's Delta numbers at the default size, agreement of every
helper with a literal transcription of eq. 4, the Newton inverse, and the class bins.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from lensdist_torch.calibration.sequence_class import NO_DISTORTION_PX, interval_class
from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import (
    CLASS_LABELS,
    REJECT,
    class_bounds,
    delta_avg,
    delta_max,
    delta_metric,
    delta_top,
    distort_points,
    distortion_center,
    distortion_class,
    distortion_grid,
    estimated_class,
    pixel_grid,
    pixel_offsets,
    render_distorted,
    undistort_points,
)

H, W = 320, 424
K2, K4 = 2.5e-6, 2.5e-11


pytestmark = pytest.mark.usefixtures("one_thread_module")


def eq4(points: torch.Tensor, k2: float, k4: float, center) -> torch.Tensor:
    """Literal eq. 4 for one coefficient pair: p = p0 + (1 + k2 r^2 + k4 r^4) (p_d - p0)."""
    x0, y0 = center
    dx, dy = points[..., 0] - x0, points[..., 1] - y0
    r = torch.sqrt(dx * dx + dy * dy)
    f = 1.0 + k2 * r**2 + k4 * r**4
    return torch.stack([x0 + f * dx, y0 + f * dy], dim=-1)


class TestSpecNumbers:
    def test_delta_max_default_size(self):
        assert float(delta_max([K2], [K4], H, W)[0]) == pytest.approx(79.1, abs=0.05)

    def test_delta_avg_default_size(self):
        assert float(delta_avg([K2], [K4], H, W)[0]) == pytest.approx(14.4, abs=0.05)

    def test_delta_top(self):
        assert delta_top("delta_max", LensdistConfig()) == pytest.approx(79.1, abs=0.05)
        assert delta_top("delta_avg", LensdistConfig()) == pytest.approx(14.4, abs=0.05)

    def test_delta_metric_by_name(self):
        k2, k4 = [1e-6, 2e-6], [3e-12, 1e-11]
        assert torch.equal(delta_metric(k2, k4, H, W, metric="delta_max"), delta_max(k2, k4, H, W))
        assert torch.equal(delta_metric(k2, k4, H, W, metric="delta_avg"), delta_avg(k2, k4, H, W))
        with pytest.raises(ValueError, match="metric"):
            delta_metric(k2, k4, H, W, metric="delta_median")

    def test_delta_max_is_at_the_corner(self):
        """The farthest pixel centre from p0 is a corner: r^2 = 211.5^2 + 159.5^2."""
        r = math.sqrt(211.5**2 + 159.5**2)
        assert float(delta_max([K2], [K4], H, W)[0]) == pytest.approx(K2 * r**3 + K4 * r**5, rel=1e-12)


class TestHandWorked:
    def test_single_pixel_offset(self):
        """11 x 11 image, p0 = (5, 5); pixel (8, 9): d = (3, 4), r = 5.

        k2 = 0.01, k4 = 0.001: delta = 0.01 * 125 + 0.001 * 3125 = 4.375 px;
        factor = 1 + 0.25 + 0.625 = 1.875, p = (5 + 5.625, 5 + 7.5) = (10.625, 12.5).
        """
        off = pixel_offsets([0.01], [0.001], 11, 11)
        assert off.shape == (1, 11, 11)
        assert float(off[0, 9, 8]) == pytest.approx(4.375, abs=1e-12)
        assert float(off[0, 5, 5]) == 0.0  # the centre does not move
        p = undistort_points(torch.tensor([[8.0, 9.0]], dtype=torch.float64), [0.01], [0.001], (5.0, 5.0))
        assert p[0].tolist() == pytest.approx([10.625, 12.5], abs=1e-12)

    def test_center(self):
        assert distortion_center(320, 424) == (211.5, 159.5)
        assert distortion_center(11, 11) == (5.0, 5.0)

    def test_pixel_grid(self):
        g = pixel_grid(3, 4)
        assert g.shape == (3, 4, 2)
        assert g[2, 3].tolist() == [3.0, 2.0]  # (x, y)
        assert g[0, 0].tolist() == [0.0, 0.0]


class TestMonotone:
    @pytest.mark.parametrize("k2,k4", [(K2, K4), (K2, 0.0), (0.0, K4), (1e-7, 3e-12)])
    def test_offsets_grow_along_a_ray(self, k2, k4):
        c = distortion_center(H, W)
        for angle in (0.0, 0.7, 2.0, -2.5):
            t = torch.linspace(0.0, 265.0, 500, dtype=torch.float64)
            pts = torch.stack([c[0] + t * math.cos(angle), c[1] + t * math.sin(angle)], dim=-1)
            off = (undistort_points(pts[None], [k2], [k4], c)[0] - pts).norm(dim=-1)
            assert off[0] == 0
            assert bool((off[1:] > off[:-1]).all())

    def test_pixel_offsets_increase_with_radius(self):
        off = pixel_offsets([K2], [K4], H, W)[0].flatten()
        g = pixel_grid(H, W, torch.float64).reshape(-1, 2)
        r = (g - torch.tensor(distortion_center(H, W), dtype=torch.float64)).norm(dim=-1)
        order = torch.argsort(r)
        sorted_off, sorted_r = off[order], r[order]
        # non-decreasing, and strictly increasing wherever the radius does
        assert bool((sorted_off[1:] >= sorted_off[:-1]).all())
        grows = sorted_r[1:] > sorted_r[:-1] * (1 + 1e-12)
        assert bool((sorted_off[1:][grows] > sorted_off[:-1][grows]).all())

    def test_delta_grows_with_each_coefficient(self):
        k2 = torch.linspace(0, K2, 6, dtype=torch.float64)
        for f in (delta_max, delta_avg):
            d = f(k2, torch.full_like(k2, K4 / 2), H, W)
            assert bool((d[1:] > d[:-1]).all())
            d = f(torch.full_like(k2, K2 / 2), k2 * 1e-5, H, W)
            assert bool((d[1:] > d[:-1]).all())


class TestIdentity:
    def test_undistort_identity(self):
        pts = torch.rand(2, 7, 5, 2, dtype=torch.float64) * 400
        out = undistort_points(pts, [0.0, 0.0], [0.0, 0.0], (211.5, 159.5))
        torch.testing.assert_close(out, pts, atol=1e-12, rtol=0)  # (p - p0) + p0 up to rounding

    def test_distort_identity(self):
        pts = torch.rand(2, 30, 2, dtype=torch.float64) * 400
        out = distort_points(pts, [0.0, 0.0], [0.0, 0.0], (211.5, 159.5))
        torch.testing.assert_close(out, pts, atol=1e-12, rtol=0)

    def test_render_identity(self):
        img = torch.rand(2, 3, 24, 40)
        out = render_distorted(img, [0.0, 0.0], [0.0, 0.0])
        assert out.shape == img.shape
        torch.testing.assert_close(out, img, atol=1e-5, rtol=0)

    def test_offsets_zero(self):
        assert float(pixel_offsets([0.0], [0.0], 32, 48).abs().max()) == 0.0
        assert float(delta_max([0.0], [0.0], H, W)[0]) == 0.0
        assert float(delta_avg([0.0], [0.0], H, W)[0]) == 0.0


class TestAgainstEq4:
    @pytest.mark.parametrize("k2,k4", [(K2, K4), (1e-6, 0.0), (0.0, 2e-11), (2e-6, -1e-11)])
    def test_pixel_offsets_equal_displacement(self, k2, k4):
        g = pixel_grid(H, W, torch.float64)
        p = eq4(g, k2, k4, distortion_center(H, W))
        expected = (p - g).norm(dim=-1)
        torch.testing.assert_close(pixel_offsets([k2], [k4], H, W)[0], expected, atol=1e-9, rtol=1e-9)
        # and through the library's own eq. 4
        q = undistort_points(g[None], [k2], [k4], distortion_center(H, W))[0]
        torch.testing.assert_close((q - g).norm(dim=-1), expected, atol=1e-9, rtol=1e-9)

    def test_distortion_grid_is_eq4_per_pair(self):
        k2, k4 = [K2, 1e-6, 0.0], [K4, 0.0, 1e-11]
        grid = distortion_grid(k2, k4, 40, 56, dtype=torch.float64)
        assert grid.shape == (3, 40, 56, 2)
        g = pixel_grid(40, 56, torch.float64)
        for i in range(3):
            torch.testing.assert_close(grid[i], eq4(g, k2[i], k4[i], distortion_center(40, 56)), atol=1e-12, rtol=0)

    def test_batched_coefficients(self):
        d = delta_max([K2, 0.0, K2 / 2], [K4, 0.0, 0.0], H, W)
        assert d.shape == (3,) and d.dtype == torch.float64
        assert float(d[1]) == 0.0
        assert float(d[0]) == pytest.approx(float(delta_max([K2], [K4], H, W)[0]))

    def test_mismatched_coefficients_raise(self):
        with pytest.raises(ValueError, match="same number"):
            pixel_offsets([K2, K2], [K4], 8, 8)
        with pytest.raises(ValueError, match="finite"):
            pixel_offsets([float("nan")], [K4], 8, 8)


class TestNewtonInverse:
    @pytest.mark.parametrize(
        "k2,k4",
        [
            (K2, K4),  # the largest coefficients
            (K2, 0.0),
            (0.0, K4),
            (1e-9, 1e-14),
            (K2, -2.5e-11),  # negative k4: f'(r) = 1 + 3 k2 r^2 + 5 k4 r^4 > 0.9 up to the corner
        ],
    )
    def test_inverse_of_eq4_over_the_whole_image(self, k2, k4):
        c = distortion_center(H, W)
        pd = pixel_grid(H, W, torch.float64)
        p = eq4(pd, k2, k4, c)
        back = distort_points(p[None], [k2], [k4], c)[0]
        err = (back - pd).norm(dim=-1).max()
        assert float(err) < 1e-6

    def test_round_trip_batched(self):
        c = distortion_center(H, W)
        pts = torch.rand(3, 200, 2, dtype=torch.float64) * torch.tensor([W - 1.0, H - 1.0], dtype=torch.float64)
        k2, k4 = [K2, 1e-6, 0.0], [K4, 5e-12, 1e-11]
        out = undistort_points(distort_points(pts, k2, k4, c), k2, k4, c)
        torch.testing.assert_close(out, pts, atol=1e-6, rtol=0)

    def test_centre_is_fixed(self):
        c = distortion_center(H, W)
        pts = torch.tensor([[list(c)]], dtype=torch.float64)
        out = distort_points(pts, [K2], [K4], c)
        assert torch.isfinite(out).all()
        assert out.tolist() == [[list(c)]]


class TestClasses:
    TOP = 80.0

    @pytest.mark.parametrize(
        "delta,cls",
        [
            (1e-9, 0), (10.0, 0), (20.0, 0),
            (20.0 + 1e-9, 1), (40.0, 1),
            (40.5, 2), (60.0, 2),
            (60.1, 3), (80.0, 3),
            (0.0, REJECT),
            (80.0 + 1e-9, 3), (500.0, 3),
        ],
    )
    def test_bins(self, delta, cls):
        assert int(distortion_class(torch.tensor([delta], dtype=torch.float64), self.TOP)[0]) == cls

    def test_batched_and_dtype(self):
        out = distortion_class(torch.tensor([0.0, 5.0, 25.0, 45.0, 65.0, 79.1]), self.TOP)
        assert out.dtype == torch.int64
        assert out.tolist() == [REJECT, 0, 1, 2, 3, 3]

    def test_top_coefficients_are_the_last_class(self):
        for metric in ("delta_max", "delta_avg"):
            top = delta_top(metric, LensdistConfig())
            d = delta_metric([K2, K2 / 1000], [K4, K4 / 1000], H, W, metric=metric)
            assert distortion_class(d, top).tolist()[0] == 3
            assert distortion_class(d, top).tolist()[1] == 0

    def test_other_class_count(self):
        assert distortion_class(torch.tensor([1.0, 3.0, 6.0, 0.0]), 6.0, n_classes=3).tolist() == [0, 1, 2, REJECT]

    @pytest.mark.parametrize("top", [0.0, -1.0, float("nan"), float("inf")])
    def test_bad_top(self, top):
        with pytest.raises(ValueError, match="top"):
            distortion_class(torch.tensor([1.0]), top)

    @pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
    def test_bad_delta(self, bad):
        with pytest.raises(ValueError, match="delta"):
            distortion_class(torch.tensor([1.0, bad]), self.TOP)


class TestRender:
    def test_linear_ramp_is_sampled_at_eq4(self):
        """Bilinear sampling of a linear ramp is exact: I_d(p_d) = ramp(p(p_d)) wherever p is inside."""
        h, w = 48, 64
        g = pixel_grid(h, w, torch.float64)
        ramp = ((g[..., 0] + 2 * g[..., 1]) / 200.0)[None, None]
        k2, k4 = 2e-5, 1e-9
        out = render_distorted(ramp, [k2], [k4])[0, 0]
        p = eq4(g, k2, k4, distortion_center(h, w))
        inside = (p[..., 0] >= 0) & (p[..., 0] <= w - 1) & (p[..., 1] >= 0) & (p[..., 1] <= h - 1)
        assert 0.3 < float(inside.double().mean()) < 1.0  # the test covers both cases
        expected = (p[..., 0] + 2 * p[..., 1]) / 200.0
        torch.testing.assert_close(out[inside], expected[inside], atol=1e-9, rtol=0)
        # outside the source the image is zero-padded: a far-out corner sample is 0
        assert float(out[0, 0]) == 0.0

    def test_one_coefficient_pair_per_image(self):
        with pytest.raises(ValueError, match="one value per image"):
            render_distorted(torch.rand(2, 1, 8, 8), [K2], [K4])


def test_one_pair_and_a_sequence_have_their_own_r_threshold():
    """R below analysis.no_distortion_px (one pair, 0.75 px) or sequence_class.NO_DISTORTION_PX (a sequence, 0.25 px).

    Class 1 is ]0, 14.4 / 4] px at 320 x 424 (Delta_top = 14.39 px, section 6), starting at the threshold.
    """
    cfg = LensdistConfig()
    d = torch.tensor([0.2, 0.5, 0.8, 3.0], dtype=torch.float64)
    pair = [CLASS_LABELS[int(c)] for c in estimated_class(d, d, metric="delta_avg", config=cfg)]
    seq = [
        CLASS_LABELS[int(c)]
        for c in estimated_class(d, d, metric="delta_avg", config=cfg, threshold=NO_DISTORTION_PX)
    ]
    assert pair == ["R", "R", "1", "1"] and seq == ["R", "1", "1", "1"]
    assert class_bounds("R", "delta_avg", cfg) == (0.0, 0.75)
    assert class_bounds("1", "delta_avg", cfg, 0.25) == pytest.approx((0.25, delta_top("delta_avg", cfg) / 4))
    # the sequence rule: class 1 at 0.5 +- 0.1 px, none where the interval spans 0.25 px, whatever the pair's threshold
    assert interval_class(0.5, 0.5, (0.4, 0.6), cfg)[0] == "1"
    label, reason = interval_class(0.3, 0.3, (0.2, 0.4), cfg)
    assert label is None and "no-distortion threshold (0.25 px)" in reason
    moved = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, no_distortion_px=0.1))
    assert interval_class(0.5, 0.5, (0.4, 0.6), moved)[0] == "1"
    assert interval_class(0.3, 0.3, (0.2, 0.4), moved)[0] is None
