"""The multi-view path's series of mappings and its speed-ups keep its answers: failed mappings retried
and one mapping where the first shows degenerate motion (lensdist_torch.workflows.multiview), the
skipped seeds named (geometry.multiview_runs), the bundle adjustments' tolerance (geometry.multiview)."""

from pathlib import Path

import pytest
import torch

from lensdist_torch.config import MultiViewConfig
from lensdist_torch.geometry.multiview import BA_FUNCTION_TOLERANCE, MultiViewCalibration
from lensdist_torch.geometry.multiview_runs import combine_reconstructions
from lensdist_torch.workflows import multiview as wmv

DEGENERATE = "degenerate motion: the camera turned by at most 2.4 degrees"


def _cal(d, rotation, registered=22, label=None, reason=DEGENERATE):
    return MultiViewCalibration(
        "FULL_OPENCV", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]], [-0.2, 0.05, 0, 0, 0], d, (0.0, d + 12.0), 5 * d,
        (0.0, 5 * d + 40), 1.0, 2e-6, 0.0, 0.1, label, reason, registered, 22, 6052, 0.33, {}, [d] * 6, rotation,
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

    def reconstruct(folder, names, cfg, stop=None, image_size=None, on_matches=None):
        assert image_size == (288, 384)  # the features' cap follows the frames' area
        assert callable(on_matches)  # the homography model reads the matches before any mapping (no database here)
        calls["names"], calls["files"] = list(names), sorted(p.name for p in Path(folder).iterdir())
        out = []
        for i in range(cfg.reconstructions + (cfg.extra_mappings if stop is not None else 0)):
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
    ok = [_cal(d, 30.0, label="3", reason="")._replace(delta_avg_user_interval=(d - 1, d + 1)) for d in (8.0, 8.4, 7.8, 99.0)]
    calls = _fake_colmap(monkeypatch, tmp_path, [ok[0], 3, 0, ok[1], ok[2], ok[3]])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 5 and res["ok"] and res["class_label"] == "3" and res["delta_avg_user_px"] == 8.0
    assert [r["seed"] for r in res["reconstructions"]] == [0, 1, 2, 3, 4]
    assert res["reconstructions"][1] == {"seed": 1, "failed": "3 of 22 frames registered"}
    assert res["reconstructions"][2] == {"seed": 2, "failed": "0 of 22 frames registered"}
    # all six tries run, two succeed: no class, the failures named
    calls = _fake_colmap(monkeypatch, tmp_path, [ok[0], 3, 3, 3, 3, ok[1]])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 6 and res["class_label"] is None
    assert res["reason"].startswith("only 2 of 6 reconstructions succeeded (3 needed)") and "seed 4: 3 of 22" in res["reason"]
    # degenerate motion after a failed start: the two successes still missing are skipped, not tried
    calls = _fake_colmap(monkeypatch, tmp_path, [3, _cal(12.3, 2.4), ok[0]])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 2 and [r["seed"] for r in res["reconstructions"]] == [0, 1, 2, 3]
    assert res["reconstructions"][2] == {"seed": 2, "skipped": "degenerate motion in the first mapping"}
    assert res["class_label"] is None and res["reason"].startswith(DEGENERATE)


def test_no_mapping_is_skipped_while_the_successful_ones_disagree_on_the_motion(monkeypatch, tmp_path):
    # a CI run on 10 rendered frames: seed 0 turned 5.7 degrees, seed 1 under 2; skipping seed 2 there left the
    # median answer at 5.7 degrees with a seed skipped (a ValueError in combine_reconstructions): all three run now
    turned, still = _cal(8.0, 5.7, label="3", reason=""), _cal(8.2, 1.0)
    calls = _fake_colmap(monkeypatch, tmp_path, [turned, still, _cal(8.1, 5.5, label="3", reason="")])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 3 and res["ok"] and all("skipped" not in r for r in res["reconstructions"])


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
    wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig(mapped_frames=5))
    assert calls["names"] == [f"frame_{i:03d}.png" for i in (0, 5, 10, 16, 21)]  # of 22 frames


def test_a_long_video_is_written_with_a_doubling_stride(monkeypatch, tmp_path):
    from lensdist_torch.workflows import calibrate

    clip = tmp_path / "clip.mp4"
    clip.write_bytes(b"")
    monkeypatch.setattr(calibrate, "read_frames", lambda path, grey, most: ((str(i), torch.full((1, 1, 8, 8), i / 100))
                                                                          for i in range(min(most, 100))))
    (tmp_path / "frames").mkdir()
    calls = _fake_colmap(monkeypatch, tmp_path / "frames", [_cal(7.6, 30.0, label="3", reason="")] * 3)
    wmv.multiview_path(clip, (288, 384), MultiViewConfig(mapped_frames=10), max_frames=90)
    # 90 frames: the stride doubled to 4 past 20 files and to 8 past 20 again; kept 0, 8, ..., 88 (12 files)
    assert calls["files"] == [f"{i:06d}.png" for i in range(0, 90, 8)]
    assert calls["names"] == [f"{8 * j:06d}.png" for j in (0, 1, 2, 4, 5, 6, 7, 9, 10, 11)]


