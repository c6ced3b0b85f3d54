"""Every sequence path answers with one record: LensAnswer's core, then the path's own diagnostics."""

import dataclasses

import pytest

from lensdist_torch.calibration import LensAnswer, PlanarCalibration, SequenceCalibration
from lensdist_torch.calibration.multiview import MultiViewCalibration

CORE = ["k2_user", "k4_user", "delta_avg_user_px", "delta_avg_user_interval", "delta_max_user_px",
        "delta_max_user_interval", "class_label", "reason"]
RECORDS = [SequenceCalibration, MultiViewCalibration, PlanarCalibration]


def test_the_core_is_the_eight_fields_of_an_answer():
    assert [f.name for f in dataclasses.fields(LensAnswer)] == CORE


@pytest.mark.parametrize("record", RECORDS, ids=lambda r: r.__name__)
def test_each_path_record_is_the_core_then_its_own(record):
    names = [f.name for f in dataclasses.fields(record)]
    assert issubclass(record, LensAnswer) and names[: len(CORE)] == CORE
    assert not set(record.__annotations__) & set(CORE)  # declared once, in LensAnswer


@pytest.mark.parametrize("record", RECORDS, ids=lambda r: r.__name__)
def test_each_field_is_documented_under_attributes(record):
    doc = record.__doc__ + LensAnswer.__doc__
    attributes = doc.split("Attributes:")[1] + LensAnswer.__doc__.split("Attributes:")[1]
    missing = [f.name for f in dataclasses.fields(record) if f"\n        {f.name}:" not in attributes]
    assert missing == []


@pytest.mark.parametrize("record", RECORDS, ids=lambda r: r.__name__)
def test_records_are_frozen_and_keyword_only(record):
    nan = float("nan")
    core = dict(k2_user=nan, k4_user=nan, delta_avg_user_px=nan, delta_avg_user_interval=(nan, nan),
                delta_max_user_px=nan, delta_max_user_interval=(nan, nan), class_label=None, reason="r")
    with pytest.raises(TypeError, match="positional"):
        record(*core.values())
    a = LensAnswer(**core)
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.reason = "changed"
    assert a.to_dict()["reason"] == "r" and list(a.to_dict()) == CORE
