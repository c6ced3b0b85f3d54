"""examples/calibrate_archive.py runs as a user runs it and does what its docstring says."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "calibrate_archive.py"


def _load():
    spec = importlib.util.spec_from_file_location("calibrate_archive", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_calibrate_archive_demo_finds_the_changed_lens(tmp_path, capsys, one_thread_module):
    example = _load()
    run = example.main(["--demo", str(tmp_path), "--method", "direct"])
    assert (run.inputs, run.computed, run.failed) == (5, 5, 1)
    a, b = run.cameras
    truth = float(example.delta_avg([1e-6], [0.0], *example.DEMO_SIZE)[0])
    assert (a.camera, a.inputs, a.pooled) == ("A", 3, 2) and a.delta_avg_low_px <= truth <= a.delta_avg_high_px
    assert [Path(p).name for p in a.disagreeing] == ["dive_03"]  # the lens changed
    assert b.camera == "B" and b.delta_avg_low_px == 0.0 and b.delta_avg_high_px < 0.25 and b.disagreeing == ()
    out = capsys.readouterr().out
    assert "run again: 0 calibrated, 5 reused" in out and "truth" in out
    assert len(list((tmp_path / "answers").glob("*.json"))) == 4 and (tmp_path / "cameras.csv").is_file()


def test_calibrate_archive_wants_a_manifest_or_the_demo(tmp_path):
    with pytest.raises(SystemExit) as info:
        _load().main([str(tmp_path)])
    assert info.value.code == 2
