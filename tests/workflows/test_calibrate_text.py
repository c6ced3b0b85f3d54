"""``lensdist calibrate``'s text: the answer first (class and kind, Delta, OpenCV's camera and what its focal
is, the next command), eq. 4 and each path's numbers only with --debug; and the OpenCV camera at a user's focal."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.calibration.controllers.calibrate import FOCAL_SOURCES, _with_focal
from lensdist_torch.cli.calibrate import _print_calibration
from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.geometry.opencv_model import opencv_export


def _answer(k2: float, cls: str | None = "2", method: str = "direct", focal_source: str = "half diagonal") -> dict:
    h, w = 240, 320
    d = float(delta_avg(torch.tensor(k2, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64), h, w))
    return {
        "path": "frames/",
        "image_size": [h, w],
        "frames": 12,
        "pairs_used": 9,
        "pairs_rejected": 1,
        "method": method,
        "class": cls,
        "reason": None if cls else "interval too wide: +-2.00 px",
        "k2_user": k2,
        "k4_user": 0.0,
        "delta_avg_user_px": d,
        "delta_avg_user_interval": [0.9 * d, 1.1 * d],
        "delta_max_user_px": 4 * d,
        "delta_max_user_interval": [3.6 * d, 4.4 * d],
        "opencv": opencv_export(k2, 0.0, h, w, model="standard"),
        "opencv_rational": opencv_export(k2, 0.0, h, w, model="rational"),
        "focal_source": focal_source,
        "multiview": None,
        "planar": None,
    }


@pytest.mark.parametrize("k2,kind", [(2e-6, "barrel"), (-2e-6, "pincushion")])
def test_the_answer_comes_first_with_its_kind_and_the_next_command(capsys, k2, kind):
    _print_calibration(_answer(k2), "out")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"distortion class: 2, {kind}  (1 = small")
    assert lines[1].startswith("Delta_avg = ") and lines[1].endswith("over your 320 x 240 frames")
    assert lines[3] == "from the direct path (eq. 4)"
    assert "fx, fy: the half diagonal, a convention (the lens model has no focal length; --focal F sets yours)" in lines
    assert lines[-2:] == [
        "next: lensdist undistort frames/ --from out/calibration.json --out out/undistorted",
        "eq. 4's k2, k4 and each path's numbers: with --debug, or in the JSON (--json, --out)",
    ]


def test_eq4_and_each_paths_numbers_only_with_debug(capsys):
    """Issue 51: eq. 4's coefficients and each path's internals stood where a user looks for the answer."""
    _print_calibration(_answer(2e-6), "out")
    plain = capsys.readouterr().out
    assert "eq. 4 about" not in plain and "each path:" not in plain and "pairs used" not in plain
    _print_calibration(_answer(2e-6), "out", debug=True)
    lines = capsys.readouterr().out.splitlines()
    assert lines[: len(plain.splitlines()) - 1] == plain.splitlines()[:-1]  # the same answer, then the internals
    i = lines.index("next: lensdist undistort frames/ --from out/calibration.json --out out/undistorted")
    assert lines[i + 1] == "eq. 4 about the frame centre, in your pixels: k2 = 2.0000e-06, k4 = 0.0000e+00"
    assert lines[i + 2 :] == ["each path:", "12 frames of 320 x 240; direct path: 9 pairs used, 1 rejected"]


def test_cannot_tell_names_no_kind_and_no_next_command(capsys):
    _print_calibration(_answer(2e-6, cls=None), None)
    text = capsys.readouterr().out
    assert text.startswith("distortion class: cannot tell (interval too wide: +-2.00 px)")
    assert "barrel" not in text and "next:" not in text and "estimate, not an answer: Delta_avg" in text


@pytest.mark.parametrize("source,says", [("colmap", "COLMAP's estimate"), ("given", "yours (--focal)")])
def test_the_focal_says_where_it_comes_from(capsys, source, says):
    _print_calibration(_answer(2e-6, focal_source=source), None)
    assert f"fx, fy: {says}" in capsys.readouterr().out


@pytest.mark.parametrize("std,says", [(10.0, ", +-19.6 px (95 %)"), (float("inf"), ", not determined by the tracks"),
                                     (None, ", not determined by the tracks")])
def test_colmaps_focal_comes_with_its_posterior(capsys, std, says):
    res = _answer(2e-6, method="multiview", focal_source="colmap") | {"camera_model": "RADIAL", "confidence": 0.95}
    res["multiview"] = {"model": "RADIAL", "registered": 12, "points3D": 900, "reprojection_px": 0.5,
                        "delta_avg_user_px": 1.0, "delta_avg_user_interval": [0.9, 1.1],
                        "models": {"RADIAL": {"focal_std_px": std}, "OPENCV": {"focal_std_px": 1.0}}}
    _print_calibration(res, None)
    text = capsys.readouterr().out
    assert f"fx, fy: COLMAP's estimate from the bundle adjustment{says}" in text
    assert "\nfrom the multi-view path (COLMAP), lens model RADIAL\n" in text  # the model that gave the answer


def test_another_paths_camera_at_colmaps_focal_claims_no_spread(capsys):
    # a held row (another path's lens weighed at COLMAP's focal) has no posterior of its own focal
    res = _answer(2e-6, method="multiview", focal_source="colmap") | {"camera_model": "own lens"}
    res["multiview"] = {"model": "own lens", "registered": 12, "points3D": 900, "reprojection_px": 0.5,
                        "delta_avg_user_px": 1.0, "delta_avg_user_interval": [0.9, 1.1],
                        "models": {"own lens": {"weight": 0.9}, "RADIAL": {"focal_std_px": 1.0}}}
    _print_calibration(res, None)
    assert "fx, fy: COLMAP's estimate from the bundle adjustment\n" in capsys.readouterr().out


def test_a_given_focal_reaches_the_homography_models_camera():
    """The homography model's lens has no focal: its OpenCV camera is fitted again at the caller's."""
    lens = {"coefficients": [0.05], "centre": [159.5, 119.5]}
    res = {"method": "planar", "k2_user": 1e-6, "planar": lens, "opencv": None, "opencv_rational": None}
    out = _with_focal(dict(res), 500.0, (240, 320))
    assert out["focal_source"] == "given" == FOCAL_SOURCES[1]
    for key in ("opencv", "opencv_rational"):
        k = out[key]["camera_matrix"]
        assert k[0][0] == pytest.approx(500.0) and k[1][1] == pytest.approx(500.0)
        assert out[key]["fit_error_mean_px"] < 0.05  # the same lens, at that focal
    assert _with_focal(dict(res), None, (240, 320))["focal_source"] == "half diagonal"
    assert _with_focal({**res, "method": "multiview"}, 500.0, (240, 320))["focal_source"] == "colmap"


@pytest.mark.parametrize(
    "argv", [["calibrate", "{d}"], ["--debug", "calibrate", "{d}"], ["calibrate", "{d}", "--debug"]]
)
def test_the_command_shows_the_internals_with_debug_only(capsys, monkeypatch, tmp_path, argv):
    import lensdist_torch.calibration.controllers.calibrate as calibrate
    from lensdist_torch import cli

    monkeypatch.setattr(calibrate, "calibrate_path", lambda *a, **k: _answer(2e-6) | {"path": str(tmp_path)})
    assert cli.main([a.format(d=tmp_path) for a in argv] + ["--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "distortion class: 2, barrel  (1 = small ... 4 = very strong, R = none visible)"
    assert ("each path:" in lines) == ("--debug" in argv)
