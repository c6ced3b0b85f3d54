"""``lensdist undistort --from FILE`` against hostile files (issue 19): the class, the verification
and OpenCV's camera are checked with the coefficients they could contradict
(lensdist_torch/calibration/controllers/answer_file.py); fields undistort ignores are not."""

from __future__ import annotations

import copy
import json

import pytest
import torch

from lensdist_torch.cli import main
from lensdist_torch.core.png import encode_png, to_uint8

pytestmark = pytest.mark.bad_input

#: What ``lensdist calibrate --json --method direct`` wrote for a rendered 120 x 160 pan (k2 = 1e-5):
#: class 2 (Delta_avg 4.0 px at the paper's frame), verified.
CALIBRATE = {
    "frames": 10, "image_size": [120, 160], "analysis_size": [120, 160], "scale": 1.0,
    "k2_user": 9.855728059694316e-06, "k4_user": -4.3367377688289655e-12, "delta_avg_user_px": 2.2,
    "class": "2", "reason": None, "method": "direct",
    "opencv": {"camera_matrix": [[99.3, 0.0, 79.5], [0.0, 99.3, 59.5], [0.0, 0.0, 1.0]],
               "dist_coeffs": [-0.1, 0.01, 0.0, 0.0, 0.0]},
    "verification": {"pairs": 6, "error_blocks_before": 1255, "blocks_before": 1399, "error_blocks_after": 844,
                     "blocks_after": 1385, "registered_before": 6, "registered_after": 6,
                     "error_share_before": 1255 / 1399, "error_share_after": 844 / 1385, "verdict": "lowered"},
}
#: What ``lensdist analyze --json`` writes (the self-calibration's answer) for a 240 x 320 pair: class 1.
ANALYZE = {"method": "selfcal", "class": "1", "k2_user": 1e-6, "k4_user": 0.0, "input_size": [240, 320],
           "analysed_region_user_px": [0, 0, 240, 320], "warnings": [], "cannot_tell": False}


def _edit(base: dict, **changes) -> dict:
    """A deep copy of ``base`` with dotted fields replaced (``verification__verdict``), or removed (``...``)."""
    out = copy.deepcopy(base)
    for key, value in changes.items():
        *path, last = key.split("__")
        target = out
        for part in path:
            target = target[part]
        if value is ...:
            target.pop(last)
        else:
            target[last] = value
    return out


@pytest.fixture
def frames(tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    g = torch.Generator().manual_seed(0)
    (folder / "a.png").write_bytes(encode_png(to_uint8(torch.rand(1, 120, 160, generator=g))))
    return folder


def _run(tmp_path, capsys, folder, data: dict):
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps(data))
    code = main(["undistort", str(folder), "--from", str(cal), "--out", str(tmp_path / "out"), "--quiet"])
    out, err = capsys.readouterr()
    return code, err.strip(), cal


def _refused(tmp_path, capsys, folder, data: dict, *words: str) -> str:
    code, err, cal = _run(tmp_path, capsys, folder, data)
    assert code == 2 and err.startswith("lensdist undistort: error: ") and "\n" not in err, (code, err)
    assert "Traceback" not in err and "internal error" not in err
    assert str(cal) in err, err
    for w in words:
        assert w in err, (w, err)
    assert not (tmp_path / "out").exists()
    return err


@pytest.mark.parametrize("data", [CALIBRATE, ANALYZE, _edit(CALIBRATE, verification=None, opencv=None),
                                  _edit(CALIBRATE, opencv=...),
                                  # fields undistort ignores are not refused
                                  _edit(CALIBRATE, delta_avg_user_px="banana", frames=-3, method=7, warnings={})])
def test_files_of_both_commands_are_read(tmp_path, capsys, frames, data):
    if data is ANALYZE:  # 240 x 320: the 120 x 160 frames are its rescaling by 1/2
        data = _edit(ANALYZE)
    code, err, _ = _run(tmp_path, capsys, frames, data)
    assert code == 0, err
    applied = json.loads((tmp_path / "out" / "undistortion.json").read_text())
    s = 160 / data.get("image_size", data.get("input_size"))[1]
    assert applied["k2"] == pytest.approx(data["k2_user"] / s**2)


