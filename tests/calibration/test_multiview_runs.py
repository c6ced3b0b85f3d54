"""Several reconstructions of one sequence: the spread between them in the interval, and one-thread runs
that repeat exactly (lensdist_torch.calibration.multiview_runs, calibration.multiview.reconstruct)."""

import math
from pathlib import Path

import pytest

from lensdist_torch.calibration.multiview import MultiViewCalibration
from lensdist_torch.calibration.multiview_runs import (
    combine_reconstructions,
    reconstruction_spread,
    widened_interval,
)
from lensdist_torch.calibration.sequence_class import interval_class
from lensdist_torch.config import LensdistConfig, MultiViewConfig

Z = 1.959963984540054  # the normal quantile at 97.5 %: the models' posteriors are normal


def _cal(d, lo, hi, label="4", reason="", registered=28, rms=1.3, paper=None):
    """A reconstruction's answer; ``paper``: its Delta_avg at the paper's frame (default d: a frame of the paper's
    size)."""
    return MultiViewCalibration(
        model="RADIAL", camera_matrix=[[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1]], dist_coeffs=[-0.2, 0.05, 0, 0, 0],
        delta_avg_user_px=d, delta_avg_user_interval=(lo, hi), delta_max_user_px=2 * d,
        delta_max_user_interval=(2 * lo, 2 * hi), invertible_fraction=0.9, k2_user=-1e-7, k4_user=0.0,
        eq4_fit_error_px=0.5, class_label=label, reason=reason, registered=registered, frames=37, points3D=1000,
        observations=20000, reprojection_px=rms, models={}, jackknife=[d] * 6, rotation_spread_deg=40.0,
        paper_delta_avg_px=d if paper is None else paper)


def test_spread_joins_the_interval_in_quadrature_by_hand():
    # answer 100 +- 10 (its models' mixture); the others 104 and 97: spread 4,
    # half-width sqrt(10^2 + (1.96 * 4)^2) = sqrt(100 + 61.466) = 12.707
    runs = [(0, _cal(104.0, 95.0, 113.0)), (1, _cal(100.0, 90.0, 110.0)), (2, _cal(97.0, 88.0, 106.0))]
    assert reconstruction_spread([104.0, 100.0, 97.0], 100.0) == 4.0
    assert widened_interval(100.0, (90.0, 110.0), 4.0, Z) == pytest.approx((87.293, 112.707), abs=1e-3)
    # a lopsided mixture keeps its sides: 100 (-12, +3), spread 4: sqrt(144 + 61.466), sqrt(9 + 61.466)
    assert widened_interval(100.0, (88.0, 103.0), 4.0, Z) == pytest.approx((85.666, 108.394), abs=1e-3)
    res = combine_reconstructions(runs, THREE)
    assert res.delta_avg_user_px == 100.0 and res.reconstruction_spread_px == 4.0  # the median answers
    assert res.delta_avg_user_interval == pytest.approx((87.293, 112.707), abs=1e-3)
    # Delta_max: 200 +- 20, spread 8: sqrt(400 + (1.96 * 8)^2) = 25.414
    assert res.delta_max_user_interval == pytest.approx((174.586, 225.414), abs=1e-3)
    assert res.class_label == "4" and res.reason == ""  # [87.3, 112.7] lies in class 4 (10.8 px and up)
    assert [r["seed"] for r in res.reconstructions] == [0, 1, 2] and res.reconstructions[2]["delta_avg_user_px"] == 97.0
    # class 3 each (7.2-10.8 px; +-2 px, overlapping), spread 1.5 (others 10.5 and 8): sqrt(4 + (1.96 * 1.5)^2)
    # = 3.556 px, [5.444, 12.556]: classes 2 to 4, no class, the spread named
    wide = combine_reconstructions([(0, _cal(10.5, 8.5, 12.5, label="3")), (1, _cal(9.0, 7.0, 11.0, label="3")),
                                    (2, _cal(8.0, 6.0, 10.0, label="3"))])
    assert wide.class_label is None and wide.delta_avg_user_interval[1] == pytest.approx(12.556, abs=1e-3)
    assert wide.reason == ("the interval [5.44, 12.56] px at the paper's frame spans classes 2, 3 and 4 (the 3 "
                           "reconstructions differ by up to 1.50 px)")


