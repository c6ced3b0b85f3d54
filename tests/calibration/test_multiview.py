"""The multi-view calibration: OpenCV's model inverted to convergence, COLMAP cameras as OpenCV's, BIC and intervals."""

import dataclasses
import math
import sys

import numpy as np
import pytest
import torch

from lensdist_torch.calibration.controllers.multiview_path import combine, held_answers
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.geometry.opencv_model import map_grid_step, opencv_delta, opencv_ideal_points

cv2 = pytest.importorskip("cv2")

# A wide-angle action camera (GoPro HERO4, 1280 x 960): OpenCV's calibration of the chessboard views
# of github.com/udacity/CarND-Camera-Calibration (MIT), computed with calibrateCamera's defaults.
GOPRO_K = np.array(
    [[560.2738673000947, 0.0, 651.2616487995417], [0.0, 561.3238292031594, 499.05810110554165], [0, 0, 1]]
)
GOPRO_DIST = np.array([-0.23287939835072627, 0.06167987983514998, -1.4677466480809523e-05, 3.785501319615777e-05,
                       -0.007540935298540569])


def _converged_cv2(points, k, dist):
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-14)
    return (
        cv2.undistortPointsIter(points[:, None], k, dist, None, k, crit)[:, 0]
        if hasattr(cv2, "undistortPointsIter")
        else cv2.undistortPoints(points[:, None], k, dist, None, k, criteria=crit)[:, 0]
    )


def test_ideal_points_agree_with_opencv_run_to_convergence():
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(200, 1080, 400), rng.uniform(150, 810, 400)]
    ideal, ok = opencv_ideal_points(torch.from_numpy(p), torch.from_numpy(GOPRO_K), torch.from_numpy(GOPRO_DIST))
    assert bool(ok.all())
    ref = _converged_cv2(p, GOPRO_K, GOPRO_DIST)
    assert np.abs(ideal.numpy() - ref).max() < 1e-5


def test_ideal_points_invert_the_forward_model_with_tangential_and_rational_terms():
    k = np.array([[400.0, 0, 320], [0, 410, 240], [0, 0, 1]])
    dist = np.array([-0.3, 0.08, 1e-3, -2e-3, -0.01, 0.02, 0.003, 0.001])
    rng = np.random.default_rng(1)
    x = rng.uniform(-0.7, 0.7, (300, 3))
    x[:, 2] = 1
    pd = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k, dist)[0][:, 0]
    ideal, ok = opencv_ideal_points(torch.from_numpy(pd), torch.from_numpy(k), torch.from_numpy(dist))
    truth = x[:, :2] * [400, 410] + [320, 240]
    assert bool(ok.all()) and np.abs(ideal.numpy() - truth).max() < 1e-6


def test_delta_of_the_wide_angle_camera_by_hand():
    # radial part alone: r F(r) = r - 0.2329 r^3 + ... turns at r* = 1.9066, F(r*) = 1.1559 (normalised), so only
    # the pixels with a distorted radius below 1.1559 invert: 90.6 % of the frame, Delta 103.2 px there
    out = opencv_delta(torch.from_numpy(GOPRO_K), torch.from_numpy(GOPRO_DIST), 960, 1280, step=2)
    assert out["invertible_fraction"] == pytest.approx(0.906, abs=0.002)
    assert out["delta_avg_px"] == pytest.approx(103.2, abs=0.3)
    none = opencv_delta(torch.from_numpy(GOPRO_K), torch.zeros(5, dtype=torch.float64), 96, 128)
    assert none["delta_avg_px"] < 1e-9 and none["invertible_fraction"] == 1.0


def test_ideal_points_refuse_a_wrong_number_of_coefficients():
    with pytest.raises(ValueError, match="dist_coeffs must hold 4, 5 or 8"):
        opencv_ideal_points(torch.zeros(1, 2), torch.eye(3), torch.zeros(3))


# ------------------------------------------------------------------ COLMAP
pycolmap = pytest.importorskip("pycolmap")
from lensdist_torch.calibration.multiview import (  # noqa: E402
    opencv_from_colmap,
    rotation_spread_deg,
    self_calibrate_reconstruction,
)
from lensdist_torch.calibration.multiview_fits import camera_of, with_model  # noqa: E402


@pytest.mark.parametrize("model, params", [
    ("SIMPLE_PINHOLE", [500.0, 320.0, 240.0]),
    ("SIMPLE_RADIAL", [500.0, 320.0, 240.0, -0.1]),
    ("RADIAL", [500.0, 320.0, 240.0, -0.2, 0.04]),
    ("OPENCV", [500.0, 505.0, 321.0, 239.0, -0.2, 0.04, 1e-3, -2e-3]),
    ("FULL_OPENCV", [500.0, 505.0, 321.0, 239.0, -0.2, 0.04, 1e-3, -2e-3, -0.01, 0.02, 0.003, 0.001]),
])
def test_colmap_camera_is_opencvs_exactly(model, params):
    cam = pycolmap.Camera.create_from_model_name(1, model, 500.0, 640, 480)
    cam.params = params
    rng = np.random.default_rng(2)
    x = np.c_[rng.uniform(-0.5, 0.5, (200, 2)), np.ones(200)]
    colmap_px = cam.img_from_cam(x)
    k, d = opencv_from_colmap(cam)
    opencv_px = cv2.projectPoints(x, np.zeros(3), np.zeros(3), k.numpy(), d.numpy())[0][:, 0]
    assert np.abs(colmap_px - 0.5 - opencv_px).max() < 1e-6  # COLMAP's pixel centres lie at +0.5


