"""``lensdist undistort --from`` applies the answer's own lens, not eq. 4's fit of it.

A scene is distorted through a radial lens of three terms about a centre off the frame's (eq. 4's
two terms about the frame centre follow it to about a pixel), written as frames, and given with a
saved answer as ``lensdist calibrate`` writes it (``method`` "planar"). The undistorted frames
must match the scene where valid, far closer than with eq. 4's fit; bad lens fields are one-line
errors naming the field.
"""

from __future__ import annotations

import json
import math

import pytest
import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.core.images import load_scene
from lensdist_torch.core.png import encode_png
from lensdist_torch.geometry.distortion import (
    CLASS_LABELS,
    class_bounds,
    fit_eq4,
    paper_frame_delta_avg,
    sample_at_pixels,
)
from lensdist_torch.geometry.frame import pixel_grid
from lensdist_torch.geometry.opencv_model import opencv_ideal_points
from lensdist_torch.geometry.radial_lens import lens_distorted_points, lens_ideal_points
from lensdist_torch.geometry.undistort import lens_undistortion_grid, opencv_undistortion_grid
from lensdist_torch.workflows.undistort import undistort_path

H, W = 96, 128
LENS = ([0.22, 0.06, 0.03], [70.0, 41.0])  # barrel about a centre 6.5 px right of and 6.5 px above the frame's