def test_one_reconstruction_keeps_its_interval():
    res = combine_reconstructions([(5, _cal(100.0, 90.0, 110.0))], MultiViewConfig(reconstructions=1))
    assert res.delta_avg_user_interval == pytest.approx((90.0, 110.0)) and res.reconstruction_spread_px == 0.0
    assert res.class_label == "4"


def test_reconstructions_that_disagree_beyond_their_intervals_cannot_tell():
    """The GoPro views' runs of 2026-11-24 (truth 103.2 px): 122.4 [107.3, 137.5] alone was confidently wrong."""
    runs = [
        (0, _cal(122.4, 107.3, 137.5)),
        (1, _cal(53.0, 17.9, 88.2, label=None, reason="interval too wide: +-35.15 px")),
        (2, _cal(119.2, 61.2, 177.3, label=None, reason="interval too wide: +-58.05 px")),
    ]
    res = combine_reconstructions(runs, THREE)
    assert res.class_label is None and res.delta_avg_user_px == 119.2
    assert res.reason.startswith(
        "the reconstructions disagree beyond their intervals (seed 0 122.40 px [107.30, 137.50]"
    )
    lo, hi = res.delta_avg_user_interval
    assert lo <= 103.2 <= hi and res.reconstruction_spread_px == pytest.approx(66.2)
    assert hi - 119.2 == pytest.approx(math.hypot(58.1, Z * 66.2), abs=1e-9)


THREE = MultiViewConfig(reconstructions=3)  # the engine's variation measured over three mappings


def test_too_few_reconstructions_cannot_tell_and_a_median_of_two_prefers_more_views():
    res = combine_reconstructions([(0, _cal(100.0, 95.0, 105.0)), (1, "5 of 37 frames registered"),
                                   (2, "0 of 37 frames registered")], THREE)
    assert res.class_label is None and res.reason.startswith("only 1 of 3 reconstructions succeeded (3 needed)")
    assert "seed 1: 5 of 37 frames registered" in res.reason and res.reconstructions[1] == {
        "seed": 1,
        "failed": "5 of 37 frames registered",
    }
    two = combine_reconstructions(
        [(0, _cal(100.0, 95.0, 105.0, registered=20)), (1, _cal(102.0, 97.0, 107.0, registered=30))], THREE
    )
    assert two.delta_avg_user_px == 102.0 and two.reconstruction_spread_px == 2.0
    with pytest.raises(ValueError, match="at least one successful reconstruction"):
        combine_reconstructions([(0, "0 of 37 frames registered")], THREE)


def test_failed_starts_beside_enough_successes_keep_the_class_and_are_listed():
    # the GoPro views' seeds 0-4: 1 and 2 register 3 of 37 frames; 0, 3 and 4 answer
    runs = [(0, _cal(100.0, 90.0, 110.0)), (1, "3 of 37 frames registered"), (2, "3 of 37 frames registered"),
            (3, _cal(98.0, 88.0, 108.0)), (4, _cal(103.0, 93.0, 113.0))]
    res = combine_reconstructions(runs, THREE)
    assert res.class_label == "4" and res.delta_avg_user_px == 100.0 and res.reconstruction_spread_px == 3.0
    assert [r.get("failed") for r in res.reconstructions] == [None, "3 of 37 frames registered",
                                                              "3 of 37 frames registered", None, None]
    short = combine_reconstructions(runs[:4], THREE)  # two successes of three needed
    assert short.class_label is None and short.reason.startswith("only 2 of 4 reconstructions succeeded (3 needed)")


def test_the_answers_own_reason_stays():
    own = "the interval [0.20, 0.31] px at the paper's frame spans the no-distortion threshold (0.25 px)"
    res = combine_reconstructions(
        [(0, _cal(10.0, 9.8, 10.2, label=None, reason=own)), (1, _cal(10.1, 9.9, 10.3, label=None, reason=own))],
        MultiViewConfig(reconstructions=2),
    )
    assert res.class_label is None and res.reason == own


