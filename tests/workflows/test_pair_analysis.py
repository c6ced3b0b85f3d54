"""PairAnalysis: a pair's analysis as one record, and the CLI's JSON and text defined once by it (issue 50, item 2)."""

from __future__ import annotations

import dataclasses
import json
import re

import pytest
import torch

from lensdist_torch import PairAnalysis, analyze_pair, load_scene
from lensdist_torch.cli import main
from lensdist_torch.workflows.pair_analysis import JSON_KEYS

#: The JSON's keys in their order for the gravel pair below, as ``lensdist analyze --json`` printed
#: them when the analysis was a dict: the record must not reorder, drop or add one.
KEYS = {
    "selfcal": "method distances reject_threshold confidence estimated_class estimated_class_max delta_avg delta_max "
    "k2 k4 delta_avg_std delta_avg_interval relief relief_z distortion_type raw_confidence relief_found "
    "relief_agreement relief_parted planar_delta_avg planar_delta_avg_std planar_delta_avg_interval relief_delta_avg "
    "relief_delta_avg_std relief_delta_avg_interval registration_ok registered_by overlap motion_px in_domain "
    "warnings cannot_tell cannot_tell_reasons class class_max estimated_delta_avg estimated_delta_max "
    "beyond_class_range analysed_region_user_px delta_avg_region_user_px delta_max_region_user_px "
    "delta_avg_user_px delta_avg_user_interval delta_max_user_px registration_residual error_blocks "
    "analysis_size input_size "
    "user_px_per_analysis_px homography k2_user k4_user opencv",
    "regression": "method distances reject_threshold confidence estimated_class estimated_class_max delta_avg "
    "delta_max raw_confidence registration_ok registered_by overlap motion_px fitted_on texture_distance texture_limit "
    "selfcal_check in_domain warnings cannot_tell cannot_tell_reasons class class_max estimated_delta_avg "
    "estimated_delta_max delta_avg_interval distortion_type beyond_class_range analysed_region_user_px "
    "delta_avg_region_user_px delta_max_region_user_px delta_avg_user_px delta_avg_user_interval delta_max_user_px "
    "registration_residual error_blocks analysis_size input_size user_px_per_analysis_px homography",
    "eigenspace": "method distances reject_threshold confidence estimated_class estimated_class_max delta_avg "
    "delta_max registration_ok registered_by overlap motion_px fitted_on texture_distance texture_limit selfcal_check "
    "in_domain warnings cannot_tell cannot_tell_reasons class class_max estimated_delta_avg estimated_delta_max "
    "delta_avg_interval distortion_type beyond_class_range analysed_region_user_px delta_avg_region_user_px "
    "delta_max_region_user_px delta_avg_user_px delta_avg_user_interval delta_max_user_px "
    "registration_residual error_blocks "
    "analysis_size input_size user_px_per_analysis_px homography",
}


@pytest.fixture(scope="module")
def pngs(tmp_path_factory):
    """Two crops of a shipped scene, 8 px apart, as PNG files (what a user gives the CLI)."""
    from kornia.io import write_image

    out = tmp_path_factory.mktemp("pair")
    scene = load_scene("gravel")[0, 0]
    for name, img in (("a.png", scene[:320, :424]), ("b.png", scene[8:328, :424])):
        write_image(str(out / name), (img * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous())
    return str(out / "a.png"), str(out / "b.png")


@pytest.fixture(scope="module")
def analysed(pngs):
    """method -> the pair's PairAnalysis, through the Python API."""
    return {m: analyze_pair(*pngs, method=m) for m in KEYS}


@pytest.mark.parametrize("method", list(KEYS))
def test_to_json_is_the_cli_json(pngs, analysed, capsys, method):
    assert main(["analyze", *pngs, "--method", method, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    mine = analysed[method].to_json()
    assert list(printed) == list(mine) == KEYS[method].split()
    # the OpenCV export's least squares rounds differently from call to call (1e-15 on a
    # coefficient at the noise): compared apart, to that precision
    cv_printed, cv_mine = printed.pop("opencv", None), mine.pop("opencv", None)
    assert printed == mine
    assert (cv_printed is None) == (cv_mine is None)
    if cv_mine is not None:
        assert list(cv_printed) == list(cv_mine)
        for key, value in cv_mine.items():
            flat = torch.tensor(value, dtype=torch.float64).flatten().tolist()
            assert torch.tensor(cv_printed[key], dtype=torch.float64).flatten().tolist() == pytest.approx(
                flat, rel=1e-9, abs=1e-12
            ), key


@pytest.mark.parametrize("method", list(KEYS))
def test_summary_is_the_cli_text(pngs, analysed, capsys, method):
    assert main(["analyze", *pngs, "--method", method]) == 0
    assert capsys.readouterr().out == analysed[method].summary() + "\n"


def test_to_json_round_trips_as_strict_json(analysed):
    """NaN and infinities become null; the dict is a copy (editing it leaves the record)."""
    r = dataclasses.replace(analysed["selfcal"], relief_z=float("nan"), registration_residual=float("inf"))
    d = r.to_json()
    assert d["relief_z"] is None and d["registration_residual"] is None
    assert json.loads(json.dumps(d, allow_nan=False)) == d
    d["warnings"].append("edited")
    d["homography"][0][0] = 2.0
    assert "edited" not in r.warnings and r.homography[0][0] != 2.0
    assert d["class"] == r.class_label and "class_label" not in d and "class_max_label" not in d


def test_every_field_is_documented_under_attributes():
    doc = PairAnalysis.__doc__
    block = doc[doc.index("    Attributes:\n"): doc.index("    Example:\n")]
    documented = re.findall(r"^        (\w+): \S", block, flags=re.M)
    assert documented == [f.name for f in dataclasses.fields(PairAnalysis)]
    assert set(JSON_KEYS) <= set(documented)


def test_the_record_is_frozen_and_built_by_keyword(analysed):
    r = analysed["selfcal"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.delta_avg = 1.0
    with pytest.raises(TypeError, match="positional"):
        PairAnalysis("selfcal")
    fields = {f.name: getattr(r, f.name) for f in dataclasses.fields(r)}
    assert PairAnalysis(**fields) == r
