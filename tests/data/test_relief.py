"""The relief renderer (lensdist_torch.data.relief) against the pinhole camera's own projection.

A camera at height A above the ground, looking straight down from the nadir X_c, sees a point
X raised by h = rho(X) A where a flat scene would be seen at X_c + (X - X_c) A / (A - h)
(similar triangles). The renderer inverts that map; these tests project its answers forward
with that formula and check the parallax a camera would see: proportional to the baseline,
none for a rotation about the optical axis.
"""

from __future__ import annotations

import math

import pytest
import torch

from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence, tilted_offsets
from lensdist_torch.data.relief import HeightField, draw_height_field, relief_fraction, relief_samples

F64 = torch.float64
REGION = (0.0, 400.0, 0.0, 300.0)


def field(relief: float = 0.03, seed: int = 0) -> HeightField:
    return draw_height_field(torch.Generator().manual_seed(seed), REGION, relief)


def project(x, y, nadir, f: HeightField):
    """Where a flat scene would be seen: X_c + (X - X_c) / (1 - rho(X)) (module docstring)."""
    rho = relief_fraction(f, x, y)
    return nadir[0] + (x - nadir[0]) / (1 - rho), nadir[1] + (y - nadir[1]) / (1 - rho)


def grid(n: int = 21):
    xs, ys = torch.meshgrid(torch.linspace(60, 340, n, dtype=F64), torch.linspace(50, 250, n, dtype=F64), indexing="xy")
    return xs, ys


class TestHeightField:
    @pytest.mark.parametrize("relief", [0.01, 0.03, 0.1])
    def test_peak_is_the_relief(self, relief):
        f = field(relief)
        xs, ys = torch.meshgrid(torch.linspace(0, 400, 64, dtype=F64), torch.linspace(0, 300, 64, dtype=F64), indexing="xy")
        assert float(relief_fraction(f, xs, ys).abs().max()) == pytest.approx(relief, rel=1e-12)

    def test_zero_relief_is_flat(self):
        f = field(0.0)
        xs, ys = grid()
        assert float(relief_fraction(f, xs, ys).abs().max()) == 0.0

    @pytest.mark.bad_input
    @pytest.mark.parametrize("relief", [-0.01, 0.5, 2.0, math.nan])
    def test_relief_out_of_range(self, relief):
        with pytest.raises(ValueError, match=r"^relief must be a fraction of the camera's height in \[0, 0.5\)"):
            field(relief)

    def test_gaussian_value_by_hand(self):
        # one bump of peak 0.02 and sigma 10 at (5, 5): at (5, 15), one sigma away, 0.02 e^(-1/2)
        f = HeightField(torch.tensor([[5.0, 5.0]], dtype=F64), torch.tensor([10.0], dtype=F64), torch.tensor([0.02], dtype=F64))
        v = relief_fraction(f, torch.tensor(5.0, dtype=F64), torch.tensor(15.0, dtype=F64))
        assert float(v) == pytest.approx(0.02 * math.exp(-0.5), rel=1e-14)


class TestProjection:
    def test_constant_rise_by_hand(self):
        # a plateau of 10 % (a bump far wider than the view): every point seen 10 % nearer the
        # nadir, exactly, whatever the iteration count
        f = HeightField(torch.tensor([[0.0, 0.0]], dtype=F64), torch.tensor([1e9], dtype=F64), torch.tensor([0.1], dtype=F64))
        x, y = relief_samples(torch.tensor([110.0, 50.0], dtype=F64), torch.tensor([20.0, -30.0], dtype=F64), (10.0, 20.0), f)
        assert torch.allclose(x, torch.tensor([100.0, 46.0], dtype=F64), atol=1e-9, rtol=0)
        assert torch.allclose(y, torch.tensor([20.0, -25.0], dtype=F64), atol=1e-9, rtol=0)

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_forward_projection_returns_the_flat_position(self, seed):
        f, nadir = field(0.03, seed), (200.0, 150.0)
        xs, ys = grid()
        gx, gy = relief_samples(xs, ys, nadir, f)
        px, py = project(gx, gy, nadir, f)
        assert float((px - xs).abs().max()) < 1e-4 and float((py - ys).abs().max()) < 1e-4
        # and the relief moved the points by up to a few % of their distance to the nadir
        moved = torch.hypot(gx - xs, gy - ys).max()
        assert 0.5 < float(moved) < 0.03 * 1.05 * math.hypot(140, 100)

    def test_flat_scene_is_unchanged(self):
        xs, ys = grid()
        assert relief_samples(xs, ys, (0.0, 0.0), None) == (xs, ys)


class TestParallax:
    """Two views of one ground point: where each sees it, against where a plane would put it."""

    def _views(self, nadir_a, nadir_b, scale_b: float = 1.0):
        f = field(0.03, 4)
        xs, ys = grid()
        gx, gy = relief_samples(xs, ys, nadir_a, f)  # the ground points view A sees on its grid
        bx, by = project(gx, gy, nadir_b, f)  # where view B sees them (flat-scene positions)
        # a plane would be seen by B where A sees it, moved with the camera: B's flat position of
        # a ground point at height 0 equals A's, so the parallax is the difference
        return (bx - xs), (by - ys), relief_fraction(f, gx, gy)

    @pytest.mark.parametrize("baseline", [(10.0, 0.0), (0.0, 20.0), (7.0, -7.0)])
    def test_translation_parallax_is_baseline_times_height(self, baseline):
        a = (200.0, 150.0)
        b = (a[0] + baseline[0], a[1] + baseline[1])
        dx, dy, rho = self._views(a, b)
        # X_b + (X - X_b) / (1 - rho) - (X_a + (X - X_a) / (1 - rho)) = -baseline rho / (1 - rho)
        k = -rho / (1 - rho)
        assert torch.allclose(dx, baseline[0] * k, atol=1e-4, rtol=0)
        assert torch.allclose(dy, baseline[1] * k, atol=1e-4, rtol=0)
        assert float(torch.hypot(dx, dy).max()) > 0.2 * math.hypot(*baseline) * 0.03  # not vanishing

    def test_no_baseline_no_parallax(self):
        # the same nadir and height: a rotation about the optical axis only maps the flat
        # positions by a homography about the nadir, which this covers
        dx, dy, _ = self._views((200.0, 150.0), (200.0, 150.0))
        assert float(torch.hypot(dx, dy).max()) < 1e-4