def test_a_sequence_class_scales_its_interval_to_the_papers_frame_by_hand():
    """R below calibration.no_distortion_px (0.25 px at the paper's frame); an interval spanning it cannot tell.

    A frame twice the paper's (640 x 848) with the lens of Delta_avg 0.3 px at the paper's: 0.6 px here,
    so +-0.2 px here is +-0.1 px there, [0.2, 0.4] spanning 0.25; +-0.08 px is [0.26, 0.34]: class 1.
    """
    st = LensdistConfig()
    assert interval_class(0.3, 0.6, (0.52, 0.68), st) == ("1", "")
    label, reason = interval_class(0.3, 0.6, (0.4, 0.8), st)
    assert label is None and reason == ("the interval [0.20, 0.40] px at the paper's frame spans the no-distortion "
                                        "threshold (0.25 px): a distortion or none cannot be told")
    assert interval_class(0.1, 0.2, (0.18, 0.22), st) == ("R", "")  # [0.09, 0.11]: below it
    assert interval_class(0.1, 0.2, (-0.5, 0.22), st) == ("R", "")  # a lower end below 0 is 0
    label, reason = interval_class(math.nan, 0.6, (0.52, 0.68), st)
    assert label is None and reason.startswith("no class: Delta_avg 0.6 px in [0.52, 0.68], nan px at the paper's")
    assert interval_class(0.3, 0.6, (0.52, math.inf), st)[0] is None  # no upper bound: no class
    # a class bin is 3.6 px wide at the paper's frame: [3.7, 7.1] is class 2 however wide, [3.5, 3.7] spans 1 and 2
    assert interval_class(5.0, 5.0, (3.7, 7.1), st) == ("2", "")
    assert interval_class(3.6, 3.6, (3.5, 3.7), st)[1].endswith("spans classes 1 and 2")


def test_the_widened_interval_that_spans_the_r_threshold_cannot_tell():
    """Three reconstructions each confidently class 1 (0.40 px at the paper's frame, +-0.1 px of 0.5 px here, the
    intervals overlapping); their spread widens the interval until it spans 0.25 px there: "cannot tell"."""
    def runs(*deltas):
        return [(s, _cal(d, d - 0.1, d + 0.1, label="1", paper=0.8 * d)) for s, d in enumerate(deltas)]

    res = combine_reconstructions(runs(0.5, 0.62, 0.45))
    half = res.delta_avg_user_interval[1] - 0.5  # sqrt(0.1^2 + (z 0.12)^2) = 0.256 px here, 0.204 px there
    assert half == pytest.approx(math.hypot(0.1, Z * 0.12), abs=1e-9)
    assert res.class_label is None and res.reason.startswith("the interval [0.20, 0.60] px at the paper's frame spans")
    tight = combine_reconstructions(runs(0.5, 0.52, 0.49))  # sqrt(0.1^2 + (z 0.02)^2) = 0.107 px: [0.31, 0.49] there
    assert tight.class_label == "1" and tight.reason == ""


@pytest.mark.bad_input
@pytest.mark.parametrize("value", [0, -1, 1.5, "3", True])
def test_reconstructions_must_be_a_positive_int(value):
    with pytest.raises(ValueError, match=r"^multiview.reconstructions must be a positive int, got "):
        MultiViewConfig(reconstructions=value)


# ------------------------------------------------------------------ the same numbers, run after run
def test_reconstructions_repeat_exactly_with_the_default_threads(tmp_path):
    # the extraction and the verification in two shards of one thread each, the matching and the mapping on one:
    # with COLMAP's own threads the 12 GoPro views' verified matches changed from run to run
    pycolmap = pytest.importorskip("pycolmap")
    from lensdist_torch.calibration.multiview import reconstruct

    real = Path(__file__).parents[1] / "data" / "real" / "gopro_hero4_wall"
    names = sorted(p.name for p in real.glob("*.jpg"))
    cfg = MultiViewConfig(reconstructions=2)
    assert cfg.num_threads == 2

    def numbers():
        recs = reconstruct(real, names, config=cfg, image_size=(240, 320))
        assert len(recs) == 2 and all(isinstance(r, pycolmap.Reconstruction) for r in recs)
        return [(r.num_reg_images(), r.num_points3D(), [float(v) for v in next(iter(r.cameras.values())).params])
                for r in recs]

    first = numbers()
    assert first == numbers() == numbers()  # bit for bit
    assert first[0][0] >= 2 and first[0][2] != first[1][2]  # the second seed is another reconstruction


