"""The multi-view path's series of mappings and its speed-ups keep its answers: failed mappings retried,
every mapping run whatever the camera's motion (lensdist_torch.calibration.controllers.multiview_path), the bundle
adjustments' tolerance (calibration.multiview)."""

import dataclasses
from pathlib import Path

import pytest
import torch

from lensdist_torch.calibration.controllers import multiview_path as wmv
from lensdist_torch.calibration.multiview import EXTRA_MAPPINGS, MultiViewCalibration
from lensdist_torch.config import MultiViewConfig

WIDE = "the interval [0.30, 24.30] px at the paper's frame spans classes 1, 2, 3 and 4"


def _cal(d, rotation, registered=22, label=None, reason=WIDE):
    return MultiViewCalibration(
        model="FULL_OPENCV", camera_matrix=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]], dist_coeffs=[-0.2, 0.05, 0, 0, 0],
        delta_avg_user_px=d, delta_avg_user_interval=(0.0, d + 12.0), delta_max_user_px=5 * d,
        delta_max_user_interval=(0.0, 5 * d + 40), invertible_fraction=1.0, k2_user=2e-6, k4_user=0.0,
        eq4_fit_error_px=0.1, class_label=label, reason=reason, registered=registered, frames=22, points3D=6052,
        observations=60000, reprojection_px=0.33, models={}, jackknife=[d] * 6, rotation_spread_deg=rotation,
        paper_delta_avg_px=d)


def _fake_colmap(monkeypatch, tmp_path, answers):
    """22 frames; ``reconstruct`` runs the mappings as the real one does (``stop`` after each), counted.

    ``answers``: per mapping seed its self-calibration, or an int: a mapping that registered that many frames.
    """
    pytest.importorskip("pycolmap")
    for i in range(22):
        (tmp_path / f"frame_{i:03d}.png").write_bytes(b"")
    calls = {"mappings": 0}

    class Rec:
        def __init__(self, answer):
            self.answer = answer
            self.n = answer if isinstance(answer, int) else answer.registered

        def num_reg_images(self):
            return self.n

        def num_points3D(self):
            return 100 * self.n

    def reconstruct(folder, names, *, config, stop=None, image_size=None, on_matches=None, on_stage=None):
        assert image_size == (288, 384)  # the features' cap follows the frames' area
        assert callable(on_matches)  # the homography model reads the matches before any mapping (no database here)
        calls["names"], calls["files"] = list(names), sorted(p.name for p in Path(folder).iterdir())
        out = []
        for i in range(config.reconstructions + (EXTRA_MAPPINGS if stop is not None else 0)):
            calls["mappings"] += 1
            out.append(Rec(answers[i]))
            if stop is not None and stop(i, out[-1]):
                break
        return out

    monkeypatch.setattr(wmv, "reconstruct", reconstruct)
    monkeypatch.setattr(wmv, "self_calibrate_reconstruction", lambda rec, *a, **k: rec.answer)
    return calls


def test_failed_mappings_are_retried_with_further_seeds(monkeypatch, tmp_path):
    # the GoPro views: seeds 1 and 2 stop at 3 views in about a second; 0, 3 and 4 answer, seed 5 never runs
    ok = [
        dataclasses.replace(_cal(d, 30.0, label="3", reason=""), delta_avg_user_interval=(d - 1, d + 1))
        for d in (9.0, 9.4, 8.8, 99.0)
    ]
    calls = _fake_colmap(monkeypatch, tmp_path, [ok[0], 3, 0, ok[1], ok[2], ok[3]])
    res = wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig(reconstructions=3))
    assert calls["mappings"] == 5 and res["ok"] and res["class_label"] == "3" and res["delta_avg_user_px"] == 9.0
    assert [r["seed"] for r in res["reconstructions"]] == [0, 1, 2, 3, 4]
    assert res["reconstructions"][1] == {"seed": 1, "failed": "3 of 22 frames registered"}
    assert res["reconstructions"][2] == {"seed": 2, "failed": "0 of 22 frames registered"}
    # all six tries run, two succeed: no class, the failures named
    calls = _fake_colmap(monkeypatch, tmp_path, [ok[0], 3, 3, 3, 3, ok[1]])
    res = wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig(reconstructions=3))
    assert calls["mappings"] == 6 and res["class_label"] is None
    assert (
        res["reason"].startswith("only 2 of 6 reconstructions succeeded (3 needed)")
        and "seed 4: 3 of 22" in res["reason"]
    )
    # a slow pan after a failed start: the three successes run (no mapping is skipped for the motion)
    calls = _fake_colmap(monkeypatch, tmp_path, [3, _cal(12.3, 2.4), _cal(12.2, 2.4), _cal(13.0, 2.3)])
    res = wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig(reconstructions=3))
    assert calls["mappings"] == 4 and [r["seed"] for r in res["reconstructions"]] == [0, 1, 2, 3]
    assert res["class_label"] is None and res["reason"] == WIDE
    # the default: one mapping answers, after failed starts
    calls = _fake_colmap(monkeypatch, tmp_path, [3, 0, ok[1], ok[0]])
    res = wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig())
    assert calls["mappings"] == 3 and res["class_label"] == "3" and res["delta_avg_user_px"] == 9.4
    assert res["reconstruction_spread_px"] == 0.0 and tuple(res["delta_avg_user_interval"]) == (8.4, 10.4)


