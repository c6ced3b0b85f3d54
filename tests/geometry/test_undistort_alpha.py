"""Issue 22, item 4: undistort's output view chosen as OpenCV's getOptimalNewCameraMatrix(alpha),
checked against cv2 for eq. 4 lenses expressed as OpenCV coefficients, and the new camera matrix
written beside the frames (undistortion.json)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lensdist_torch import cli
from lensdist_torch.core.png import encode_png, to_uint8
from lensdist_torch.geometry.distortion import render_distorted
from lensdist_torch.geometry.opencv_model import opencv_export
from lensdist_torch.geometry.undistort import optimal_view, undistort_image, undistortion_grid

cv2 = pytest.importorskip("cv2")

H, W = 320, 424
LENSES = [(2e-6, 0.0), (-2e-6, 0.0), (1e-6, 1e-11), (-1e-6, -5e-12)]  # barrel, pincushion, with k4


def _new_matrix(k2, k4, alpha):
    cv = opencv_export(k2, k4, H, W)
    f, cx, cy = cv["camera_matrix"][0][0], cv["camera_matrix"][0][2], cv["camera_matrix"][1][2]
    sx, sy, tx, ty = optimal_view(k2, k4, H, W, alpha=alpha)
    return np.array(cv["camera_matrix"]), np.array(cv["dist_coeffs"]), np.array(
        [[sx * f, 0, sx * cx + tx], [0, sy * f, sy * cy + ty], [0, 0, 1]])


@pytest.mark.parametrize("k2, k4", LENSES)
@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0])
def test_the_new_camera_matrix_is_opencvs(k2, k4, alpha):
    K, dist, ours = _new_matrix(k2, k4, alpha)
    theirs, _ = cv2.getOptimalNewCameraMatrix(K, dist, (W, H), alpha)
    # where the frame's edge lands: a focal length error times the normalised half width
    half = np.array([(W - 1) / 2, (H - 1) / 2]) / K[0, 0]
    edge = np.abs(np.diag(ours)[:2] - np.diag(theirs)[:2]) * half
    assert edge.max() < 1.0 and np.abs(ours[:2, 2] - theirs[:2, 2]).max() < 0.5, (ours, theirs)


@pytest.mark.parametrize("k2, k4", LENSES)
def test_alpha_0_only_valid_pixels_alpha_1_every_source_pixel(k2, k4):
    _, valid0 = undistortion_grid(k2, k4, H, W, dtype=torch.float64, view=optimal_view(k2, k4, H, W, alpha=0.0))
    assert valid0[0, 0, 1:-1, 1:-1].all()  # every pixel valid (the outermost ring within rounding)
    sx, sy, tx, ty = optimal_view(k2, k4, H, W, alpha=1.0)
    _, valid1 = undistortion_grid(k2, k4, H, W, dtype=torch.float64, view=(sx, sy, tx, ty))
    rows, cols = valid1[0, 0].any(1).nonzero(), valid1[0, 0].any(0).nonzero()
    # the undistorted frame spans the output: its valid region touches all four edges
    assert int(rows.min()) <= 1 and int(rows.max()) >= H - 2 and int(cols.min()) <= 1 and int(cols.max()) >= W - 2
    assert float(valid1.mean()) < 1.0 or (k2, k4) == (0.0, 0.0)


@pytest.mark.parametrize("k2, k4", [(2e-6, 0.0), (-2e-6, 0.0)])
@pytest.mark.parametrize("alpha", [0.0, 1.0])
def test_the_frames_are_cv2_undistorts(k2, k4, alpha):
    """cv2.undistort(frame, K, dist, newCameraMatrix=...) with OpenCV's fitted model: the same frame."""
    g = torch.Generator().manual_seed(0)
    ideal = torch.nn.functional.interpolate(torch.rand(1, 1, H // 8, W // 8, generator=g), (H, W), mode="bicubic",
                                            align_corners=True).clamp(0, 1)
    frame = render_distorted(ideal, torch.tensor([k2]), torch.tensor([k4]))
    ours, valid = undistort_image(frame, k2, k4, view=optimal_view(k2, k4, H, W, alpha=alpha))
    K, dist, new = _new_matrix(k2, k4, alpha)
    theirs = cv2.undistort(frame[0, 0].numpy().astype(np.float32), K, dist, newCameraMatrix=new)
    inner = valid[0, 0].numpy() > 0
    inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
    assert np.abs(ours[0, 0].numpy() - theirs)[inner].mean() < 0.01


def test_undistort_writes_the_new_camera_beside_the_frames(tmp_path, capsys):
    k2, k4 = 2e-6, 0.0
    frames = render_distorted(torch.rand(2, 1, 64, 80), torch.tensor([k2] * 2), torch.tensor([k4] * 2))
    src = tmp_path / "frames"
    src.mkdir()
    for i, f in enumerate(frames):
        (src / f"f{i}.png").write_bytes(encode_png(to_uint8(f)))
    assert cli.main(["undistort", str(src), "--k2", str(k2), "--k4", "0", "--alpha", "1", "--out", str(tmp_path / "o"),
                     "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "alpha 1" in out and "new camera matrix: fx = " in out and "undistortion.json" in out
    cam = json.loads((tmp_path / "o" / "undistortion.json").read_text())
    assert cam["alpha"] == 1 and cam["output_size"] == [64, 80] and cam["input_size"] == [64, 80] and cam["frames"] == 2
    sx, sy, tx, ty = optimal_view(k2, k4, 64, 80, alpha=1.0)
    assert cam["view"] == pytest.approx({"sx": sx, "sy": sy, "tx": tx, "ty": ty})
    assert cam["new_camera_matrix"][0][0] == pytest.approx(sx * cam["camera_matrix"][0][0])
    assert len(cam["dist_coeffs"]) == 5 and cam["k2"] == k2
    # without --alpha: the frames keep their scale, the new camera is the old one (as before)
    assert cli.main(["undistort", str(src), "--k2", str(k2), "--k4", "0", "--out", str(tmp_path / "p"), "--quiet",
                     "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["alpha"] is None and res["camera"]["new_camera_matrix"] == res["camera"]["camera_matrix"]
    # a second run into the same folder is refused, undistortion.json included, unless --overwrite
    (tmp_path / "q").mkdir()
    (tmp_path / "q" / "undistortion.json").write_text("{}")
    assert cli.main(["undistort", str(src), "--k2", str(k2), "--k4", "0", "--out", str(tmp_path / "q"), "--quiet"]) == 2
    assert "undistortion.json exists" in capsys.readouterr().err


@pytest.mark.bad_input
@pytest.mark.parametrize("alpha", [-0.1, 1.5, "nan", True])
def test_alpha_outside_0_1_is_refused(alpha):
    with pytest.raises(ValueError, match="alpha must be a number from 0 to 1"):
        optimal_view(1e-6, 0.0, H, W, alpha=float(alpha) if isinstance(alpha, str) else alpha)