@pytest.mark.parametrize("label", ["banana", 7, True, "r", ["R"], "", "5"])
def test_an_invalid_class(tmp_path, capsys, frames, label):
    """Before: 'banana' or 7 undistorted the frames, exit 0."""
    _refused(tmp_path, capsys, frames, _edit(CALIBRATE, **{"class": label}),
             "field 'class' must be one of '1', '2', '3', '4', 'R' or null", f"got {label!r}")


def test_a_missing_class(tmp_path, capsys, frames):
    _refused(tmp_path, capsys, frames, _edit(CALIBRATE, **{"class": ...}), "no field 'class'")


@pytest.mark.parametrize("label,k2,size,delta", [
    ("R", 3e-6, [320, 424], "Delta_avg 12.58 px"),  # the audit's case: class R, Delta_avg 12.6 px
    ("1", 4e-6, [240, 320], "Delta_avg 9.49 px"),  # a class-3 lens
    ("4", 1e-6, [240, 320], "Delta_avg 2.37 px"),  # a class-1 lens
    ("R", 1.6e-6, [120, 160], "Delta_avg 0.94 px"),  # above both producers' R thresholds (0.25, 0.75 px)
])
def test_a_class_its_coefficients_contradict(tmp_path, capsys, frames, label, k2, size, delta):
    """Before: every one undistorted the frames, exit 0."""
    data = _edit(CALIBRATE, **{"class": label, "k2_user": k2, "k4_user": 0.0, "image_size": size,
                               "verification": None, "opencv": None})
    _refused(tmp_path, capsys, frames, data, f"field 'class' is {label!r}", delta, "contradicts itself")


@pytest.mark.parametrize("label", ["R", "1"])
def test_between_the_two_r_thresholds_either_class_is_read(tmp_path, capsys, frames, label):
    """Delta_avg 0.59 px: R for one pair (analysis.no_distortion_px 0.75), class 1 for a sequence (0.25)."""
    data = _edit(CALIBRATE, **{"class": label, "k2_user": 1e-6, "k4_user": 0.0, "image_size": [120, 160],
                               "verification": None, "opencv": None})
    assert _run(tmp_path, capsys, frames, data)[0] == 0


def test_a_class_at_its_bound_is_read(tmp_path, capsys, frames):
    """Within FROM_CLASS_TOLERANCE of the bound (the producers' rounding): class 1 at Delta_avg 3.6 px."""
    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.geometry.distortion import class_bounds, paper_frame_delta_avg

    hi = class_bounds("1", "delta_avg", LensdistConfig())[1]
    k2 = 1e-6 * hi / paper_frame_delta_avg(1e-6, 0.0, (120, 160), LensdistConfig()) * 1.01  # 1 % above class 1
    data = _edit(CALIBRATE, **{"class": "1", "k2_user": k2, "k4_user": 0.0, "verification": None, "opencv": None})
    assert _run(tmp_path, capsys, frames, data)[0] == 0


def test_a_class_without_coefficients(tmp_path, capsys, frames):
    data = _edit(CALIBRATE, k2_user=None, k4_user=None)
    _refused(tmp_path, capsys, frames, data, "field 'class' is '2', but 'k2_user' and 'k4_user' are null")