def test_degenerate_first_mapping_answers_after_one_mapping(monkeypatch, tmp_path):
    # 22 rendered frames of 384 x 288 panning over relief (the speed goal's sequence): the camera turned
    # by 2.4 degrees in every mapping (seeds 0-2: 2.4, 2.4, 2.3), each mapping and its self-calibration
    # cost 3 min of the 4 min 52 s; now one runs, and the answer says which seeds were skipped
    calls = _fake_colmap(monkeypatch, tmp_path, [_cal(12.30, 2.38), _cal(12.24, 2.38), _cal(13.02, 2.31)])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 1
    assert res["ok"] and res["class_label"] is None and res["reason"].startswith(DEGENERATE)
    assert "1 of 3 mappings run" in res["reason"] and "lacks the spread between reconstructions" in res["reason"]
    assert [r.get("skipped") is not None for r in res["reconstructions"]] == [False, True, True]
    assert res["delta_avg_user_interval"] == pytest.approx((0.3, 24.3))  # the one run's half-width, 12 px


@pytest.mark.parametrize("first", [_cal(12.3, 4.6), _cal(12.3, 2.4, registered=20)],
                         ids=["near-the-limit", "not-every-frame"])
def test_all_mappings_run_unless_the_first_settles_degenerate_motion(monkeypatch, tmp_path, first):
    # 4.6 degrees is under the 5 needed but within 10 % of it: another seed could cross it; a mapping that
    # left frames out may not have seen the turn
    calls = _fake_colmap(monkeypatch, tmp_path, [first, _cal(12.2, 4.6), _cal(13.0, 4.7)])
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 3 and res["class_label"] is None
    assert "skipped" not in res["reason"] and res["reconstruction_spread_px"] == pytest.approx(0.7)


def test_a_turning_camera_runs_every_mapping(monkeypatch, tmp_path):
    # the same frames with +-3 degrees of yaw: 5.97 degrees in every mapping
    runs = [_cal(7.65, 5.97, label=None, reason="interval too wide: +-4.18 px")] * 3
    calls = _fake_colmap(monkeypatch, tmp_path, runs)
    res = wmv.multiview_path(tmp_path, (288, 384), MultiViewConfig())
    assert calls["mappings"] == 3 and len(res["reconstructions"]) == 3
    assert all("skipped" not in r for r in res["reconstructions"])


def test_skipped_seeds_only_with_degenerate_motion():
    res = combine_reconstructions([(0, _cal(10.0, 2.4))], skipped=[1, 2])
    assert res.class_label is None and res.reason.startswith(DEGENERATE) and "1 of 3 mappings run" in res.reason
    assert res.reconstructions[1] == {"seed": 1, "skipped": "degenerate motion in the first mapping"}
    with pytest.raises(ValueError, match=r"^skipped must be empty unless the motion is degenerate, got 2 seeds"):
        combine_reconstructions([(0, _cal(10.0, 6.0, label="3", reason=""))], skipped=[1, 2])


def test_a_cut_short_multiview_interval_does_not_win_over_the_direct_one():
    # neither path can tell: the numbers are the less uncertain path's, but not a multi-view interval
    # that lacks the spread between reconstructions
    direct = {"class": None, "reason": "interval too wide", "delta_avg_user_px": 7.0,
              "delta_avg_user_interval": [0.0, 20.0], "delta_max_user_px": 40.0, "delta_max_user_interval": [0.0, 90.0]}
    mv = {"ok": True, **combine_reconstructions([(0, _cal(10.0, 2.4))], skipped=[1, 2])._asdict()}
    mv["delta_avg_user_interval"] = (9.0, 11.0)  # narrower than the direct one, relatively
    assert wmv.combine(direct, mv)["method"] == "direct"
    mv["reconstructions"] = mv["reconstructions"][:1]  # all mappings run: the narrower one wins
    assert wmv.combine(direct, mv)["method"] == "multiview"


def test_bundle_adjustments_stop_at_ceres_default_tolerance(monkeypatch):
    pycolmap = pytest.importorskip("pycolmap")
    from lensdist_torch.geometry import multiview

    seen = []
    monkeypatch.setattr(pycolmap, "bundle_adjustment",
                        lambda rec, options: seen.append(options.ceres.solver_options.function_tolerance))
    multiview._adjust(object())
    assert seen == [BA_FUNCTION_TOLERANCE] == [1e-6]