def test_evenly_spaced_frames_by_hand_and_their_properties():
    assert wmv.evenly_spaced(10, 4) == [0, 3, 6, 9] and wmv.evenly_spaced(3, 60) == [0, 1, 2]
    for n in range(3, 400, 7):
        for most in (3, 10, 60):
            idx = wmv.evenly_spaced(n, most)
            assert len(idx) == min(n, most) and idx[0] == 0 and idx[-1] == n - 1 and idx == sorted(set(idx))
            gaps = [b - a for a, b in zip(idx, idx[1:])]
            assert max(gaps) - min(gaps) <= 1  # as even as whole frames allow


def test_at_most_mapped_frames_go_to_colmap(monkeypatch, tmp_path):
    runs = [_cal(7.6, 30.0, label="3", reason="")] * 3
    calls = _fake_colmap(monkeypatch, tmp_path, runs)
    wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig(mapped_frames=5))
    assert calls["names"] == [f"frame_{i:03d}.png" for i in (0, 5, 10, 16, 21)]  # of 22 frames


def test_a_long_video_is_written_with_a_doubling_stride(monkeypatch, tmp_path):
    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"")
    monkeypatch.setattr(wmv, "read_frames", lambda path, grey, most: ((str(i), torch.full((1, 1, 8, 8), i / 100))
                                                                          for i in range(min(most, 100))))
    (tmp_path / "frames").mkdir()
    calls = _fake_colmap(monkeypatch, tmp_path / "frames", [_cal(7.6, 30.0, label="3", reason="")] * 3)
    wmv.multiview_path(clip, (288, 384), config=MultiViewConfig(mapped_frames=10), max_frames=90)
    # 90 frames: the stride doubled to 4 past 20 files and to 8 past 20 again; kept 0, 8, ..., 88 (12 files)
    assert calls["files"] == [f"{i:06d}.png" for i in range(0, 90, 8)]
    assert calls["names"] == [f"{8 * j:06d}.png" for j in (0, 1, 2, 4, 5, 6, 7, 9, 10, 11)]


@pytest.mark.parametrize("rotations", [(2.4, 2.4, 2.3), (5.97, 5.97, 5.97)], ids=["pan", "turning"])
def test_every_mapping_runs_whatever_the_camera_turned(monkeypatch, tmp_path, rotations):
    # 22 rendered frames of 384 x 288 panning over relief (seeds 0-2 turned 2.4, 2.4, 2.3 degrees), and the same
    # frames with +-3 degrees of yaw: the motion is no rule; each mapping's answer, and their spread, speaks
    runs = [dataclasses.replace(_cal(d, r, label="3", reason=""), delta_avg_user_interval=(d - 0.5, d + 0.5))
            for d, r in zip((12.3, 12.24, 13.02), rotations)]
    calls = _fake_colmap(monkeypatch, tmp_path, runs)
    res = wmv.multiview_path(tmp_path, (288, 384), config=MultiViewConfig(reconstructions=3))
    assert calls["mappings"] == 3 and [r["seed"] for r in res["reconstructions"]] == [0, 1, 2]
    assert res["delta_avg_user_px"] == 12.3 and res["reconstruction_spread_px"] == pytest.approx(0.72)
    half = res["delta_avg_user_interval"][1] - 12.3  # sqrt(0.5^2 + (1.96 0.72)^2): the spread widens it
    assert half == pytest.approx(1.5, abs=0.01) and res["class_label"] == "4" and res["reason"] == ""
