"""Real footage with a known truth: twelve real GoPro views (tests/data/real, MIT) through known lenses.

The views' own lens (a chessboard calibration, 0.56 px RMS) is undone and a known eq. 4 lens is
applied (``lensdist_torch.data.relens``): the real scene, light, noise, JPEG and wide-baseline
motion of a hand-held camera, with a truth. ``calibrate_sequence`` must cover the truth with its
95 % interval, land within 15 % of it (0.6 px below 4 px), and never give a class that is wrong.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.core import load_image
from lensdist_torch.data.relens import relens_frames
from lensdist_torch.geometry import calibrate_sequence
from lensdist_torch.geometry.distortion import CLASS_LABELS, delta_avg, estimated_class, paper_frame_delta_avg

REAL = Path(__file__).parents[1] / "data" / "real" / "gopro_hero4_wall"


@pytest.fixture(scope="module")
def views(one_thread_module):
    cal = json.loads((REAL / "calibration.json").read_text())
    return torch.cat([load_image(REAL / name) for name in cal["frames"]]), cal


@pytest.mark.slow
# Delta_avg 0, 3.58 and 14.33 px at 320 x 240; before the pooling and the second start these views gave
# 0.06, 2.18 and 5.70 px (the last two outside the tolerance below), now 0.06, 3.66 and 12.80
@pytest.mark.parametrize("k2", [0.0, 2e-6, 8e-6])
def test_real_views_through_a_known_lens(views, k2):
    frames, cal = views
    out = relens_frames(frames, cal["K"], cal["dist"], k2, 0.0)
    assert out.valid_fraction == 1.0  # the wide source covers the milder lens's view: no guessed pixels
    res = calibrate_sequence(out.frames)
    truth = float(delta_avg([k2], [0.0], 240, 320)[0])
    lo, hi = res.delta_avg_user_interval
    assert lo <= truth <= hi
    assert abs(res.delta_avg_user_px - truth) <= 0.15 * max(truth, 4.0)
    if res.class_label is not None:  # a class, when given, is the truth's
        cfg = LensdistConfig()
        paper = torch.tensor([paper_frame_delta_avg(k2, 0.0, (240, 320), cfg)])  # the same lens at 320 x 424
        assert res.class_label == CLASS_LABELS[int(estimated_class(paper, paper, "delta_avg", cfg)[0])]
