"""Real frames through a known lens (lensdist_torch.data.relens) against OpenCV and by hand.

With no new lens (k2 = k4 = 0) the relensed frame is the calibration's undistorted view, which
OpenCV builds independently: ``cv2.initUndistortRectifyMap`` with a new camera matrix whose
principal point is the frame centre, then ``cv2.remap``. With a lens, a pixel at radius r from
the centre shows the ideal point at r (1 + k2 r^2 + k4 r^4): worked by hand below. Undistorting a
relensed frame with the library's own ``undistort_image`` gives back the plain undistorted view.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lensdist_torch.data.relens import relens_frames, relens_map
from lensdist_torch.geometry.undistort import undistort_image

cv2 = pytest.importorskip("cv2")

H, W = 120, 160
# a wide lens like the GoPro HERO4's chessboard calibration, scaled to 160 x 120
K = np.array([[70.0, 0.0, 81.4], [0.0, 70.2, 62.4], [0.0, 0.0, 1.0]])
DIST = np.array([-0.233, 0.0617, 0.0, 0.0, -0.00754])


def _texture(seed: int = 0) -> torch.Tensor:
    """A smooth random texture (1, 1, H, W) in [0, 1]: bilinear sampling of it is accurate."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 1, H // 8 + 1, W // 8 + 1, generator=g, dtype=torch.float64)
    return torch.nn.functional.interpolate(coarse, size=(H, W), mode="bicubic", align_corners=True).clamp(0, 1)


def test_no_new_lens_is_opencvs_undistorted_view():
    src = _texture()
    f = (K[0, 0] + K[1, 1]) / 2
    new_k = np.array([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]])
    mx, my = cv2.initUndistortRectifyMap(K, DIST, None, new_k, (W, H), cv2.CV_32FC1)
    ref = cv2.remap(src[0, 0].numpy().astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    out = relens_frames(src.float(), K, DIST, k2=0.0, k4=0.0)
    got = out.frames[0, 0].numpy()
    inside = (mx >= 1) & (mx <= W - 2) & (my >= 1) & (my <= H - 2)
    assert inside.mean() > 0.95 and out.valid_fraction > 0.95
    assert np.abs(got - ref)[inside].mean() < 1e-5 and np.abs(got - ref)[inside].max() < 1e-4  # seen: 1e-7, 1.2e-6
    src_pts, ok = relens_map(H, W, K, DIST, k2=0.0, k4=0.0)
    # the maps agree to float32 (seen: 8e-6 px; 1 % more k1 moves OpenCV's by 0.37 px)
    assert np.abs(src_pts[..., 0].numpy() - mx)[inside].max() < 1e-4 and np.abs(src_pts[..., 1].numpy() - my)[inside].max() < 1e-4


def test_a_new_lens_by_hand():
    # no source lens, the principal point at the centre: the map is eq. 4 itself
    centred = np.array([[100.0, 0, (W - 1) / 2], [0, 100.0, (H - 1) / 2], [0, 0, 1]])
    src, ok = relens_map(H, W, centred, np.zeros(5), k2=1e-5, k4=0.0)
    cx, cy = (W - 1) / 2, (H - 1) / 2
    # pixel x = 129, y = 59 is (49.5, -0.5) from the centre (79.5, 59.5)
    r2 = 49.5**2 + 0.5**2
    want = (cx + 49.5 * (1 + 1e-5 * r2), cy - 0.5 * (1 + 1e-5 * r2))
    assert src[59, 129].tolist() == pytest.approx(want, abs=1e-9)
    assert bool(ok[59, 129]) and not bool(ok[0, 0])  # the corner sees 9.9 % past the frame (1e-5 r^2 = 0.099)
    src4, _ = relens_map(H, W, centred, np.zeros(5), k2=0.0, k4=2e-9)
    assert src4[59, 129].tolist() == pytest.approx((cx + 49.5 * (1 + 2e-9 * r2**2), cy - 0.5 * (1 + 2e-9 * r2**2)), abs=1e-9)


def test_undistorting_a_relensed_frame_gives_the_undistorted_view():
    src = _texture(1)
    plain = relens_frames(src.float(), K, DIST, k2=0.0, k4=0.0).frames
    lensed = relens_frames(src.float(), K, DIST, k2=4e-5, k4=0.0).frames  # barrel, ~4 px at the corners of 160 x 120
    back, valid = undistort_image(lensed, [4e-5], [0.0])
    m = valid[0, 0].bool()
    m[:4], m[-4:], m[:, :4], m[:, -4:] = False, False, False, False
    assert float(m.float().mean()) > 0.7
    assert float((back - plain)[0, 0][m].abs().mean()) < 3e-3
    assert float((lensed - plain)[0, 0][m].abs().mean()) > 10 * float((back - plain)[0, 0][m].abs().mean())


def test_output_size_carries_the_lens_in_its_own_pixels():
    src = _texture(2).float()
    full = relens_frames(src, K, DIST, k2=4e-5, k4=0.0).frames
    half = relens_frames(src, K, DIST, k2=4 * 4e-5, k4=0.0, size=(H // 2, W // 2))  # k2 scales by 1 / s^2, s = 1/2
    area = torch.nn.functional.avg_pool2d(full, 2)
    assert half.frames.shape == (1, 1, H // 2, W // 2) and half.k2 == pytest.approx(1.6e-4)
    assert float((half.frames - area)[..., 4:-4, 4:-4].abs().mean()) < 5e-3


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"camera_matrix": np.eye(2)}, "camera_matrix"),
        ({"camera_matrix": np.diag([0.0, 1.0, 1.0])}, "camera_matrix"),
        ({"dist_coeffs": np.zeros(3)}, "dist_coeffs"),
        ({"dist_coeffs": np.array([np.nan, 0, 0, 0, 0])}, "dist_coeffs"),
        ({"k2": float("inf")}, "k2 and k4"),
        ({"k4": "1e-9"}, "k2 and k4"),
        ({"size": (1, 5)}, "size"),
    ],
)
def test_bad_arguments_are_named(kwargs, match):
    args = {"frames": _texture().float(), "camera_matrix": K, "dist_coeffs": DIST, "k2": 0.0, "k4": 0.0}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        relens_frames(**args)


@pytest.mark.bad_input
def test_integer_frames_are_refused():
    with pytest.raises(TypeError, match="frames"):
        relens_frames(torch.zeros(1, 1, H, W, dtype=torch.uint8), K, DIST, k2=0.0, k4=0.0)