def _scene() -> torch.Tensor:
    """The gravel scene smoothed (a quarter of the size, enlarged again): bilinear resampling twice stays exact to
    ~0.3 %."""
    small = torch.nn.functional.interpolate(load_scene("gravel"), size=(H // 4, W // 4), mode="area")
    return torch.nn.functional.interpolate(small, size=(H, W), mode="bicubic", align_corners=True).clamp(0, 1)


def _answer(tmp_path, lens=LENS, **changes) -> tuple:
    """Frames of the scene through ``lens`` and a planar answer for them: (folder, json path, scene)."""
    scene = _scene()
    p = pixel_grid(H, W, torch.float64).reshape(-1, 2)
    ideal = lens_ideal_points(p, lens[0], H, W, centre=lens[1])
    distorted = sample_at_pixels(scene.double(), ideal.reshape(1, H, W, 2)).float()
    k2, k4, _ = fit_eq4(p, ideal, H, W)
    cfg = LensdistConfig()
    dc = paper_frame_delta_avg(k2, k4, (H, W), cfg)
    label = next(
        c for c in CLASS_LABELS if class_bounds(c, "delta_avg", cfg)[0] <= dc < class_bounds(c, "delta_avg", cfg)[1]
    )
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in ("a", "b"):
        (folder / f"{name}.png").write_bytes(encode_png((distorted[0].clamp(0, 1) * 255).round().to(torch.uint8)))
    answer = {"k2_user": k2, "k4_user": k4, "image_size": [H, W], "class": label, "reason": None, "method": "planar",
              "planar": {"coefficients": list(lens[0]), "centre": list(lens[1])}} | changes
    src = tmp_path / "calibration.json"
    src.write_text(json.dumps(answer))
    return folder, src, scene


def test_the_lens_inverse_round_trips_and_matches_eq4_as_its_special_case():
    p = torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * torch.tensor(
        [W - 1.0, H - 1.0]
    )
    back, ok = lens_distorted_points(lens_ideal_points(p, LENS[0], H, W, centre=LENS[1]), LENS[0], H, W, centre=LENS[1])
    assert bool(ok.all()) and float((back - p).abs().max()) < 1e-8
    grid, valid = lens_undistortion_grid(*LENS, H, W, dtype=torch.float64)
    mapped = lens_ideal_points(grid[0].reshape(-1, 2), LENS[0], H, W, centre=LENS[1]).reshape(H, W, 2)
    err = (mapped - pixel_grid(H, W, torch.float64)).norm(dim=-1)[valid[0, 0] > 0]
    assert float(err.max()) < 1e-6 and float(valid.mean()) > 0.8


def test_undistort_from_a_planar_answer_applies_its_lens(tmp_path):
    folder, src, scene = _answer(tmp_path)
    res = undistort_path(folder, tmp_path / "out", from_json=src)
    assert res["lens"] == {"kind": "radial", "coefficients": LENS[0], "centre": LENS[1]}
    assert res["camera"]["applied"] == "the homography model's lens"
    saved = json.loads((tmp_path / "out" / "undistortion.json").read_text())
    assert saved["lens"]["centre"] == LENS[1] and saved["opencv_model"] == "rational"
    from lensdist_torch.core import load_image

    out = load_image(tmp_path / "out" / "a.png")
    mask = load_image(tmp_path / "out" / "masks" / "a.png") > 0.5
    inner = torch.zeros_like(mask)
    inner[..., 8:-8, 8:-8] = True  # bilinear twice and 8-bit: compare away from the frame's edge
    lens_err = float((out - scene[0]).abs()[mask & inner].mean())
    # eq. 4's fit to the same lens, applied as --k2 --k4 would: its error is the lens's misfit
    eq4 = undistort_path(folder, tmp_path / "eq4", k2=res["k2"], k4=res["k4"])
    out4 = load_image(tmp_path / "eq4" / "a.png")
    mask4 = load_image(tmp_path / "eq4" / "masks" / "a.png") > 0.5
    eq4_err = float((out4 - scene[0]).abs()[mask & mask4 & inner].mean())
    assert eq4["lens"] is None and lens_err < 0.005 and eq4_err > 3 * lens_err, (lens_err, eq4_err)  # 0.0024, 0.0134


def test_frames_at_another_size_scale_the_centre(tmp_path):
    folder, src, _ = _answer(tmp_path)
    data = json.loads(src.read_text())
    data["image_size"] = [
        2 * H,
        2 * W,
    ]  # the answer was for frames twice as large: the centre halves about pixel centres
    data["planar"]["centre"] = [(c + 0.5) * 2 - 0.5 for c in LENS[1]]
    src.write_text(json.dumps(data))
    res = undistort_path(folder, tmp_path / "out", from_json=src)
    assert res["lens"]["centre"] == pytest.approx(LENS[1], abs=1e-12)


@pytest.mark.parametrize("planar,field", [
    ({"coefficients": [0.1, "x"], "centre": [60.0, 40.0]}, "planar.coefficients"),
    ({"coefficients": [0.1] * 4, "centre": [60.0, 40.0]}, "planar.coefficients"),
    ({"coefficients": [0.1], "centre": [60.0, 400.0]}, "planar.centre"),
    ({"coefficients": [0.1], "centre": [math.nan, 4.0]}, "planar.centre"),
    (None, "planar.coefficients"),
])
def test_a_bad_lens_field_is_named(tmp_path, planar, field):
    folder, src, _ = _answer(tmp_path)
    data = json.loads(src.read_text())
    data["planar"] = planar
    src.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        undistort_path(folder, tmp_path / "out", from_json=src)
    assert not (tmp_path / "out").exists()


def test_a_lens_that_folds_inside_the_frame_is_refused(tmp_path):
    folder, src, _ = _answer(tmp_path)
    data = json.loads(src.read_text())
    data["planar"]["coefficients"] = [-3.0]  # r (1 - 3 r^2) stops growing at r = 1/3 of the half diagonal, 26 px
    src.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="folds"):
        undistort_path(folder, tmp_path / "out", from_json=src)


def test_the_view_of_alpha_follows_the_lens(tmp_path):
    folder, src, _ = _answer(tmp_path)  # alpha 0: valid pixels only; alpha 1: every source pixel kept
    res = {a: undistort_path(folder, tmp_path / f"out{a}", from_json=src, alpha=a) for a in (0.0, 1.0)}
    assert res[0.0]["valid_fraction"] > 0.995 and res[1.0]["valid_fraction"] < 0.98
    # this barrel lens spreads the ideal frame beyond the frame: both views zoom out, the outer rectangle more
    assert 1 > res[0.0]["camera"]["view"]["sx"] > res[1.0]["camera"]["view"]["sx"]


# ------------------------------------------------------------------ the multi-view path's OpenCV camera
CAM = (
    [[90.0, 0.0, 70.0], [0.0, 92.0, 41.0], [0.0, 0.0, 1.0]],
    [-0.3, 0.1, 3e-3, -4e-3, -0.01],
)  # off-centre, tangential


@pytest.mark.parametrize("dist", [CAM[1], CAM[1] + [0.05, 0.01, 0.0]])
def test_the_opencv_grid_is_cv2s_initundistortrectifymap(dist):
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    grid, valid = opencv_undistortion_grid(CAM[0], dist, H, W, dtype=torch.float64)
    mx, my = cv2.initUndistortRectifyMap(np.array(CAM[0]), np.array(dist), None, np.array(CAM[0]), (W, H), cv2.CV_32FC1)
    theirs = torch.from_numpy(np.stack([mx, my], -1)).double()
    ok = valid[0, 0] > 0
    assert float(ok.double().mean()) > 0.9 and float((grid[0] - theirs).abs()[ok].max()) < 1e-3


def test_undistort_from_a_multiview_answer_applies_its_camera(tmp_path):
    scene = _scene()
    k, d = torch.tensor(CAM[0], dtype=torch.float64), torch.tensor(CAM[1], dtype=torch.float64)
    p = pixel_grid(H, W, torch.float64).reshape(-1, 2)
    ideal, ok = opencv_ideal_points(p, k, d)
    distorted = sample_at_pixels(scene.double(), ideal.reshape(1, H, W, 2)).float()
    k2, k4, _ = fit_eq4(p[ok], ideal[ok], H, W)
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "a.png").write_bytes(encode_png((distorted[0].clamp(0, 1) * 255).round().to(torch.uint8)))
    cfg = LensdistConfig()
    dc = paper_frame_delta_avg(k2, k4, (H, W), cfg)
    label = next(
        c for c in CLASS_LABELS if class_bounds(c, "delta_avg", cfg)[0] <= dc < class_bounds(c, "delta_avg", cfg)[1]
    )
    answer = {"k2_user": k2, "k4_user": k4, "image_size": [H, W], "class": label, "reason": None, "method": "multiview",
              "opencv": {"camera_matrix": CAM[0], "dist_coeffs": CAM[1]}, "opencv_rational": None}
    src = tmp_path / "calibration.json"
    src.write_text(json.dumps(answer))
    res = undistort_path(folder, tmp_path / "out", from_json=src)
    assert res["lens"]["kind"] == "opencv" and res["camera"]["dist_coeffs"] == CAM[1]
    from lensdist_torch.core import load_image

    inner = torch.zeros(1, H, W, dtype=torch.bool)
    inner[..., 8:-8, 8:-8] = True
    errs = {}
    for name, kwargs in (("camera", {"from_json": src}), ("eq4", {"k2": k2, "k4": k4})):
        undistort_path(folder, tmp_path / name, **kwargs)
        out, mask = load_image(tmp_path / name / "a.png"), load_image(tmp_path / name / "masks" / "a.png") > 0.5
        errs[name] = float((out - scene[0]).abs()[mask & inner].mean())
    assert errs["camera"] < 0.005 and errs["eq4"] > 2 * errs["camera"], errs
    answer["opencv"]["dist_coeffs"] = [0.1, 0.2, 0.3]
    src.write_text(json.dumps(answer))
    with pytest.raises(ValueError, match=r"opencv\.dist_coeffs"):
        undistort_path(folder, tmp_path / "bad", from_json=src)


def test_a_lens_that_stretches_the_frame_tenfold_is_refused(tmp_path):
    folder, src, _ = _answer(tmp_path)
    data = json.loads(src.read_text())
    data["planar"]["coefficients"] = [12.0]  # 1 + 12 r^2 at the far corner (r about 1.08): 15-fold
    src.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="stretches"):
        undistort_path(folder, tmp_path / "out", from_json=src)
    assert not (tmp_path / "out").exists()


def test_a_lens_whose_class_is_not_the_files_is_refused(tmp_path):
    folder, src, _ = _answer(tmp_path)  # class 4, from eq. 4's fit to the lens
    data = json.loads(src.read_text())
    data["planar"]["coefficients"] = [0.002]  # a lens of a fraction of a pixel: not class 4
    src.write_text(json.dumps(data))
    with pytest.raises(
        ValueError, match=r"'class' is '4', but field 'planar\.coefficients' \(the lens applied.*contradicts itself"
    ):
        undistort_path(folder, tmp_path / "out", from_json=src)
