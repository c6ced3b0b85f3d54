"""Sub-pixel matches: a plane rendered in closed form through a known lens, the true partners known exactly."""

import math

import pytest
import torch

from lensdist_torch.calibration.match_refinement import _prepared, align_patches, local_affines, refine_matches
from lensdist_torch.calibration.matches import PlanarMatches
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.geometry.radial_lens import lens_distorted_points, lens_ideal_points

SIZE = (240, 320)
LENS, CENTRE = [0.35, -0.08], (166.0, 114.0)  # barrel, 6.5 px off the frame centre


def _texture(p: torch.Tensor) -> torch.Tensor:
    """A smooth plane texture in [0, 1] at (..., 2) plane points (several orientations and scales)."""
    x, y = p[..., 0], p[..., 1]
    v = (torch.sin(x / 3.1) * torch.cos(y / 4.3) + 0.6 * torch.sin((0.8 * x + 0.6 * y) / 2.2)
         + 0.4 * torch.cos((x - 1.3 * y) / 6.7))
    return (v + 2.0) / 4.0


def _homography(angle: float, scale: float, tx: float, ty: float, px: float = 0.0) -> torch.Tensor:
    c, s = scale * math.cos(angle), scale * math.sin(angle)
    return torch.tensor([[c, -s, tx], [s, c, ty], [px, 0.0, 1.0]], dtype=torch.float64)


def _render(plane_to_ideal: torch.Tensor) -> torch.Tensor:
    """A view of the plane through LENS: each pixel's ideal point taken back onto the plane, no interpolation."""
    h, w = SIZE
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    pix = torch.stack([xx, yy], -1).reshape(-1, 2)
    plane = apply_homography(torch.linalg.inv(plane_to_ideal)[None], lens_ideal_points(pix, LENS, h, w, centre=CENTRE))[
        0
    ]
    return _texture(plane).reshape(h, w).float()


def _true_partner(x1: torch.Tensor, h01: torch.Tensor) -> torch.Tensor:
    h, w = SIZE
    return lens_distorted_points(
        apply_homography(h01[None], lens_ideal_points(x1, LENS, h, w, centre=CENTRE))[0], LENS, h, w, centre=CENTRE
    )[0]


def test_align_patches_recovers_a_shift_under_a_change_of_exposure():
    yy, xx = torch.meshgrid(torch.arange(80.0), torch.arange(100.0), indexing="ij")
    one = _texture(torch.stack([xx, yy], -1).double()).float()
    two = (
        0.7 * _texture(torch.stack([xx - 1.37, yy + 2.21], -1).double()) + 0.12
    ).float()  # content moved by (1.37, -2.21)
    x1 = torch.tensor([[40.0, 30.0], [55.5, 41.25], [30.0, 50.0]], dtype=torch.float64)
    start = x1 + torch.tensor([1.37, -2.21], dtype=torch.float64) + torch.tensor([[0.6, -0.5], [-0.7, 0.4], [0.3, 0.8]],
                                                                                 dtype=torch.float64)
    out, ncc, ok = align_patches(
        _prepared(one, 1.0), _prepared(two, 1.0), x1, start, affine=torch.eye(2, dtype=torch.float64).expand(3, 2, 2)
    )
    assert ok.all() and (ncc > 0.999).all()
    # bilinear sampling of the 14 px waves errs by up to 0.008 in intensity: about 0.02 px here (0.8 px before)
    assert (out - x1 - torch.tensor([1.37, -2.21], dtype=torch.float64)).abs().max() < 0.03


def test_a_flat_patch_is_not_kept():
    flat = _prepared(torch.full((60, 60), 0.5), 0.0)
    x = torch.tensor([[30.0, 30.0]], dtype=torch.float64)
    _, _, ok = align_patches(flat, flat, x, x + 0.5, affine=torch.eye(2, dtype=torch.float64)[None])
    assert not ok.any()