@pytest.mark.parametrize("frames", [4, 40])
def test_the_matching_runs_on_one_thread_whatever_num_threads(monkeypatch, tmp_path, frames):
    # on two threads COLMAP's CPU matcher kept a fraction of some pairs' matches, at random (60 frames of 968 x 608:
    # 2 and 20 of 297 pairs between runs, 4324 -> 2930 matches); on one, runs repeat (docs/method.md, section 11)
    pc = pytest.importorskip("pycolmap")
    from lensdist_torch.calibration import features

    seen = []
    monkeypatch.setattr(features, "extract_in_shards", lambda *a, **k: None)
    monkeypatch.setattr(features, "verify_in_shards", lambda *a, **k: None)
    for name in ("match_exhaustive", "match_sequential"):
        monkeypatch.setattr(pc, name, lambda db, *, matching_options, _name=name, **k: seen.append(
            (_name, matching_options.num_threads)))
    features.extract_and_match(tmp_path / "db.db", tmp_path, [f"f{i}.png" for i in range(frames)],
                               config=MultiViewConfig(num_threads=2))
    assert seen == [("match_exhaustive" if frames <= features.EXHAUSTIVE_BELOW else "match_sequential", 1)]


@pytest.mark.parametrize("threads", [2, 3])
def test_the_extraction_in_shards_is_one_threads_extraction_bit_for_bit(tmp_path, threads):
    # the peer: COLMAP's own extraction on one thread (its ids in the frames' order); the shards run side by side
    pc = pytest.importorskip("pycolmap")
    import numpy as np

    from lensdist_torch.calibration.features import extract_in_shards

    real = Path(__file__).parents[1] / "data" / "real" / "gopro_hero4_wall"
    names = sorted(p.name for p in real.glob("*.jpg"))[:5]
    reader = pc.ImageReaderOptions()
    reader.camera_model = "RADIAL"
    extraction = pc.FeatureExtractionOptions()
    extraction.num_threads, extraction.max_image_size, extraction.use_gpu = 1, 320, False
    pc.extract_features(tmp_path / "one.db", real, image_names=names, camera_mode=pc.CameraMode.SINGLE,
                        reader_options=reader, extraction_options=extraction, device=pc.Device.cpu)
    extraction.num_threads = 4  # each shard runs on one thread whatever the options say
    extract_in_shards(tmp_path / "shards.db", real, names, reader=reader, extraction=extraction, threads=threads)
    assert extraction.num_threads == 4  # the caller's options are not changed
    assert sorted(f.name for f in tmp_path.iterdir()) == ["one.db", "shards.db"]  # no shard left
    one, shards = pc.Database.open(tmp_path / "one.db"), pc.Database.open(tmp_path / "shards.db")
    for table in ("read_all_cameras", "read_all_rigs", "read_all_frames", "read_all_images"):
        assert [str(v) for v in getattr(one, table)()] == [str(v) for v in getattr(shards, table)()]
    assert [im.name for im in shards.read_all_images()] == names
    for i in range(1, len(names) + 1):
        assert shards.num_keypoints_for_image(i) > 50
        assert np.array_equal(one.read_keypoints(i), shards.read_keypoints(i))
        assert np.array_equal(one.read_descriptors(i).data, shards.read_descriptors(i).data)


@pytest.mark.bad_input
@pytest.mark.parametrize("threads", [0, -1, 1.5, "2"])
def test_extract_in_shards_needs_a_positive_int_of_threads(tmp_path, threads):
    from lensdist_torch.calibration.features import extract_in_shards

    with pytest.raises(ValueError, match=r"^threads must be a positive int, got "):
        extract_in_shards(tmp_path / "db.db", tmp_path, ["a.png"], reader=None, extraction=None, threads=threads)


def test_the_verified_matches_repeat_exactly_with_the_default_threads(tmp_path):
    # COLMAP's threads each drew from a seeded RANSAC whichever pairs they were handed, and its extraction's
    # threads wrote the frames in the order they finished: the 12 GoPro views' verified matches differed in
    # each of three runs. Verified in fixed shards, they repeat
    pytest.importorskip("pycolmap")
    import torch

    from lensdist_torch.calibration.features import extract_and_match
    from lensdist_torch.calibration.matches import read_verified_matches

    real = Path(__file__).parents[1] / "data" / "real" / "gopro_hero4_wall"
    names = sorted(p.name for p in real.glob("*.jpg"))
    runs = []
    for i in range(3):
        extract_and_match(tmp_path / f"db{i}.db", real, names, config=MultiViewConfig(), image_size=(240, 320))
        runs.append(read_verified_matches(tmp_path / f"db{i}.db", names))
        assert sorted(f.name for f in tmp_path.iterdir()) == [f"db{j}.db" for j in range(i + 1)]  # no shard left
    assert len(runs[0].pair) > 500 and MultiViewConfig().num_threads == 2
    for other in runs[1:]:
        assert all(torch.equal(getattr(runs[0], f), getattr(other, f)) for f in ("x1", "x2", "pair", "first", "second"))