def _synthetic(seed, frames=8, noise=0.5):
    pycolmap.set_random_seed(seed)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_frames_per_rig, o.num_points3D = 1, frames, 200
    o.camera_model_id, o.camera_params = pycolmap.CameraModelId.RADIAL, [600.0, 320.0, 240.0, -0.2, 0.05]
    o.camera_width, o.camera_height = 640, 480
    rec = pycolmap.synthesize_dataset(o)
    truth = opencv_delta(*opencv_from_colmap(next(iter(rec.cameras.values()))), 480, 640)
    n = pycolmap.SyntheticNoiseOptions()
    n.point2D_stddev = noise
    pycolmap.synthesize_noise(n, rec)
    return rec, truth


def test_a_camera_without_distortion_is_weighed_with_delta_zero_and_loses_to_a_real_lens():
    # COLMAP's synthetic RADIAL camera (k = -0.2, 0.05) seen with little noise: SIMPLE_PINHOLE predicts held-out
    # frames worse and keeps no weight; its row is Delta 0 with std 0 (no parameter moves it)
    rec, truth = _synthetic(1, frames=10, noise=0.3)
    cfg = MultiViewConfig(models=("SIMPLE_PINHOLE", "RADIAL"), jackknife_blocks=4)
    res = self_calibrate_reconstruction(rec, cfg)
    pin, radial = res.models["SIMPLE_PINHOLE"], res.models["RADIAL"]
    assert pin["delta_avg_px"] == pytest.approx(0.0, abs=1e-9) and pin["delta_avg_std_px"] == 0.0
    assert pin["elpd"] < radial["elpd"] and pin["weight"] < 0.01 and res.model == "RADIAL"
    assert opencv_from_colmap(camera_of(with_model(rec, "SIMPLE_PINHOLE")[0]))[1].tolist() == [0.0] * 5


def test_tracks_that_leave_the_corners_unseen_give_cannot_tell_and_an_interval_that_covers():
    # COLMAP's synthetic scene projects within 122 px of the centre: Delta over the 640 x 480 frame is an
    # extrapolation, the models fit the tracks equally well and disagree on it; the interval must say so
    rec, truth = _synthetic(0)
    res = self_calibrate_reconstruction(rec, MultiViewConfig(jackknife_blocks=4))
    assert res.class_label is None and "px at the paper's frame spans classes" in res.reason
    lo, hi = res.delta_avg_user_interval
    assert lo <= truth["delta_avg_px"] <= hi
    assert set(res.models) == set(MultiViewConfig().models) and len(res.jackknife) == 4
    weights = {m: v["weight"] for m, v in res.models.items()}
    assert res.model == max(weights, key=weights.get) and sum(weights.values()) == pytest.approx(1.0)
    assert res.reprojection_px == pytest.approx(0.5 * math.sqrt(2), rel=0.15)  # the noise, both coordinates
    assert rec.num_reg_images() == 8  # the input is left as it was
    assert res.rotation_spread_deg == rotation_spread_deg(rec) > 0  # a diagnostic: no rule on it
    assert all(v["rotation_deg"] > 0 for v in res.models.values())
    # every model keeps its OpenCV camera: its Delta from it is the table's, and the chosen one's is the answer's
    for v in res.models.values():
        f64 = {"dtype": torch.float64}
        own = opencv_delta(torch.tensor(v["camera_matrix"], **f64), torch.tensor(v["dist_coeffs"], **f64), 480, 640,
                           step=map_grid_step(480, 640))
        assert own["delta_avg_px"] == pytest.approx(v["delta_avg_px"], rel=1e-9)
    assert res.models[res.model]["camera_matrix"] == res.camera_matrix


def _spread_synthetic(seed, frames=8, noise=0.5):
    """A RADIAL camera (f 1500 px, k1 -2, k2 4: Delta_avg 14.97 px) whose tracks (length >= 3) reach the frame's
    edges, the scene fixed and the noise drawn from ``seed``."""
    pycolmap.set_random_seed(0)
    o = pycolmap.SyntheticDatasetOptions()
    o.num_rigs, o.num_frames_per_rig, o.num_points3D = 1, frames, 600
    o.camera_model_id, o.camera_params = pycolmap.CameraModelId.RADIAL, [1500.0, 320.0, 240.0, -2.0, 4.0]
    o.camera_width, o.camera_height = 640, 480
    rec = pycolmap.synthesize_dataset(o)
    for point_id in list(rec.point3D_ids()):
        if rec.point3D(point_id).track.length() < 3:
            rec.delete_point3D(point_id)
    truth = opencv_delta(*opencv_from_colmap(next(iter(rec.cameras.values()))), 480, 640, step=map_grid_step(480, 640))
    pycolmap.set_random_seed(seed)
    n = pycolmap.SyntheticNoiseOptions()
    n.point2D_stddev = noise
    pycolmap.synthesize_noise(n, rec)
    return rec, truth["delta_avg_px"]