def test_local_affines_are_the_derivative_of_the_lens_homography_lens_map():
    h, w = SIZE
    hm = _homography(0.1, 1.08, 12.0, -7.0, px=2e-4)
    x = torch.tensor([[20.0, 30.0], [160.0, 120.0], [300.0, 220.0]], dtype=torch.float64)

    def f(p):
        u = lens_ideal_points(p[None], LENS, h, w, centre=CENTRE)
        return lens_distorted_points(apply_homography(hm[None], u)[0], LENS, h, w, centre=CENTRE)[0][0]

    exact = torch.stack([torch.func.jacfwd(f)(p) for p in x])  # forward-mode AD through the Newton inverse
    assert (local_affines(x, hm, LENS, centre=CENTRE, size=SIZE) - exact).abs().max() < 1e-4
    assert not torch.allclose(exact[0], torch.eye(2, dtype=torch.float64) * 1.08, atol=1e-2)  # the lens bends it


@pytest.fixture(scope="module")
def scene():
    """Two views of the plane through LENS (a 6 % scale change, a turn, a tilt) and 150 points of the first."""
    h0, h1 = _homography(0.0, 1.0, 0.0, 0.0), _homography(0.12, 1.06, -9.0, 6.0, px=1e-4)
    g = torch.Generator().manual_seed(0)
    x1 = torch.rand(150, 2, generator=g, dtype=torch.float64) * torch.tensor([260.0, 180.0], dtype=torch.float64) + 30
    h01 = h1 @ torch.linalg.inv(h0)
    return [_render(h0), _render(h1)], x1, _true_partner(x1, h01), h01, g


def test_refined_matches_are_the_true_partners(scene):
    images, x1, truth, h01, g = scene
    noisy = truth + 0.8 * torch.randn(truth.shape, generator=g, dtype=torch.float64).clamp(-2, 2)  # a keypoint's error
    m = PlanarMatches(
        x1, noisy, torch.zeros(len(x1), dtype=torch.long), torch.tensor([0]), torch.tensor([1]), ("a", "b")
    )
    out, info = refine_matches(m, lambda v: images[v], {(0, 1): h01}, LENS, centre=CENTRE, size=SIZE)
    kept = (x1[:, None] == out.x1[None]).all(-1).any(1)
    error = (out.x2 - truth[kept]).norm(dim=1)
    assert info["kept"] == len(out.pair) >= 0.8 * len(x1) and out.first.tolist() == [0] and out.second.tolist() == [1]
    assert float(error.median()) < 0.03 and float(error.max()) < 0.15  # from 0.8 px of noise
    assert float((noisy[kept] - truth[kept]).norm(dim=1).median()) > 0.8
    # with the lens left out of the local map the patches still align near the centre, but less well at the edges
    plain, _ = refine_matches(m, lambda v: images[v], {(0, 1): h01}, [0.0], centre=CENTRE, size=SIZE)
    assert len(plain.pair) <= len(out.pair)


def test_pairs_without_a_homography_are_dropped_and_a_wrong_size_refused(scene):
    images, x1, truth, h01, _ = scene
    m = PlanarMatches(
        x1, truth, torch.zeros(len(x1), dtype=torch.long), torch.tensor([0]), torch.tensor([1]), ("a", "b")
    )
    out, info = refine_matches(m, lambda v: images[v], {}, LENS, centre=CENTRE, size=SIZE)
    assert len(out.pair) == 0 and len(out.first) == 0 and info["kept"] == 0 and math.isnan(info["median_shift_px"])
    few = refine_matches(m, lambda v: images[v], {(0, 1): h01}, LENS, centre=CENTRE, size=SIZE, min_matches=200)
    assert len(few[0].first) == 0  # more than the pair has: dropped
    with pytest.raises(ValueError, match=r"^images: view 0 is \(120, 160\), expected"):
        refine_matches(m, lambda v: images[v][::2, ::2], {(0, 1): h01}, LENS, centre=CENTRE, size=SIZE)
