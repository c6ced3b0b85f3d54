"""Keys that became constants of the method: a file or a stored config naming one never silently changes meaning.

The one table is :data:`lensdist_torch.config.retired.RETIRED`; a key at its constant's value
loads (dropped), at any other value it is a one-line error naming the key, the file and the
constant.
"""

from __future__ import annotations

import pytest
from one_line import one_line_error

from lensdist_torch.config import LensdistConfig, config_from_dict, load_config, retired_keys, stored_config
from lensdist_torch.config.retired import RETIRED, Retired

FAKE = ("quality", "old_margin")  # a key of an earlier version, a constant now: the mechanism, whatever the table holds


@pytest.fixture
def fake_constant(monkeypatch):
    monkeypatch.setitem(RETIRED, FAKE, Retired(by="lensdist_torch.calibration.direct.OLD_MARGIN", value=(0.5, 2.0)))


def test_a_removed_key_at_the_constant_loads_and_is_dropped(fake_constant, tmp_path):
    path = tmp_path / "old.toml"
    path.write_text("[quality]\nold_margin = [0.5, 2]\nblock_size = 16\n[image]\nheight = 320\nwidth = 416\n")
    assert load_config(path).quality.block_size == 16
    assert stored_config({"quality": {"old_margin": [0.5, 2.0]}}) == LensdistConfig()  # a checkpoint's config
    assert retired_keys({"quality": {"old_margin": [0.5, 2.0]}}) == []  # loads as it is: a data set's too


@pytest.mark.bad_input
@pytest.mark.parametrize("value", ["[0.5, 3.0]", "[0.5]", "0.5", "true", "'0.5, 2'"])
def test_a_removed_key_at_another_value_is_one_line(fake_constant, tmp_path, value):
    path = tmp_path / "old.toml"
    path.write_text(f"[quality]\nold_margin = {value}\n")
    one_line_error(ValueError, lambda: load_config(path), "quality.old_margin", str(path),
                   "a constant of the method now: lensdist_torch.calibration.direct.OLD_MARGIN")
    one_line_error(ValueError, lambda: stored_config({"quality": {"old_margin": [1.0, 2.0]}}), "quality.old_margin")
    assert retired_keys({"quality": {"old_margin": [1.0, 2.0]}}) == ["quality.old_margin"]


def test_every_constant_of_the_table_is_the_modules():
    """The table's value of each key that became a constant is the constant's, in the module that names it."""
    import importlib

    for (section, key), r in RETIRED.items():
        if r.value is None:
            continue
        module, name = r.by.rsplit(".", 1)
        assert getattr(importlib.import_module(module), name) == r.value, (section, key)
        assert key not in config_from_dict({}).__getattribute__(section).__dataclass_fields__, (section, key)


def test_a_direct_path_key_of_an_earlier_version(tmp_path):
    """``[calibration] outlier_mads`` became ``pooling.OUTLIER_MADS``: at 4 it loads, at 5 it is refused."""
    from lensdist_torch.calibration.pooling import OUTLIER_MADS

    path = tmp_path / "old.toml"
    path.write_text(f"[calibration]\noutlier_mads = {OUTLIER_MADS}\nmotion_steps = [0.14, 0.22]\nparallax = 0\n")
    assert load_config(path).calibration.parallax == 0
    path.write_text("[calibration]\noutlier_mads = 5.0\n")
    one_line_error(ValueError, lambda: load_config(path), "calibration.outlier_mads", str(path),
                   "a constant of the method now: lensdist_torch.calibration.pooling.OUTLIER_MADS")


@pytest.mark.bad_input
def test_calibrate_refuses_a_changed_constant_with_one_line(tmp_path, capsys):
    from lensdist_torch.cli import main as cli_main

    (tmp_path / "frames").mkdir()
    path = tmp_path / "old.toml"
    path.write_text("[calibration]\nmax_motion = 0.5\n")
    assert cli_main(["calibrate", str(tmp_path / "frames"), "--config", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calibration.max_motion" in err and str(path) in err
    assert "a constant of the method now: lensdist_torch.calibration.direct.MAX_MOTION" in err


def test_a_self_calibration_key_of_an_earlier_version(tmp_path):
    """``[selfcal] noise_floor`` became ``selfcal.model.NOISE_FLOOR``: as paper.toml wrote it, it loads."""
    path = tmp_path / "old.toml"
    path.write_text("[selfcal]\nnoise_floor = 0.00196078431372549\ngain_range = [0.25, 4]\nnewton = 5\nparallax = 0\n")
    assert load_config(path).selfcal.parallax == 0
    path.write_text("[selfcal]\nhuber_k = 2.0\n")
    one_line_error(ValueError, lambda: load_config(path), "selfcal.huber_k", str(path),
                   "a constant of the method now: lensdist_torch.selfcal.model.HUBER_K")
    one_line_error(ValueError, lambda: stored_config({"selfcal": {"ridge": 1e-9}}), "selfcal.ridge",
                   "lensdist_torch.selfcal.prior.RIDGE")