class TestSequence:
    def test_a_lower_camera_sees_radial_parallax(self):
        # frames 0 and 1 at the same place, the second from a lower camera (altitude on): with a
        # flat scene the second is a zoom of the first; with relief the hills grow faster than
        # the ground (their fraction of the camera's height rises), so the relief's effect on
        # the two frames differs
        kw = dict(size=(96, 128), seed=11, step_px=(0.0, 0.0), jitter_px=0.0, rotation_deg=0.0, altitude=0.2)
        flat, _ = synthetic_sequence(2, 0.0, 0.0, **kw)
        raised, _ = synthetic_sequence(2, 0.0, 0.0, relief=0.03, **kw)
        # the relief's own effect on each frame, (raised - flat), differs between the frames
        d0, d1 = (raised[0] - flat[0]).abs().mean(), (raised[1] - flat[1]).abs().mean()
        assert float(d0) > 1e-3 and float(d1) > 1e-3
        assert float(((raised[1] - flat[1]) - (raised[0] - flat[0])).abs().mean()) > 1e-3

    def test_relief_changes_the_frames_but_not_the_flat_ones(self):
        flat, _ = synthetic_sequence(3, 1e-6, 0.0, size=(64, 80), seed=2)
        again, _ = synthetic_sequence(3, 1e-6, 0.0, size=(64, 80), seed=2, relief=0.0, altitude=0.0)
        assert torch.equal(flat, again)
        raised, _ = synthetic_sequence(3, 1e-6, 0.0, size=(64, 80), seed=2, relief=0.03)
        assert float((raised - flat).abs().mean()) > 0.01

    def test_parallax_grows_with_the_baseline(self):
        """Ideal frames of a relief scene under pure translation: the first frame against the
        k-th, registered by the best global translation (phase correlation is not needed: the
        steps are known and integer), leave a residual that grows with the step."""
        resid = []
        for step in (0.0, 16.0, 48.0):
            seq, _ = synthetic_sequence(2, 0.0, 0.0, size=(96, 128), seed=3, step_px=(step, step), jitter_px=0.0,
                                        rotation_deg=0.0, relief=0.03)
            s = int(step)
            a, b = seq[0, 0, s:, :], seq[1, 0, : 96 - s, :]
            resid.append(float((a - b).abs().mean()))
        assert resid[0] < 1e-6  # no baseline: identical frames
        assert resid[1] > 1e-3 and resid[2] > 1.5 * resid[1]


class TestObliqueViews:
    """``synthetic_sequence(..., tilt_deg=...)``: frames whose optical axes are not parallel."""

    @pytest.mark.parametrize("pitch,roll", [(0.1, 0.0), (0.0, -0.2), (0.15, 0.12), (-0.3, 0.25)])
    def test_the_ground_point_projects_back_to_its_pixel(self, pitch, roll):
        """The tilted camera (kornia's rotations about x by pitch, then y by roll) sees the ground point
        (o, f) of the upright frame at the pixel it came from."""
        from kornia.geometry.conversions import axis_angle_to_rotation_matrix

        rel = torch.rand(50, 2, generator=torch.Generator().manual_seed(0), dtype=F64) * 400 - 200
        focal = 424.0
        o = tilted_offsets(rel, focal, pitch, roll)
        rx = axis_angle_to_rotation_matrix(torch.tensor([[pitch, 0.0, 0.0]], dtype=F64))[0]
        ry = axis_angle_to_rotation_matrix(torch.tensor([[0.0, roll, 0.0]], dtype=F64))[0]
        ground = torch.cat([o, torch.full((50, 1), focal, dtype=F64)], 1)
        cam = ground @ (ry @ rx)  # R^T p for each row p
        assert torch.allclose(focal * cam[:, :2] / cam[:, 2:], rel, atol=1e-9)

    def test_an_upright_camera_is_the_identity(self):
        rel = torch.tensor([[10.0, -20.0], [150.0, 90.0]], dtype=F64)
        assert torch.allclose(tilted_offsets(rel, 300.0, 0.0, 0.0), rel, atol=1e-12)

    def test_no_tilt_draws_nothing_and_a_tilt_changes_every_frame(self):
        kw = dict(size=(64, 80), seed=5, relief=0.02, rotation_deg=3.0, altitude=0.1)
        upright, _ = synthetic_sequence(3, 1e-6, 0.0, **kw)
        assert torch.equal(upright, synthetic_sequence(3, 1e-6, 0.0, tilt_deg=0.0, **kw)[0])
        oblique, _ = synthetic_sequence(3, 1e-6, 0.0, tilt_deg=8.0, **kw)
        assert all(float((oblique[i] - upright[i]).abs().mean()) > 0.01 for i in range(3))

    @pytest.mark.parametrize("tilt", [-1.0, float("nan"), 45.0])
    def test_a_tilt_out_of_range_is_one_line(self, tilt):
        with pytest.raises(ValueError, match="tilt_deg must be in"):
            synthetic_sequence(2, 0.0, 0.0, size=(32, 40), tilt_deg=tilt)
