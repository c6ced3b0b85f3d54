"""The paper's metric as the verifier of a calibration (issue 18, item 5)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from lensdist_torch.calibration.controllers import calibrate
from lensdist_torch.calibration.controllers.calibrate import _verified, synthetic_sequence
from lensdist_torch.calibration.controllers.verify import error_blocks, verify_undistortion
from lensdist_torch.config import CalibrationConfig, LensdistConfig

K2 = 2e-6  # at 160 x 212: Delta_avg ~ 2 px


@pytest.fixture(scope="module")
def frames():
    return synthetic_sequence(6, K2, 0.0, size=(160, 212), step_px=(20, 24))[0]


PAIRS = torch.tensor([[0, 3], [1, 4], [2, 5]])


def test_identical_views_have_no_error_block():
    img = synthetic_sequence(1, 0.0, 0.0, size=(64, 96))[0]
    ones = torch.ones_like(img)
    errors, counted, ok = error_blocks(img, img.clone(), ones, ones, settings=LensdistConfig())
    assert ok and errors == 0 and counted == 8 * 12  # every 8 x 8 block of the 64 x 96 frame


def test_the_true_coefficients_lower_the_errors_most(frames):
    shares = {k: verify_undistortion(frames, PAIRS, k, 0.0)["error_share_after"] for k in (0.0, K2 / 2, K2, 2 * K2)}
    before = verify_undistortion(frames, PAIRS, K2, 0.0)["error_share_before"]
    assert shares[0.0] == pytest.approx(before)  # no correction, the same registration
    assert shares[K2] < 0.5 * before  # the truth removes most of them
    assert shares[K2] < shares[K2 / 2] < before and shares[K2] < shares[2 * K2]


def test_at_most_max_pairs_evenly_spread(frames):
    out = verify_undistortion(frames, torch.tensor([[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]]), K2, 0.0, max_pairs=2)
    assert out["pairs"] == 2 and out["registered_before"] == out["registered_after"] == 2


def _answer(k2):
    return {"class": "1", "reason": None, "k2_user": k2, "k4_user": 0.0, "scale": 1.0}


def test_a_class_is_withheld_when_the_correction_does_not_help(frames):
    cal = SimpleNamespace(pairs=PAIRS, pair_used=torch.ones(3, dtype=torch.bool))
    cfg, st = CalibrationConfig(), LensdistConfig()
    right = _verified(_answer(K2), frames, cal, cfg, st)
    assert (
        right["class"] == "1"
        and right["verification"]["error_share_after"] < right["verification"]["error_share_before"]
    )
    wrong = _verified(_answer(-K2), frames, cal, cfg, st)  # pincushion for a barrel lens: more errors
    assert wrong["class"] is None and "does not lower their registration errors" in wrong["reason"]
    # nothing to verify: no class, class R, or verification off
    assert _verified({**_answer(K2), "class": "R"}, frames, cal, cfg, st)["verification"] is None
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(calibrate, "VERIFY_PAIRS", 0)
        off = _verified(_answer(-K2), frames, cal, cfg, st)
    assert off["class"] == "1" and off["verification"] is None


def test_unrelated_views_are_not_measurable_and_keep_the_class():
    """Far-apart views that no homography relates, before or after: not verified, not refuted."""
    from lensdist_torch.core.images import load_scene

    a = load_scene("gravel")[..., :160, :212]
    b = load_scene("grass")[..., :160, :212]
    frames = torch.cat([a, b, a.flip(-1), b.flip(-2)])
    cal = SimpleNamespace(pairs=torch.tensor([[0, 1], [2, 3]]), pair_used=torch.ones(2, dtype=torch.bool))
    res = _verified(_answer(K2), frames, cal, CalibrationConfig(), LensdistConfig())
    check = res["verification"]
    assert check["registered_before"] == check["registered_after"] == 0
    assert check["verdict"] == "not measurable" and res["class"] == "1"


@pytest.mark.bad_input
def test_undistort_from_a_calibration_that_could_not_tell(tmp_path, frames):
    """Issue 19 audit: `undistort --from` used the numbers of a 'cannot tell' calibration without a word."""
    import json

    from lensdist_torch.core.png import encode_png, to_uint8
    from lensdist_torch.workflows.undistort import undistort_path

    (tmp_path / "in").mkdir()
    for i, f in enumerate(frames[:2]):
        (tmp_path / "in" / f"f{i}.png").write_bytes(encode_png(to_uint8(f)))
    cal = {"k2_user": 2e-6, "k4_user": 0.0, "image_size": [160, 212], "class": None, "reason": "interval too wide"}
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    with pytest.raises(ValueError, match="could not tell .interval too wide.*--k2 2e-06 --k4 0"):
        undistort_path(tmp_path / "in", tmp_path / "out", from_json=tmp_path / "cal.json")
    assert not (tmp_path / "out").exists()
    cal["class"] = "1"
    (tmp_path / "cal.json").write_text(json.dumps(cal))
    assert undistort_path(tmp_path / "in", tmp_path / "out", from_json=tmp_path / "cal.json")["frames"] == 2


@pytest.mark.parametrize("before,after,shares,says", [
    (1, 3, (0.050, 0.056), "lowered"),  # the GoPro views' check: two more pairs register once undistorted
    (0, 2, (None, None), "lowered"),  # nothing registered before, two after
    (3, 3, (0.05, 0.04), "lowered"),  # the same pairs: the shares decide
    (3, 3, (0.05, 0.06), "not lowered"),
    (3, 2, (0.05, 0.04), "lowered"),  # the shares of the pairs registered both times
    (2, 0, (None, None), "not lowered"),  # the correction broke every registration
    (0, 0, (None, None), "not measurable"),
])
def test_the_verdict_counts_a_registration_gained_as_errors_lowered(before, after, shares, says):
    from lensdist_torch.calibration.controllers.verify import verdict

    check = {"registered_before": before, "registered_after": after, "error_share_before": shares[0],
             "error_share_after": shares[1]}
    assert verdict(check) == says


def test_an_answers_own_lens_verifies_as_eq4_where_it_is_eq4(frames):
    from lensdist_torch.geometry.distortion import distortion_center
    from lensdist_torch.geometry.frame import half_diagonal

    h, w = frames.shape[-2:]
    lens = {"kind": "radial", "coefficients": [K2 * half_diagonal(h, w) ** 2], "centre": list(distortion_center(h, w))}
    eq4 = verify_undistortion(frames, PAIRS, K2, 0.0)
    assert verify_undistortion(frames, PAIRS, 0.0, 0.0, lens=lens) == eq4  # (k2, k4) unused: the lens is applied
    off = {**lens, "centre": [c + 12.0 for c in lens["centre"]]}  # the same lens about another centre: worse
    assert verify_undistortion(frames, PAIRS, K2, 0.0, lens=off)["error_share_after"] > eq4["error_share_after"]


@pytest.fixture(scope="module")
def pincushion_frames():
    return synthetic_sequence(6, -K2, 0.0, size=(160, 212), step_px=(20, 24))[0]


def test_a_pincushion_lens_is_verified_inside_its_corrected_frame(pincushion_frames):
    """Its correction leaves the corners empty: registered inside the valid box, the truth lowers the errors."""
    cal = SimpleNamespace(pairs=PAIRS[:2], pair_used=torch.ones(2, dtype=torch.bool))
    right = _verified(_answer(-K2), pincushion_frames, cal, CalibrationConfig(), LensdistConfig())
    check = right["verification"]
    assert check["registered_after"] == 2 and check["verdict"] == "lowered" and right["class"] == "1"
    assert check["error_share_after"] < 0.5 * check["error_share_before"]
