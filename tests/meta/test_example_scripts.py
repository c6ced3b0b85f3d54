"""The scripts of examples/ run as a user runs them and do what their docstrings say."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_example_is_tested():
    # calibrate_archive: tests/calibration/test_archive_example.py
    assert sorted(p.stem for p in EXAMPLES.glob("*.py")) == ["calibrate_archive", "calibrate_video",
                                                             "quality_loss_training_step"]


def test_quality_loss_training_step_registers_the_view(capsys):
    shift = _load("quality_loss_training_step").main(["--steps", "120"])
    assert float((shift - torch.tensor([2.0, -3.0])).norm()) < 0.1  # the truth of its misregistered view
    assert "learned shift" in capsys.readouterr().out


def test_calibrate_video_demo_answers_the_rendered_lens(tmp_path, capsys):
    example = _load("calibrate_video")
    answer = example.main(["--demo", str(tmp_path), "--method", "direct"])
    truth = float(example.delta_avg([example.DEMO_K2], [0.0], *example.DEMO_SIZE)[0])
    lo, hi = answer["delta_avg_user_interval"]
    assert answer["class"] == "1" and lo <= truth <= hi
    assert abs(answer["delta_avg_user_px"] / truth - 1) < 0.05
    assert len(list((tmp_path / "undistorted").glob("*.png"))) == 12
    assert len(list((tmp_path / "undistorted" / "masks").glob("*.png"))) == 12
    assert (tmp_path / "calibration.json").is_file() and "truth" in capsys.readouterr().out


def test_calibrate_video_wants_a_path_or_the_demo(tmp_path):
    example = _load("calibrate_video")
    with pytest.raises(SystemExit) as info:
        example.main([str(tmp_path)])  # the output folder alone: neither a PATH nor --demo
    assert info.value.code == 2
