"""Issue 51, item 3: a pair read from an .mp4 at 640 x 480 gets its Delta_avg interval in the user's
pixels (``delta_avg_user_interval``), and it covers the lens's true Delta_avg over the frame."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lensdist_torch import analyze_pair
from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.workflows.decision import in_user_pixels

K2, SIZE = 1e-6, (480, 640)


def _through_mp4(tmp_path, frames: np.ndarray) -> list[np.ndarray]:
    """The frames written as a lossy H.264 .mp4 (4:2:0, PyAV's default quality) and read back."""
    av = pytest.importorskip("av")
    path = tmp_path / "clip.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = SIZE[1], SIZE[0], "yuv420p"
        for f in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.repeat(f[..., None], 3, 2), format="rgb24")))
        container.mux(stream.encode())
    with av.open(str(path)) as container:
        return [f.to_ndarray(format="gray") for f in container.decode(video=0)]


def test_a_pair_from_an_mp4_has_an_interval_in_the_users_pixels_that_covers(tmp_path):
    frames, _ = synthetic_sequence(6, K2, 0.0, size=SIZE, step_px=(6.0, 10.0), seed=1)
    decoded = _through_mp4(tmp_path, (frames[:, 0].clamp(0, 1) * 255).round().byte().numpy())
    img1, img2 = (torch.from_numpy(decoded[i]).float()[None, None] / 255 for i in (2, 5))
    res = analyze_pair(img1, img2)
    truth = float(delta_avg(torch.tensor([K2]), torch.tensor([0.0]), *SIZE)[0])  # 14.33 px
    assert res.class_label == "3" and res.input_size == list(SIZE)
    lo, hi = res.delta_avg_user_interval
    assert lo <= truth <= hi and lo < res.delta_avg_user_px < hi
    # the analysis frame's interval, carried over by the ratio of the two Deltas
    ratio = res.delta_avg_user_px / res.delta_avg
    assert np.allclose([lo, hi], np.multiply(res.delta_avg_interval, ratio), rtol=1e-12)
    assert "in your 640 x 480 pixels: Delta_avg" in res.summary() and f"[{lo:.1f}, {hi:.1f}] (95 %)" in res.summary()
    assert res.to_json()["delta_avg_user_interval"] == [lo, hi]


def test_the_interval_scales_with_the_frame_when_the_crop_is_the_frame():
    # a 640 x 848 frame is the 320 x 424 analysis frame scaled by 2: the ratio is s exactly
    res = {"k2": 4e-6, "k4": 0.0, "delta_avg": float(delta_avg([4e-6], [0.0], 320, 424)[0]),
           "delta_avg_interval": [15.0, 18.0]}
    user = in_user_pixels(res, 2.0, (640, 848))
    assert user["delta_avg_user_px"] == pytest.approx(2 * res["delta_avg"], rel=1e-12)
    assert user["delta_avg_user_interval"] == pytest.approx([30.0, 36.0], rel=1e-12)
    # no answer, no interval
    assert in_user_pixels({"k2": None, "delta_avg": None}, 2.0, (640, 848))["delta_avg_user_interval"] is None