def test_a_held_camera_keeps_the_paths_lens_map_at_any_focal_length():
    from lensdist_torch.calibration.multiview_fits import held_camera
    from lensdist_torch.geometry.opencv_model import opencv_ideal_points

    k = torch.tensor([[400.0, 0, 319.5], [0, 404.0, 239.5], [0, 0, 1]], dtype=torch.float64)
    d = torch.tensor([-0.3, 0.1, 1e-3, -2e-3, -0.02, 0.05, 0.01, 0.002], dtype=torch.float64)
    p = torch.rand(400, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * torch.tensor(
        [639.0, 479.0]
    )
    want, ok = opencv_ideal_points(p, k, d)
    for focal in (250.0, 600.0, 1500.0):  # COLMAP's focal differs from the path's convention: the map stays
        cam = held_camera(k.tolist(), d.tolist(), focal=focal, camera_id=1, width=640, height=480)
        got, ok2 = opencv_ideal_points(p, *opencv_from_colmap(cam))
        assert cam.model_name == "FULL_OPENCV" and cam.params[0] == focal and bool((ok == ok2).all())
        assert float((got - want)[ok].abs().max()) < 1e-9
    half = held_camera(
        k.tolist(), d.tolist(), focal=300.0, camera_id=1, width=320, height=240, scale=2.0
    )  # a reconstruction at half the size
    assert float((opencv_ideal_points(p, *opencv_from_colmap(half, 2.0))[0] - want)[ok].abs().max()) < 1e-9


def test_other_paths_cameras_are_weighed_on_the_same_held_out_frames():
    # the synthetic RADIAL scene with two other paths' answers: its own lens and one with k1 doubled. Held on the
    # tracks, the true lens predicts the held-out frames as well as the free models; the wrong one takes no weight
    rec, _ = _spread_synthetic(1)
    cam = next(iter(rec.cameras.values()))
    k, d = opencv_from_colmap(cam)
    wrong = d.clone()
    wrong[0] *= 2
    def other(dist):
        delta = opencv_delta(k, dist, 480, 640, step=map_grid_step(480, 640))
        return {"camera_matrix": k.tolist(), "dist_coeffs": dist.tolist(), "delta_avg_user_px": delta["delta_avg_px"],
                "delta_avg_user_interval": (delta["delta_avg_px"] - 0.5, delta["delta_avg_px"] + 0.5),
                "delta_max_user_px": delta["delta_max_px"],
                "delta_max_user_interval": (delta["delta_max_px"] - 1, delta["delta_max_px"] + 1)}
    res = self_calibrate_reconstruction(rec, MultiViewConfig(models=("RADIAL",), jackknife_blocks=4),
                                        others={"own lens": other(d), "k1 doubled": other(wrong)})
    rows = res.models
    assert (
        rows["k1 doubled"]["weight"] < 0.01
        and rows["k1 doubled"]["heldout_rms_px"] > 3 * rows["RADIAL"]["heldout_rms_px"]
    )
    assert rows["own lens"]["heldout_rms_px"] == pytest.approx(rows["RADIAL"]["heldout_rms_px"], rel=0.1)
    assert rows["own lens"]["path"] == "own lens" and sum(v["weight"] for v in rows.values()) == pytest.approx(1.0)
    if res.model == "own lens":  # the winner answers with its own numbers and camera
        assert res.delta_avg_user_px == rows["own lens"]["delta_avg_px"] and res.dist_coeffs == d.tolist()


def test_the_posterior_std_of_delta_is_the_spread_of_the_estimates_over_noise_draws():
    # an independent check of the bundle adjustment's covariance carried to Delta_avg: the same scene, eight
    # draws of 0.5 px noise; the std over the draws against the mean posterior std, and the 95 % intervals
    # and likewise fx's posterior std (the focal length printed with its interval), the truth 1500 px
    est, std, covered, focal, focal_std, focal_covered = [], [], 0, [], [], 0
    for seed in range(1, 9):
        rec, truth = _spread_synthetic(seed)
        res = self_calibrate_reconstruction(rec, MultiViewConfig(models=("RADIAL",), jackknife_blocks=4))
        est.append(res.delta_avg_user_px)
        std.append(res.models["RADIAL"]["delta_avg_std_px"])
        covered += res.delta_avg_user_interval[0] <= truth <= res.delta_avg_user_interval[1]
        focal.append(res.camera_matrix[0][0])
        focal_std.append(res.models["RADIAL"]["focal_std_px"])
        focal_covered += abs(focal[-1] - 1500.0) <= 1.96 * focal_std[-1]
    assert truth == pytest.approx(14.97, abs=0.01)
    ratio = float(np.mean(std)) / float(np.std(est, ddof=1))  # a sample std of 8 is within 0.6-1.5 of sigma at 90 %
    assert 0.6 < ratio < 1.8 and covered >= 7
    assert 0.6 < float(np.mean(focal_std)) / float(np.std(focal, ddof=1)) < 1.8 and focal_covered >= 7
    assert (
        res.class_label == "3" and res.reason == "" and res.dispersion < 2.0
    )  # independent noise: the posterior holds


def test_thinned_keeps_a_seeded_share_of_whole_tracks_within_the_cap():
    from lensdist_torch.calibration.multiview_fits import thinned

    rec, _ = _spread_synthetic(1)
    lengths = {i: rec.point3D(i).track.length() for i in rec.point3D_ids()}
    total = sum(lengths.values())
    same, n = thinned(rec, total, seed=0)
    assert same is rec and n == total  # within the cap: the reconstruction itself
    half, n = thinned(rec, total // 2, seed=0)
    kept = {i: half.point3D(i).track.length() for i in half.point3D_ids()}
    assert n == sum(kept.values()) and total // 2 - max(lengths.values()) < n <= total // 2
    assert all(lengths[i] == k for i, k in kept.items())  # whole tracks, every observation of a kept point
    assert rec.num_points3D() == len(lengths) and half.num_reg_images() == rec.num_reg_images()  # rec unchanged
    assert set(thinned(rec, total // 2, seed=0)[0].point3D_ids()) == set(kept)  # seeded
    assert set(thinned(rec, total // 2, seed=1)[0].point3D_ids()) != set(kept)


def test_the_posterior_widens_as_the_square_root_of_the_share_of_tracks_kept(monkeypatch):
    # MAX_OBSERVATIONS at a quarter of the tracks: RADIAL's posterior std of Delta_avg about twice the full one's
    from lensdist_torch.calibration import multiview

    rec, _ = _spread_synthetic(2)
    cfg = MultiViewConfig(models=("RADIAL",), jackknife_blocks=4)
    full = self_calibrate_reconstruction(rec, cfg)
    total = sum(rec.point3D(i).track.length() for i in rec.point3D_ids())
    monkeypatch.setattr(multiview, "MAX_OBSERVATIONS", total // 4)
    quarter = self_calibrate_reconstruction(rec, cfg)
    assert full.observations == total and total // 4 - 8 < quarter.observations <= total // 4
    assert quarter.points3D == full.points3D == rec.num_points3D()  # the reconstruction's, not the share's
    ratio = quarter.models["RADIAL"]["delta_avg_std_px"] / full.models["RADIAL"]["delta_avg_std_px"]
    assert 1.6 < ratio < 2.5


@pytest.mark.bad_input
@pytest.mark.parametrize("most", [0, -1, 1.5, True, "100"])
def test_thinned_needs_a_positive_int(most):
    from lensdist_torch.calibration.multiview_fits import thinned

    with pytest.raises(ValueError, match=r"^most must be a positive int, got "):
        thinned(None, most, seed=0)


def test_too_few_frames_is_a_one_line_error():
    rec, _ = _synthetic(0, frames=2)
    with pytest.raises(ValueError, match="at least 3 registered frames"):
        self_calibrate_reconstruction(rec)


def test_frames_without_points_are_a_one_line_error():
    """A mapping of 10 tiny frames (120 x 160) registered 8 and kept no 3-D point: BIC divided by
    zero (the calibrate_path doctest, 3 of 4 runs). Refused by name; the workflow records a failed run."""
    rec, _ = _synthetic(0)
    for point_id in list(rec.point3D_ids()):
        rec.delete_point3D(point_id)
    assert rec.num_reg_images() == 8 and rec.num_points3D() == 0
    with pytest.raises(ValueError, match=r"^rec must hold 3-D points, got none \(8 frames registered\)$"):
        self_calibrate_reconstruction(rec)


# ------------------------------------------------------------------ combining the two paths
def _direct(cls, d, lo, hi):
    return {
        "class": cls,
        "reason": None if cls else "interval too wide",
        "delta_avg_user_px": d,
        "delta_avg_user_interval": [lo, hi],
        "delta_max_user_px": 2 * d,
        "delta_max_user_interval": [2 * lo, 2 * hi],
        "k2_user": 1e-7,
        "k4_user": 0.0,
        "opencv": {"camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
    }


def _mv(cls, d, lo, hi):
    return {
        "ok": True,
        "class_label": cls,
        "reason": "" if cls else "interval too wide: +-9 px",
        "model": "RADIAL",
        "delta_avg_user_px": d,
        "delta_avg_user_interval": (lo, hi),
        "delta_max_user_px": 3 * d,
        "delta_max_user_interval": (3 * lo, 3 * hi),
        "invertible_fraction": 1.0,
        "eq4_fit_error_px": 0.1,
        "registered": 20,
        "points3D": 900,
        "observations": 18000,
        "reprojection_px": 0.4,
        "rotation_spread_deg": 30.0,
        "models": {},
        "k2_user": 2e-7,
        "k4_user": 1e-13,
        "camera_matrix": [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]],
        "dist_coeffs": [-0.1, 0.01, 0, 0, 0],
    }


def test_the_comparison_answers_where_colmap_reconstructed_the_sequence():
    # the direct path disagrees and is narrower: the multi-view answer stands, the direct path's numbers beside it
    out = combine(_direct("R", 0.1, 0.0, 0.8), _mv("2", 7.0, 6.5, 7.5))
    assert out["method"] == "multiview" and out["class"] == "2" and out["delta_avg_user_px"] == 7.0
    assert out["delta_avg_user_interval"] == (6.5, 7.5) and out["camera_model"] == "RADIAL"
    assert out["opencv"]["dist_coeffs"] == [-0.1, 0.01, 0, 0, 0] and out["opencv_rational"] is None
    assert out["direct"]["delta_avg_user_px"] == 0.1 and out["multiview"]["delta_avg_user_px"] == 7.0
    mv = _mv("2", 7.0, 6.5, 7.5)  # the JSON's multiview block carries the record's diagnostics, as the text reads them
    for key in ("registered", "points3D", "observations", "reprojection_px", "rotation_spread_deg", "models"):
        assert out["multiview"][key] == mv[key]
    # no class from the comparison: none from another path either, and its reason stands
    wide = combine(_direct("3", 9.0, 8.8, 9.2), _mv(None, 12.0, 0.0, 30.0))
    assert wide["method"] == "multiview" and wide["class"] is None and wide["reason"] == "interval too wide: +-9 px"


def test_a_held_path_that_wins_answers_with_its_own_lens_and_the_comparisons_interval():
    # the direct path's camera predicted the held-out frames best: its numbers and eq. 4, the mixture's interval
    mv = {**_mv("3", 6.9, 6.1, 7.6), "model": "direct"}
    out = combine(_direct(None, 6.9, 6.0, 7.8), mv)
    assert out["method"] == "direct" and out["class"] == "3" and out["reason"] is None
    assert out["delta_avg_user_interval"] == (6.1, 7.6)
    assert out["delta_max_user_interval"] == pytest.approx((18.3, 22.8))
    assert out["k2_user"] == 1e-7 and out.get("camera_model") is None  # the direct path's eq. 4, not the refit
    # the homography model's: its lens (centre, terms) and exports, the comparison's class
    planar = _planar(None, 6.95, 5.0, 9.0)
    out = combine(_direct(None, 6.9, 6.0, 7.8), {**_mv("3", 6.95, 6.2, 7.7), "model": "planar", "planar": planar})
    assert out["method"] == "planar" and out["class"] == "3" and out["camera_model"] == "planar-3-centre"
    assert out["delta_avg_user_interval"] == (6.2, 7.7) and out["k2_user"] == 7e-7
    assert out["opencv"]["dist_coeffs"] == [-0.4, 0.1, 0, 0, 0] and out["planar"]["class"] is None


def test_held_answers_take_each_paths_camera_and_leave_out_what_has_none():
    direct = {**_direct("3", 9.0, 8.8, 9.2), "opencv_rational": {"camera_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                                                 "dist_coeffs": [0.1] * 8}}
    held = held_answers(direct, _planar("4", 9.1, 8.0, 10.0))
    assert list(held) == ["direct", "planar"] and held["direct"]["dist_coeffs"] == [0.1] * 8  # the rational one
    assert held["planar"]["dist_coeffs"] == [-0.4, 0.1, 0, 0, 0] and held["planar"]["delta_avg_user_px"] == 9.1
    assert held["direct"]["delta_max_user_interval"] == [17.6, 18.4] and held["direct"]["invertible_fraction"] == 1.0
    nan = float("nan")
    assert held_answers({**direct, "delta_avg_user_px": nan}, {"ok": False, "reason": "too few pairs"}) == {}
    assert list(held_answers({**direct, "opencv": None, "opencv_rational": None}, _planar("4", 9.1, 8, 10))) == [
        "planar"]


def test_without_a_reconstruction_the_more_precise_of_the_other_paths_answers():
    failed = combine(
        _direct("3", 9.0, 8.8, 9.2), {"ok": False, "reason": "the engine could not reconstruct the sequence"}
    )
    assert failed["method"] == "direct" and failed["class"] == "3" and "reconstruct" in failed["multiview"]["reason"]
    no_mapping = {"ok": False, "reason": "no mapping", "planar_max_relief_z": 2.0,
                  "planar": _planar("2", 7.0, 6.5, 7.5)}
    apart = combine({**_direct("R", 0.1, 0.0, 0.8), "relief_z": 0.1}, no_mapping)
    assert apart["class"] is None and apart["method"] == "direct" and apart["delta_avg_user_px"] == 0.1
    assert apart["reason"] == ("the paths disagree beyond their intervals (direct 0.10 px [0.00, 0.80]; homography "
                               "model 7.00 px [6.50, 7.50]); the numbers are the direct path's, the most precise")


def _planar(cls, d, lo, hi):
    return {
        "ok": True,
        "class_label": cls,
        "reason": "" if cls else "interval too wide: +-9 px",
        "terms": 3,
        "delta_avg_user_px": d,
        "delta_avg_user_interval": (lo, hi),
        "delta_max_user_px": 4 * d,
        "delta_max_user_interval": (4 * lo, 4 * hi),
        "invertible_fraction": 1.0,
        "eq4_fit_error_px": 2.9,
        "k2_user": 7e-7,
        "k4_user": 1e-12,
        "pairs": 41,
        "inliers": 1133,
        "matches": 4925,
        "inlier_share": 0.61,
        "reprojection_px": 0.83,
        "models": {},
        "jackknife": [],
        "dispersion": 1.0,
        "coefficients": [0.59, 0.1, 0.33],
        "model": "planar-3-centre",
        "centre": [636.0, 509.0],
        "bending_halfwidth_px": 36.0,
        "matched_fraction": 0.81,
        "opencv_rational": None,
        "opencv": {
            "camera_matrix": [[800.0, 0, 639.5], [0, 800.0, 479.5], [0, 0, 1]],
            "dist_coeffs": [-0.4, 0.1, 0, 0, 0],
            "fit_error_mean_px": 9.7,
            "fit_error_max_px": 30.0,
        },
    }


def test_without_a_reconstruction_the_homography_model_answers_where_it_is_more_precise_on_a_flat_scene():
    direct = {**_direct(None, 61.5, 0.0, 172.0), "relief_z": 0.1}
    mv = {"ok": False, "reason": "2 of 20 frames registered", "planar": _planar("4", 134.2, 105.6, 162.8),
          "planar_max_relief_z": 2.0}  # no reconstruction: the direct path and the homography model remain
    out = combine(direct, mv)
    assert out["method"] == "planar" and out["class"] == "4" and out["reason"] is None
    assert out["delta_avg_user_px"] == 134.2 and out["camera_model"] == "planar-3-centre"
    assert out["opencv"]["dist_coeffs"] == [-0.4, 0.1, 0, 0, 0] and out["planar"]["terms"] == 3
    # the JSON's planar block carries its lens (centre included), how straight it makes lines and its own exports
    assert out["planar"]["centre"] == [636.0, 509.0] and out["planar"]["bending_halfwidth_px"] == 36.0
    assert (
        out["planar"]["opencv"]["dist_coeffs"] == [-0.4, 0.1, 0, 0, 0] and out["planar"]["model"] == "planar-3-centre"
    )
    # what guided matching did, carried into the JSON (None where it did not run)
    assert out["planar"]["guided"] is None
    guided = {
        "used": True,
        "reason": "",
        "pairs_verified": 197,
        "pairs_matched": 143,
        "matches": 6596,
        "radius_px": 3.0,
        "first_fit": {"pairs": 38},
    }
    assert combine(direct, {**mv, "planar": {**mv["planar"], "guided": guided}})["planar"]["guided"] == guided
    assert out["planar"]["refined"] is None  # and what the sub-pixel refinement did
    refined = {
        "used": True,
        "reason": "",
        "kept": 2845,
        "matches": 6594,
        "median_shift_px": 0.92,
        "before": {"pairs": 131},
    }
    assert combine(direct, {**mv, "planar": {**mv["planar"], "refined": refined}})["planar"]["refined"] == refined
    # relief found by the direct path's plane + parallax test: one homography per pair would absorb it
    relief = combine({**direct, "relief_z": 5.6}, mv)
    assert relief["method"] != "planar" and relief["class"] is None
    assert (
        relief["planar"]["reason"]
        == "relief: the direct path's plane + parallax test finds relief (z = 5.6, at most 2)"
    )
    # no relief but no finite interval either: the homography model does not count, and says nothing of relief
    nan = float("nan")
    flat = combine({**direct, "relief_z": 0.1},
                   {**mv, "planar": {**mv["planar"], "delta_avg_user_interval": [nan, nan], "reason": ""}})
    assert flat["method"] != "planar" and not (flat["planar"]["reason"] or "").startswith("relief")
    # an interval that misses another path's: no answer from it
    apart = combine({**_direct(None, 20.0, 10.0, 30.0), "relief_z": 0.1}, mv)
    assert apart["method"] != "planar" and apart["class"] is None
    # a path with a class keeps its answer
    kept = combine({**_direct("3", 9.0, 8.8, 9.2), "relief_z": 0.1}, {**mv, "planar": _planar("4", 9.1, 8.0, 10.0)})
    assert kept["method"] == "direct" and kept["class"] == "3" and kept["planar"]["class"] == "4"
    # no answer of its own: its reason is kept
    none = combine(direct, {**mv, "planar": {"ok": False, "reason": "too few matched pairs: 2 of at least 4"}})
    assert none["planar"] == {"reason": "too few matched pairs: 2 of at least 4"} and none["method"] != "planar"


def test_missing_pycolmap_is_named(monkeypatch, tmp_path):
    from lensdist_torch.calibration.controllers.multiview_path import multiview_path

    monkeypatch.setitem(sys.modules, "pycolmap", None)
    res = multiview_path(tmp_path, (10, 10))
    assert res == {"ok": False, "reason": res["reason"]} and "pip install pycolmap" in res["reason"]


def _fake_colmap(monkeypatch, tmp_path, homography):
    """multiview_path over 4 frames, COLMAP's stages replaced: the matches, then a 0.6-s mapping that fails."""
    import time

    from lensdist_torch.calibration.controllers import multiview_path as mp

    for i in range(4):
        (tmp_path / f"f{i}.png").write_bytes(b"")
    (tmp_path / "db.db").write_bytes(b"matches")

    def reconstruct(folder, names, *, config, stop, image_size, on_matches, on_stage):
        on_matches(tmp_path / "db.db")
        on_stage("mapping", 1)
        time.sleep(0.6)  # the mapping, on one thread
        stop(0, None)
        return [None]

    monkeypatch.setattr(mp, "reconstruct", reconstruct)
    monkeypatch.setattr(mp, "planar_path", homography)
    t0 = time.perf_counter()
    try:
        return mp.multiview_path(tmp_path, (30, 40)), time.perf_counter() - t0
    finally:
        assert not (tmp_path / "homography.db").exists()


def test_the_homography_model_runs_beside_the_mapping_on_its_own_copy_of_the_matches(monkeypatch, tmp_path):
    import time

    seen = []

    def homography(database, names, image_size, **kwargs):
        seen.append((database.read_bytes(), database != tmp_path / "db.db", names))
        time.sleep(0.6)
        return {"ok": False, "reason": "too few pairs of matches"}

    res, seconds = _fake_colmap(monkeypatch, tmp_path, homography)
    assert seen == [(b"matches", True, [f"f{i}.png" for i in range(4)])]
    assert res["ok"] is False and res["planar"] == {"ok": False, "reason": "too few pairs of matches"}
    assert "0 of 4 frames registered" in res["reason"]
    assert seconds < 1.1  # side by side: one after the other takes 1.2 s


def test_an_error_of_the_homography_model_reaches_the_caller(monkeypatch, tmp_path):
    def homography(database, names, image_size, **kwargs):
        raise ValueError("frames must be readable")

    with pytest.raises(ValueError, match="^frames must be readable$"):
        _fake_colmap(monkeypatch, tmp_path, homography)


def test_feature_cap_follows_the_area_sift_reads_by_hand(planar_constant):
    from lensdist_torch.calibration.multiview import feature_cap

    planar_constant("FEATURES_PER_MEGAPIXEL", 1000.0)
    cfg = MultiViewConfig(max_image_side=1000, max_features=800)
    assert feature_cap(cfg) == 800  # no size: the fixed cap
    assert feature_cap(cfg, (300, 400)) == 120  # 0.12 megapixel
    assert feature_cap(cfg, (1000, 2000)) == 500  # read at 500 x 1000: 0.5 megapixel
    assert feature_cap(cfg, (3000, 3000)) == 800  # 1 megapixel read, capped by max_features
    assert feature_cap(cfg, (10, 10)) == 64  # never below 64


def test_calibrate_path_names_what_the_multiview_path_lacks(tmp_path):
    from lensdist_torch.calibration.controllers.calibrate import calibrate_path, synthetic_sequence
    from lensdist_torch.core.png import encode_png, to_uint8

    frames, _ = synthetic_sequence(2, 1e-6, 0.0, size=(96, 128))
    for i, f in enumerate(frames):
        (tmp_path / f"f{i}.png").write_bytes(encode_png(to_uint8(f)))
    with pytest.raises(ValueError, match="needs at least 3 frames, got 2"):
        calibrate_path(tmp_path, method="multiview")
    with pytest.raises(ValueError, match="method must be one of auto, multiview, direct"):
        calibrate_path(tmp_path, method="colmap")
    auto = calibrate_path(tmp_path)  # the direct answer stands, the multi-view reason beside it
    assert auto["method"] == "direct" and "at least 3 frames" in auto["multiview"]["reason"]


def test_the_adjustment_is_pycolmaps_bit_for_bit_and_says_it_converged():
    # two frames' poses fix the gauge, as pycolmap.bundle_adjustment does: the same camera to the last bit
    from lensdist_torch.calibration.multiview_fits import BA_FUNCTION_TOLERANCE, adjust, copy_reconstruction, rss

    rec, _ = _synthetic(3, frames=6, noise=0.5)
    ours, theirs = copy_reconstruction(rec), copy_reconstruction(rec)
    adjusted = adjust(ours)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point, options.print_summary = False, False
    options.ceres.solver_options.function_tolerance = BA_FUNCTION_TOLERANCE
    pycolmap.bundle_adjustment(theirs, options)
    assert adjusted.converged and 1 <= adjusted.iterations < 100
    assert camera_of(ours).params.tolist() == camera_of(theirs).params.tolist()
    ss, n = rss(ours)  # the residuals summed over the tracks in Python: Ceres' final cost is half of it
    assert adjusted.rss == pytest.approx(ss, rel=1e-9) and adjusted.observations == n
    held = copy_reconstruction(rec)
    assert adjust(held, held=True).converged and camera_of(held).params.tolist() == camera_of(rec).params.tolist()


def test_a_model_whose_adjustment_does_not_converge_has_no_posterior_and_no_weight(monkeypatch):
    # one iteration cannot reach SIMPLE_RADIAL's minimum from RADIAL's (k2 dropped): it stops at no minimum and
    # has no covariance; RADIAL, adjusted from its own minimum, converges at once and answers alone
    from lensdist_torch.calibration import multiview_fits

    rec, _ = _synthetic(1, frames=10, noise=0.3)
    assert multiview_fits.adjust(rec).converged  # RADIAL at its minimum, as a mapping leaves it
    monkeypatch.setattr(multiview_fits, "BA_MAX_ITERATIONS", 1)
    res = self_calibrate_reconstruction(rec, MultiViewConfig(models=("SIMPLE_RADIAL", "RADIAL"), jackknife_blocks=4))
    sr, radial = res.models["SIMPLE_RADIAL"], res.models["RADIAL"]
    assert not sr["converged"] and sr["iterations"] == 1 and sr["delta_avg_std_px"] == math.inf
    assert sr["weight"] == 0.0 and radial["converged"] and radial["weight"] == 1.0 and res.model == "RADIAL"


def test_the_candidates_fitted_in_worker_processes_are_those_fitted_here(monkeypatch):
    """From PROCESSES_FROM observations (here 0) the candidates are fitted in ``num_threads`` worker processes:
    the same weights, Delta_avg and intervals as one after the other here."""
    from lensdist_torch.calibration import multiview_workers

    rec, _ = _spread_synthetic(1)
    cfg = MultiViewConfig(models=("RADIAL", "OPENCV"), jackknife_blocks=4, num_threads=1)
    here = self_calibrate_reconstruction(rec, cfg)
    started = []
    real = multiview_workers._Worker.__init__

    def counted(self, folder):
        real(self, folder)
        started.append(self)

    monkeypatch.setattr(multiview_workers, "PROCESSES_FROM", 0)
    monkeypatch.setattr(multiview_workers._Worker, "__init__", counted)
    apart = self_calibrate_reconstruction(rec, dataclasses.replace(cfg, num_threads=2))
    assert len(started) == 2 and all(w.proc.poll() == 0 for w in started)  # two workers, ended with the block
    assert apart.model == here.model and apart.delta_avg_user_px == pytest.approx(here.delta_avg_user_px, rel=1e-9)
    assert apart.delta_avg_user_interval == pytest.approx(here.delta_avg_user_interval, rel=1e-6)
    for m in cfg.models:
        assert apart.models[m]["weight"] == pytest.approx(here.models[m]["weight"], rel=1e-6, abs=1e-12)
        assert apart.models[m]["heldout_rms_px"] == pytest.approx(here.models[m]["heldout_rms_px"], rel=1e-9)


def test_an_error_in_a_worker_reaches_the_caller(monkeypatch):
    from lensdist_torch.calibration import multiview_workers

    rec, _ = _spread_synthetic(1)
    monkeypatch.setattr(multiview_workers, "PROCESSES_FROM", 0)
    with multiview_workers.candidate_fits(rec, 1, processes=2) as submit:
        with pytest.raises(ValueError, match="kind must be 'model' or 'held', got 'other'"):
            submit("other").result()


def test_the_idle_core_follows_colmaps_stages_and_the_homography_model(monkeypatch, tmp_path):
    """``idle`` is set while COLMAP leaves one of its two threads' cores free: its matching, and its mapping once the
    homography model beside it is done; cleared while its shards, or the mapping and the homography model, take both."""
    import threading
    import time

    from lensdist_torch.calibration.controllers import multiview_path as mp

    for i in range(4):
        (tmp_path / f"f{i}.png").write_bytes(b"")
    (tmp_path / "db.db").write_bytes(b"matches")
    idle, seen = threading.Event(), []

    def homography(database, names, image_size, **kwargs):
        time.sleep(0.4)
        return {"ok": False, "reason": "no pairs"}

    def reconstruct(folder, names, *, config, stop, image_size, on_matches, on_stage):
        for name, threads in (("extraction", 2), ("matching", 1), ("verification", 2)):
            on_stage(name, threads)
            seen.append((name, idle.is_set()))
        on_matches(tmp_path / "db.db")
        on_stage("mapping", 1)
        seen.append(("mapping beside the homography model", idle.is_set()))
        time.sleep(0.8)
        seen.append(("mapping alone", idle.is_set()))
        stop(0, None)
        return [None]

    monkeypatch.setattr(mp, "reconstruct", reconstruct)
    monkeypatch.setattr(mp, "planar_path", homography)
    mp.multiview_path(tmp_path, (30, 40), config=MultiViewConfig(num_threads=2), idle=idle)
    assert seen == [("extraction", False), ("matching", True), ("verification", False),
                    ("mapping beside the homography model", False), ("mapping alone", True)]
