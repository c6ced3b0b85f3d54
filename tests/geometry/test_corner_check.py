"""The chessboard check of benchmarks/bench_real_calibration.py, in both units (undistorted and image pixels).

Each view's corners are undistorted by a lens, one homography is fitted to them and its RMS is
reported; ``image_px`` takes each misfit back into the image's pixels through the lens map's
Jacobian. Checked on maps whose answer is known by hand and on corners rendered through an OpenCV
lens with noise of a known size.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

cv2 = pytest.importorskip("cv2")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from bench_real_calibration import homography_rms  # noqa: E402

from lensdist_torch.geometry.opencv_model import opencv_distort_normalized  # noqa: E402

K = [[500.0, 0.0, 330.0], [0.0, 500.0, 245.0], [0.0, 0.0, 1.0]]
DIST = [-0.25, 0.07, 0.0, 0.0, -0.008]


def _board() -> torch.Tensor:
    ys, xs = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
    return torch.stack([xs.reshape(-1), ys.reshape(-1)], 1).double()


def _views(noise: float, seed: int = 0) -> dict:
    """Corners of three views of the board through (K, DIST), with Gaussian noise of ``noise`` px per coordinate."""
    g = torch.Generator().manual_seed(seed)
    board = torch.cat([_board(), torch.ones(48, 1, dtype=torch.float64)], 1)
    views = {}
    for i, hm in enumerate(([70.0, 2, 85, -3, 71, 70, 1e-4, 2e-4], [62.0, -5, 110, 4, 63, 80, -2e-4, 1e-4],
                            [75.0, 1, 60, 0, 75, 55, 0, 0])):  # the board over most of the 660 x 490 frame
        q = board @ torch.tensor([*hm, 1.0], dtype=torch.float64).reshape(3, 3).T
        ideal = q[:, :2] / q[:, 2:]
        k = torch.tensor(K, dtype=torch.float64)
        x = (ideal - k[:2, 2]) / k[0, 0]
        img = opencv_distort_normalized(x, torch.tensor(DIST, dtype=torch.float64)) * k[0, 0] + k[:2, 2]
        views[f"v{i}"] = (img + noise * torch.randn(img.shape, generator=g, dtype=torch.float64)).tolist()
    return {"object_points_xy": _board().tolist(), "image_points": views}


def test_a_uniform_scale_divides_the_image_rms_by_its_factor():
    corners = _views(0.5)
    plain = homography_rms(None, None, corners, lambda p: p)
    assert homography_rms(None, None, corners, lambda p: p, image_px=True) == pytest.approx(plain, rel=1e-6)
    doubled = homography_rms(None, None, corners, lambda p: 2 * p + 3.0)
    assert doubled == pytest.approx([2 * v for v in plain], rel=1e-6)  # the undistorted frame magnifies
    assert homography_rms(None, None, corners, lambda p: 2 * p + 3.0, image_px=True) == pytest.approx(plain, rel=1e-5)


def test_the_true_lens_leaves_only_the_noise_in_image_pixels():
    assert max(homography_rms(K, DIST, _views(0.0), image_px=True)) < 1e-6  # no noise: every corner on its homography
    sigma = 0.4
    rms = homography_rms(K, DIST, _views(sigma, seed=3), image_px=True)
    # a least-squares fit of 8 parameters to 96 coordinates leaves sqrt((96 - 8) / 96) of the noise,
    # per corner 2 coordinates
    expected = sigma * math.sqrt(2 * (96 - 8) / 96)
    assert all(0.7 * expected < r < 1.3 * expected for r in rms), (rms, expected)
    # the undistorted frame magnifies this barrel lens's edges: its RMS is larger
    assert all(u > r for u, r in zip(homography_rms(K, DIST, _views(sigma, seed=3)), rms))


def test_a_wrong_lens_shows_in_both_units():
    for px in (False, True):  # no lens where there is one: the board's lines stay bent by pixels
        assert min(homography_rms(K, [0.0] * 5, _views(0.0), image_px=px)) > 2.0


def test_the_boards_region_holds_the_points_inside_some_views_corners():
    from bench_real_calibration import inside_boards

    square = {"image_points": {"a": [[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0], [20.0, 20.0]],
                               "b": [[50.0, 50.0], [60.0, 50.0], [55.0, 60.0]]}}
    points = torch.tensor([[20.0, 20.0], [10.0, 20.0], [31.0, 20.0], [55.0, 55.0], [55.0, 61.0], [40.0, 40.0]])
    assert inside_boards(points, square).tolist() == [True, True, False, True, False, False]  # edges count


def test_the_chessboard_again_finds_the_lens_the_corners_were_drawn_through():
    """Corners projected by OpenCV through (K, DIST) from five tilted poses: both models find the lens's Delta_avg."""
    import numpy as np
    from bench_real_calibration import truth_models

    from lensdist_torch.geometry.opencv_model import grid_points, opencv_delta

    board = np.array([[x, y, 0.0] for y in range(6) for x in range(8)])
    views = {}
    for i, (rx, ry) in enumerate([(0.0, 0.0), (0.4, 0.0), (-0.4, 0.1), (0.1, 0.45), (-0.2, -0.4)]):
        img, _ = cv2.projectPoints(board, np.array([rx, ry, 0.05]), np.array([-3.5, -2.5, 7.5]), np.array(K),
                                   np.array(DIST))
        views[f"v{i}"] = img.reshape(-1, 2).tolist()
    corners = {"object_points_xy": board[:, :2].tolist(), "image_points": views}
    again = truth_models(corners, (490, 660), {"frame": grid_points(490, 660, 8)})
    truth = opencv_delta(torch.tensor(K), torch.tensor(DIST), 490, 660, step=8)["delta_avg_px"]
    for model in again.values():
        assert model["rms_px"] < 1e-3 and model["delta_avg_frame_px"] == pytest.approx(truth, rel=0.01)
    assert again["opencv, 5 coefficients"]["dist_coeffs"] == pytest.approx(DIST, abs=1e-3)