@pytest.mark.parametrize(
    "changes,words",
    [
        ({"verification": "yes"}, ("field 'verification' must be null or an object",)),
        ({"verification__pairs": -1}, ("field 'verification.pairs' must be an int >= 0", "got -1")),
        ({"verification__blocks_after": 1.5}, ("'verification.blocks_after' must be an int >= 0",)),
        ({"verification__registered_after": ...}, ("'verification.registered_after' must be an int >= 0", "got None")),
        ({"verification__registered_after": 9}, ("counts more registered pairs or error blocks after",)),
        ({"verification__error_blocks_before": 2000}, ("counts more registered pairs or error blocks before",)),
        (
            {"verification__error_share_after": 0.1},
            ("'verification.error_share_after' must be error_blocks_after / blocks_after",),
        ),
        ({"verification__error_share_before": "0.9"}, ("'verification.error_share_before' must be",)),
        (
            {"verification__verdict": "great"},
            ("'verification.verdict' must be one of 'lowered', 'not lowered', 'not measurable'",),
        ),
        (
            {"verification__verdict": "not measurable"},
            ("'verification.verdict' is 'not measurable', but its shares and counts say 'lowered'",),
        ),
        # the shares rose: the verdict 'lowered' is a lie
        (
            {"verification__error_blocks_after": 1300, "verification__error_share_after": 1300 / 1385},
            ("'verification.verdict' is 'lowered', but its shares and counts say 'not lowered'",),
        ),
        # a consistent 'not lowered' beside a class: calibrate withholds the class then
        (
            {
                "verification__error_blocks_after": 1300,
                "verification__error_share_after": 1300 / 1385,
                "verification__verdict": "not lowered",
            },
            ("fields 'class' ('2') and 'verification' contradict", "withholds"),
        ),
    ],
)
def test_a_malformed_or_contradictory_verification(tmp_path, capsys, frames, changes, words):
    """Before: every one undistorted the frames, exit 0."""
    _refused(tmp_path, capsys, frames, _edit(CALIBRATE, **changes), *words)


def test_a_file_with_the_earlier_verdict_still_loads(tmp_path, capsys, frames):
    """Files written before the verdict counted registrations gained: 'not measurable' for 0 -> 2 pairs stands."""
    (tmp_path / "not measurable").mkdir()
    (tmp_path / "lowered").mkdir()
    data = _edit(CALIBRATE, **{"verification__registered_before": 0, "verification__registered_after": 2,
                               "verification__error_blocks_before": 0, "verification__blocks_before": 0,
                               "verification__error_blocks_after": 0, "verification__blocks_after": 0,
                               "verification__error_share_before": None, "verification__error_share_after": None,
                               "verification__verdict": "not measurable"})
    for given in ("not measurable", "lowered"):  # the earlier rule's verdict, and the rule of now's
        data["verification"]["verdict"] = given
        code, err, _ = _run(tmp_path / given, capsys, frames, data)
        assert code == 0, err
    data["verification"]["verdict"] = "not lowered"  # neither rule's: refused
    _refused(
        tmp_path,
        capsys,
        frames,
        data,
        "'verification.verdict' is 'not lowered', but its shares and counts say 'lowered'",
    )


def test_a_verified_class_r(tmp_path, capsys, frames):
    data = _edit(CALIBRATE, **{"class": "R", "k2_user": 1e-7, "k4_user": 0.0})
    _refused(tmp_path, capsys, frames, data, "fields 'class' ('R') and 'verification' contradict", "never verified")


@pytest.mark.parametrize("changes,words", [
    ({"input_size": [240, 320]}, ("fields 'image_size' [120, 160] and 'input_size' [240, 320] disagree",)),
    ({"opencv__camera_matrix": [[-99.3, 0, 79.5], [0, 99.3, 59.5], [0, 0, 1]]}, ("field 'opencv.camera_matrix'",)),
    ({"opencv__camera_matrix": "K"}, ("field 'opencv.camera_matrix'",)),
    ({"opencv__camera_matrix": [[99.3, 0, 500.0], [0, 99.3, 59.5], [0, 0, 1]]}, ("inside the 120 x 160 frame",)),
    ({"opencv": [1, 2]}, ("field 'opencv.camera_matrix'",)),
])
def test_a_size_or_camera_that_contradicts(tmp_path, capsys, frames, changes, words):
    """Before: the second size was ignored, and a bad camera matrix silently replaced by the half diagonal."""
    _refused(tmp_path, capsys, frames, _edit(CALIBRATE, **changes), *words)


@pytest.mark.parametrize("box", [[0, 0, 300, 320], [0, 0, 0, 320], [-1, 0, 240, 320], "all", [0, 0, 240]])
def test_an_analysed_region_outside_the_frame(tmp_path, capsys, frames, box):
    data = _edit(ANALYZE, analysed_region_user_px=box)
    _refused(tmp_path, capsys, frames, data, "field 'analysed_region_user_px' must be [top, left, height, width]")
