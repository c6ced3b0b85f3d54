"""The shared geometric primitives, on hand-worked values: the normalised frame and grids
(geometry/frame.py), phase correlation (geometry/phase.py), central differences and mean
pyramids (geometry/pyramid.py), eq. 4's factor and Newton inverse (geometry/distortion.py)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lensdist_torch.core.images import load_scene
from lensdist_torch.geometry import distortion
from lensdist_torch.geometry.distortion import radial_derivative, radial_factor, radial_inverse
from lensdist_torch.geometry.frame import (
    grid_sample_matrix,
    half_diagonal,
    level_coordinates,
    level_to_grid,
    normalized_grid,
    normalizer,
    pixel_grid,
    to_normalized,
)
from lensdist_torch.geometry.phase import phase_correlation
from lensdist_torch.geometry.pyramid import binomial_blur, central_differences, mean_pool_2x2, mean_pyramid

pytestmark = pytest.mark.usefixtures("one_thread_module")


def _apply(m: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """An affine (3, 3) matrix applied to (N, 2) points."""
    return pts @ m[:2, :2].T + m[:2, 2]


# ------------------------------------------------------------------ frame
class TestFrame:
    def test_half_diagonal(self):
        assert half_diagonal(3, 5) == pytest.approx(math.sqrt(5), abs=1e-15)  # 0.5 * hypot(4, 2)
        assert half_diagonal(320, 424) == pytest.approx(264.90, abs=0.005)  # 0.5 * sqrt(423^2 + 319^2)

    @pytest.mark.parametrize("h,w", [(320, 424), (41, 67), (2, 2)])
    def test_normalizer_maps_the_corners(self, h, w):
        r = half_diagonal(h, w)
        n = normalizer(h, w)
        assert n.dtype == torch.float64 and n.shape == (3, 3)
        corners = torch.tensor([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=torch.float64)
        u = _apply(n, corners)
        ex, ey = (w - 1) / (2 * r), (h - 1) / (2 * r)
        expected = torch.tensor([[-ex, -ey], [ex, -ey], [ex, ey], [-ex, ey]], dtype=torch.float64)
        torch.testing.assert_close(u, expected, atol=1e-15, rtol=0)
        torch.testing.assert_close(u.norm(dim=-1), torch.ones(4, dtype=torch.float64), atol=1e-15, rtol=0)
        centre = _apply(n, torch.tensor([[(w - 1) / 2, (h - 1) / 2]], dtype=torch.float64))
        assert centre.abs().max() == 0

    def test_level_coordinates_at_full_resolution(self):
        h, w = 41, 67
        u, v = level_coordinates(0, h, w, full_height=h, full_width=w)
        g = pixel_grid(h, w, torch.float64)
        ref = _apply(normalizer(h, w), g.reshape(-1, 2)).reshape(h, w, 2)
        torch.testing.assert_close(u, ref[0, :, 0], atol=1e-15, rtol=0)
        torch.testing.assert_close(v, ref[:, 0, 1], atol=1e-15, rtol=0)
        us, vs = level_coordinates(0, h, w, full_height=h, full_width=w, stride=2)
        assert torch.equal(us, u[::2]) and torch.equal(vs, v[::2]) and len(us) == 34 and len(vs) == 21

    @pytest.mark.parametrize("level", [1, 2])
    def test_level_pixels_sit_at_the_centre_of_their_means(self, level):
        """A level-l pixel x_l is the mean of full-resolution pixels 2^l x_l .. 2^l x_l + 2^l - 1."""
        h0, w0 = 41, 67  # odd: the pyramid drops the last row / column
        h, w = h0 >> level, w0 >> level
        u, v = level_coordinates(level, h, w, full_height=h0, full_width=w0)
        f = 2**level
        n = normalizer(h0, w0)
        xs = f * torch.arange(w, dtype=torch.float64) + (f - 1) / 2
        ys = f * torch.arange(h, dtype=torch.float64) + (f - 1) / 2
        torch.testing.assert_close(u, xs * n[0, 0] + n[0, 2], atol=1e-15, rtol=0)
        torch.testing.assert_close(v, ys * n[1, 1] + n[1, 2], atol=1e-15, rtol=0)

    def test_normalized_grid(self):
        h, w = 5, 7
        g = normalized_grid(0, h, w, full_height=h, full_width=w, dtype=torch.float64)
        assert g.shape == (h, w, 2) and g.dtype == torch.float64
        r = half_diagonal(h, w)
        assert g[0, 0].tolist() == pytest.approx([-3 / r, -2 / r], abs=1e-15)
        assert g[-1, -1].tolist() == pytest.approx([3 / r, 2 / r], abs=1e-15)
        assert g[2, 3].tolist() == [0.0, 0.0]
        assert normalized_grid(1, 2, 3, full_height=h, full_width=w).dtype == torch.float32

    @pytest.mark.parametrize("level", [0, 1, 2])
    def test_level_to_grid_is_grid_sample_of_the_level_pixels(self, level):
        h0, w0 = 41, 67
        h, w = h0 >> level, w0 >> level
        u, v = level_coordinates(level, h, w, full_height=h0, full_width=w0)
        sx, ox, sy, oy = level_to_grid(level, h, w, full_height=h0, full_width=w0)
        torch.testing.assert_close(sx * u + ox, torch.linspace(-1, 1, w, dtype=torch.float64), atol=1e-14, rtol=0)
        torch.testing.assert_close(sy * v + oy, torch.linspace(-1, 1, h, dtype=torch.float64), atol=1e-14, rtol=0)

    def test_pixel_grid(self):
        g = pixel_grid(3, 4)
        assert g.shape == (3, 4, 2) and g.dtype == torch.float32 and g.is_contiguous()
        assert g[2, 3].tolist() == [3.0, 2.0] and g[0, 1].tolist() == [1.0, 0.0]
        assert distortion.pixel_grid is pixel_grid and distortion.to_normalized is to_normalized

    def test_to_normalized_and_its_matrix(self):
        h, w = 5, 9
        pts = torch.tensor([[0.0, 0.0], [8.0, 4.0], [4.0, 2.0], [2.0, 1.0]], dtype=torch.float64)
        out = to_normalized(pts, h, w)
        assert out.tolist() == [[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0], [-0.5, -0.5]]
        torch.testing.assert_close(_apply(grid_sample_matrix(h, w), pts), out, atol=1e-15, rtol=0)
        assert to_normalized(pts.float(), h, w).dtype == torch.float32


# ------------------------------------------------------------------ phase correlation
@pytest.fixture(scope="module")
def texture() -> torch.Tensor:
    return load_scene("gravel")[0, 0, 100:165, 120:217].contiguous()  # 65 x 97


class TestPhaseCorrelation:
    @pytest.mark.parametrize("t", [(0, 0), (3, -2), (-7, 5), (20, 11)])
    def test_integer_shift(self, texture, t):
        a = texture[:-1, :-1]
        b = torch.roll(a, (t[1], t[0]), dims=(0, 1))  # b(p) = a(p - t): a(p) = b(p + t)
        est = phase_correlation(a[None], b[None])[0]
        assert est.tolist() == pytest.approx(list(t), abs=0.02)
        est = phase_correlation(b[None], a[None])[0]  # the other way round
        assert est.tolist() == pytest.approx([-t[0], -t[1]], abs=0.02)

    def test_half_pixel_shift(self, texture):
        """b(p) = (a(p) + a(p + e)) / 2 = a(p + e / 2) for a bilinear a: t = -e / 2."""
        a = texture[:-1, :-1]
        bx = 0.5 * (texture[:-1, :-1] + texture[:-1, 1:])
        by = 0.5 * (texture[:-1, :-1] + texture[1:, :-1])
        est = phase_correlation(torch.stack([a, a]), torch.stack([bx, by]))
        torch.testing.assert_close(est, torch.tensor([[-0.5, 0.0], [0.0, -0.5]]), atol=0.02, rtol=0)

    def test_quarter_pixel_shift_moves_off_the_integer(self, texture):
        a = texture[:-1, :-1]
        b = 0.75 * texture[:-1, :-1] + 0.25 * texture[:-1, 1:]  # ~ a(p + 0.25)
        tx, ty = phase_correlation(a[None], b[None])[0].tolist()
        assert -0.25 <= tx < -0.05 and abs(ty) < 0.01

    def test_batch_dtype_and_independence(self, texture):
        a = texture[:-1, :-1]
        b = torch.stack([torch.roll(a, 3, dims=1), torch.roll(a, -4, dims=0)])
        est = phase_correlation(torch.stack([a, a]), b)
        assert est.shape == (2, 2) and est.dtype == torch.float32
        # alone or in a batch, the same shift to float32 rounding (a batched FFT may take another kernel: AVX-512)
        torch.testing.assert_close(est[1:], phase_correlation(a[None], b[1:]), atol=1e-6, rtol=0)
        assert phase_correlation(a[None].double(), b[:1].double()).dtype == torch.float64


# ------------------------------------------------------------------ central differences, pyramid
class TestPyramid:
    def test_central_differences_by_hand(self):
        """I(x, y) = x^2 + 3 y: d/dx = 2x inside, (I(1) - I(0)) / 2 = 0.5 and (16 - 9) / 2 = 3.5
        at the replicated borders; d/dy = 3 inside, 1.5 on the first and last rows."""
        y, x = torch.meshgrid(torch.arange(4.0), torch.arange(5.0), indexing="ij")
        d = central_differences((x**2 + 3 * y)[None])
        assert d.shape == (1, 4, 2, 5)
        assert d[0, :, 0].tolist() == [[0.5, 2.0, 4.0, 6.0, 3.5]] * 4
        assert d[0, :, 1].tolist() == [[1.5] * 5, [3.0] * 5, [3.0] * 5, [1.5] * 5]

    @pytest.mark.parametrize("stride", [2, 3])
    def test_strided_and_into_a_buffer(self, stride):
        img = torch.rand(2, 13, 17)
        full = central_differences(img)
        h, w = len(range(0, 13, stride)), len(range(0, 17, stride))
        buf = torch.empty(2, h, 2, w)
        out = central_differences(img, stride, out=buf)
        assert out.data_ptr() == buf.data_ptr()
        assert torch.equal(out, full[:, ::stride, :, ::stride])

    @pytest.mark.parametrize("h,w", [(16, 24), (17, 25), (5, 3)])
    def test_halve_is_avg_pool(self, h, w):
        img = torch.rand(3, 1, h, w)
        torch.testing.assert_close(mean_pool_2x2(img), F.avg_pool2d(img, 2), atol=1e-6, rtol=0)
        torch.testing.assert_close(mean_pool_2x2(img[:, 0]), F.avg_pool2d(img, 2)[:, 0], atol=1e-6, rtol=0)

    def test_mean_pyramid(self):
        img = torch.rand(2, 1, 41, 67)
        pyr = mean_pyramid(img, 3)
        assert len(pyr) == 3 and pyr[0] is img
        assert [tuple(p.shape[-2:]) for p in pyr] == [(41, 67), (20, 33), (10, 16)]
        torch.testing.assert_close(pyr[2], F.avg_pool2d(F.avg_pool2d(img, 2), 2), atol=1e-6, rtol=0)
        assert mean_pyramid(img, 1) == [img]

    def test_binomial_blur_is_the_replicate_padded_convolution(self):
        img = torch.rand(2, 9, 12, dtype=torch.float64)
        k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], dtype=torch.float64)
        ref = F.conv2d(F.pad(img[:, None], (2, 2, 2, 2), mode="replicate"), (torch.outer(k, k) / 256)[None, None])
        out = torch.empty_like(img)
        assert binomial_blur(img, out) is out
        torch.testing.assert_close(out, ref[:, 0], atol=1e-14, rtol=0)
        work = torch.empty(2, 9, 16, dtype=torch.float64)
        assert torch.equal(binomial_blur(img, torch.empty_like(img), work), out)
        flat = torch.full((1, 6, 7), 0.25)
        assert torch.equal(binomial_blur(flat, torch.empty_like(flat)), flat)  # constants stay


# ------------------------------------------------------------------ eq. 4: factor and inverse
class TestRadial:
    def test_by_hand(self):
        """r = 2, k2 = 0.01, k4 = 0.001: factor 1 + 0.04 + 0.016 = 1.056, derivative
        1 + 0.12 + 0.08 = 1.2; the ideal radius 2 x 1.056 = 2.112 inverts to 2."""
        r2 = torch.tensor([4.0], dtype=torch.float64)
        assert float(radial_factor(r2, 0.01, 0.001)) == pytest.approx(1.056, abs=1e-15)
        assert float(radial_derivative(r2, 0.01, 0.001)) == pytest.approx(1.2, abs=1e-15)
        r, rho = radial_inverse(torch.tensor([2.112**2], dtype=torch.float64), 0.01, 0.001)
        assert float(rho) == pytest.approx(2.112, abs=1e-15) and float(r) == pytest.approx(2.0, abs=1e-12)

    @pytest.mark.parametrize("a,b", [(0.18, 0.12), (0.1, 0.0), (0.0, 0.12), (-0.12, -0.03), (0.18, -0.1), (1e-4, 1e-5)])
    def test_newton_round_trips_the_factor(self, a, b):
        """Normalised units, |u| up to 1.05 (the image plus a margin): 8 steps, float64, 1e-9."""
        r = torch.linspace(0, 1.05, 2001, dtype=torch.float64)
        rho = r * radial_factor(r * r, a, b)
        back, rho_ = radial_inverse(rho * rho, a, b, iterations=8)
        assert float((back - r)[1:].abs().max()) < 1e-9
        torch.testing.assert_close(rho_[1:], rho[1:], atol=1e-15, rtol=0)

    def test_newton_in_pixels_with_batched_coefficients(self):
        r = torch.linspace(0, 265.0, 1001, dtype=torch.float64).expand(3, -1)
        k2 = torch.tensor([[2.5e-6], [1e-6], [0.0]], dtype=torch.float64)
        k4 = torch.tensor([[2.5e-11], [0.0], [2.5e-11]], dtype=torch.float64)
        rho = r * radial_factor(r * r, k2, k4)
        back, _ = radial_inverse(rho * rho, k2, k4)
        assert float((back - r)[:, 1:].abs().max()) < 1e-9

    def test_centre_stays_finite(self):
        r, rho = radial_inverse(torch.zeros(3, dtype=torch.float64), 0.18, 0.12)
        assert torch.equal(rho, torch.ones(3, dtype=torch.float64)) and torch.isfinite(r / rho).all()

    def test_derivative_is_that_of_the_radius(self):
        r = torch.linspace(0.1, 1.0, 50, dtype=torch.float64)
        a, b, e = 0.15, -0.05, 1e-6
        num = ((r + e) * radial_factor((r + e) ** 2, a, b) - (r - e) * radial_factor((r - e) ** 2, a, b)) / (2 * e)
        torch.testing.assert_close(radial_derivative(r * r, a, b), num, atol=1e-8, rtol=0)
