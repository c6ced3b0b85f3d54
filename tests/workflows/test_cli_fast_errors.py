"""A missing input is a one-line error before a command imports torch (seconds of a user's time)."""

import subprocess
import sys

import pytest

CASES = [
    (
        ["analyze", "{tmp}/missing.png", "{tmp}/missing2.png"],
        "lensdist analyze: error: image file not found: {tmp}/missing.png",
    ),
    (["calibrate", "{tmp}/no_frames"], "lensdist calibrate: error: path not found: {tmp}/no_frames"),
    (
        ["undistort", "{tmp}/no_frames", "--out", "{tmp}/out", "--k2", "0"],
        "lensdist undistort: error: path not found: {tmp}/no_frames",
    ),
    (
        ["undistort", "{tmp}", "--from", "{tmp}/none.json", "--out", "{tmp}/out"],
        "lensdist undistort: error: calibration file not found: {tmp}/none.json",
    ),
]

PROBE = """
import sys
from lensdist_torch.cli import main
rc = main(sys.argv[1:])
print(rc, "torch" in sys.modules)
"""


@pytest.mark.parametrize("argv,says", CASES, ids=["analyze", "calibrate", "undistort", "undistort_from"])
def test_a_missing_input_is_refused_before_torch_is_imported(tmp_path, argv, says):
    argv = [a.format(tmp=tmp_path) for a in argv]
    run = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["2", "False"], (run.stdout, run.stderr)
    assert run.stderr == says.format(tmp=tmp_path) + "\n"


def test_analyzing_a_pair_does_not_import_torchmetrics():
    # the stateful metrics' torchmetrics costs about a second of imports that one pair's answer never uses
    probe = ("import sys\nfrom lensdist_torch.workflows.analyze import analyze_pair\n"
             "print('torchmetrics' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["False"], (run.stdout, run.stderr)
    run = subprocess.run([sys.executable, "-c", "from lensdist_torch.metric import RegistrationQualityMetric as M\n"
                          "print(M.__module__)"], capture_output=True, text=True, timeout=120)
    assert run.stdout.split() == ["lensdist_torch.metric.stateful"], run.stderr
