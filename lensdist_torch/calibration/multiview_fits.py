"""A camera fitted on a COLMAP reconstruction's tracks, free or held, with its folds and its posterior.

The fits that :func:`~lensdist_torch.calibration.multiview.self_calibrate_reconstruction` weighs:

* :func:`fit_model`: one COLMAP camera model adjusted with the structure and the poses (focal
  length and distortion free, the principal point held at the frame centre), its posterior of
  Delta from the adjustment's covariance, and per fold (a contiguous block of frames held out)
  the model adjusted without the block, its Delta (the jackknife) and the held-out frames'
  squared errors (its evidence, :mod:`~lensdist_torch.calibration.multiview_evidence`);
* :func:`fit_held_camera`: another path's camera (the direct path's or the homography model's
  OpenCV camera) held fixed while the structure and the poses adjust, scored on the same folds,
  so that every path's lens is weighed on the same held-out frames. Its lens map is kept exactly
  in pixels: COLMAP's FULL_OPENCV at the reconstruction's focal length f with the coefficients
  rescaled by a = f_c / f (k1, k4 / a^2; k2, k5 / a^4; k3, k6 / a^6; p1, p2 / a), which sends every
  pixel to the same ideal pixel as the path's own camera.

COLMAP's log goes to the null device while it runs (:func:`quiet_log`).
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import sys
from dataclasses import dataclass

import numpy as np
import torch

from lensdist_torch.calibration.multiview_evidence import (
    camera_covariance,
    fold_ranges,
    heldout_rms,
    heldout_squared_errors,
    posterior_std,
)
from lensdist_torch.calibration.pooling import jackknife_std
from lensdist_torch.geometry.opencv_model import opencv_delta, opencv_from_colmap

__all__ = [
    "pycolmap_or_error",
    "quiet_log",
    "camera_of",
    "rss",
    "Adjustment",
    "adjust",
    "with_model",
    "deltas",
    "rotation_spread_deg",
    "fold_blocks",
    "fit_model",
    "held_camera",
    "fit_held_camera",
    "copy_reconstruction",
    "thinned",
    "BA_FUNCTION_TOLERANCE",
    "BA_MAX_ITERATIONS",
    "MAX_OBSERVATIONS",
]

#: Relative cost decrease below which a bundle adjustment stops (Ceres' default; COLMAP's 0 crawled
#: along the valley of a poorly conditioned camera).
BA_FUNCTION_TOLERANCE = 1e-6
#: Iterations of a bundle adjustment at most (COLMAP's default). A camera the tracks determine converges well within
#: it from the mapping's structure; one they do not (its focal length traded along a valley of the cost) reaches no
#: minimum at any cap, and :func:`fit_model` gives it no posterior (docs/method.md, section 11).
BA_MAX_ITERATIONS = 100
#: Observations the models are weighed on at most (:func:`thinned`): a bundle adjustment's cost grows with them, and
#: every candidate is adjusted on all the frames and again on each fold. Beyond it a seeded share of the 3-D points is
#: kept, all of their observations: the posteriors widen as the square root of the share (docs/method.md, 11).
MAX_OBSERVATIONS = 100_000


def pycolmap_or_error():
    """The ``pycolmap`` module, or a one-line ``ValueError`` saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise ValueError("the multi-view calibration needs pycolmap (COLMAP's Python bindings): pip install pycolmap, "
                         "or --method direct") from None
    return pycolmap


@contextlib.contextmanager
def quiet_log():
    """COLMAP's log (glog, written to file descriptor 2 from C++) sent to the null device meanwhile.

    Its progress and its solver's warnings (thousands of lines on ill-conditioned models) would
    bury the answer; what fails reaches the caller as a missing reconstruction or a reason.
    """
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def camera_of(rec):
    """The one shared camera of a reconstruction (a ``ValueError`` where it holds several)."""
    cams = list(rec.cameras.values())
    if len(cams) != 1:
        raise ValueError(f"reconstruction must hold one shared camera, got {len(cams)}")
    return cams[0]


def rss(rec) -> tuple[float, int]:
    """Sum of squared reprojection errors (px^2) and the number of observations."""
    cam, ss, n = camera_of(rec), 0.0, 0
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        obs = [(p.xy, rec.point3D(p.point3D_id).xyz) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy, xyz = np.array([o[0] for o in obs]), np.array([o[1] for o in obs])
        proj = cam.img_from_cam(image.cam_from_world() * xyz)
        ss, n = ss + float(np.nansum((proj - xy) ** 2)), n + len(obs)
    return ss, n


@dataclass(frozen=True, kw_only=True)
class Adjustment:
    """What one bundle adjustment (:func:`adjust`) did.

    Attributes:
        converged: whether Ceres converged within :data:`BA_MAX_ITERATIONS` (the cost's relative
            decrease below :data:`BA_FUNCTION_TOLERANCE`, or its gradient vanished).
        iterations: the iterations it took.
        rss: the sum of squared reprojection errors after it (px^2): twice Ceres' final cost, the
            loss being the squared error itself (as :func:`rss` sums them over the tracks).
        observations: the observations adjusted (each two residuals).
    """

    converged: bool
    iterations: int
    rss: float
    observations: int


def adjust(rec, held: bool = False) -> Adjustment:
    """A global bundle adjustment of ``rec`` in place: points, poses and (unless ``held``) focal and distortion.

    Every registered frame adjusts, the gauge fixed by two frames' poses (as ``pycolmap.bundle_adjustment``
    does, bit for bit).
    """
    pc = pycolmap_or_error()
    options = pc.BundleAdjustmentOptions()
    options.refine_principal_point, options.print_summary = False, False
    if held:
        options.refine_focal_length = options.refine_extra_params = False
    options.ceres.solver_options.function_tolerance = BA_FUNCTION_TOLERANCE
    options.ceres.solver_options.max_num_iterations = BA_MAX_ITERATIONS
    config = pc.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    with quiet_log():
        summary = pc.create_default_ceres_bundle_adjuster(options, config, rec).solve().ceres_summary
    steps = summary.num_successful_steps + summary.num_unsuccessful_steps  # Ceres counts its iteration 0 as a step
    return Adjustment(converged=summary.termination_type.name == "CONVERGENCE", iterations=steps - 1,
                      rss=2 * summary.final_cost, observations=summary.num_residuals // 2)


def with_model(rec, model: str):
    """A copy of ``rec`` whose camera is ``model`` (focal and the first radial terms carried over), adjusted.

    Returns the copy and its :class:`Adjustment`.
    """
    pc = pycolmap_or_error()
    out, cam = copy_reconstruction(rec), camera_of(rec)
    new = pc.Camera.create_from_model_name(cam.camera_id, model, cam.mean_focal_length(), cam.width, cam.height)
    params = new.params.copy()
    old_extra, new_extra = list(cam.extra_params_idxs()), list(new.extra_params_idxs())
    for i, j in zip(old_extra[:2], new_extra[:2]):  # k1 (and k2) mean the same in every model here
        params[j] = cam.params[i]
    new.params = params
    out.cameras[cam.camera_id] = new
    return out, adjust(out)


def deltas(camera, size: tuple[int, int], scale: float, step: int) -> dict:
    """:func:`~lensdist_torch.geometry.opencv_model.opencv_delta` of a COLMAP camera in pixels scaled by ``scale``."""
    k, d = opencv_from_colmap(camera, scale)
    return opencv_delta(k, d, *size, step=step)


def rotation_spread_deg(rec) -> float:
    """The largest rotation (degrees) between two registered frames' orientations.

    Under translation alone a relief of the scene imitates radial distortion however many
    frames there are (docs/method.md, section 11): the bundle adjustment then has a valley, not
    a minimum, and every jackknife replicate stops at the same point of it.
    """
    rots = np.stack([rec.image(i).cam_from_world().rotation.matrix() for i in rec.reg_image_ids()])
    rel = np.einsum("aij,bkj->abik", rots, rots)  # R_a R_b^T
    cos = np.clip((np.trace(rel, axis1=2, axis2=3) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def fold_blocks(rec, n_blocks: int) -> list[list[int]]:
    """Registered frame ids in contiguous blocks by image name (recording order)."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    return [[images[i].frame_id for i in r] for r in fold_ranges(len(images), n_blocks)]


def _folds(rec, n_blocks: int, held: bool = False):
    """Per fold (:func:`fold_blocks`): ``rec`` adjusted without the block, and the block's held-out squared errors."""
    for block in fold_blocks(rec, n_blocks):
        train = copy_reconstruction(rec)
        for frame_id in block:
            train.deregister_frame(frame_id)
        adjust(train, held=held)
        yield train, heldout_squared_errors(train, camera_of(train), rec, block)


def fit_model(rec, *, model: str, size: tuple[int, int], scale: float, step: int, n_blocks: int) -> dict:
    """One model on ``rec``'s tracks: its adjustment, posterior, delete-a-block fits and held-out errors.

    An adjustment that does not converge within :data:`BA_MAX_ITERATIONS` stops at no minimum: the
    normal equations' inverse there is no posterior, and the model's is unbounded (it takes no weight).
    """
    r, adjusted = with_model(rec, model)
    ss, n, converged = adjusted.rss, adjusted.observations, adjusted.converged
    cam = camera_of(r)
    km, dm = opencv_from_colmap(cam, scale)
    dl = opencv_delta(km, dm, *size, step=step)

    def measure(params):  # Delta_avg and Delta_max of the camera with other intrinsics, on a grid 16 times coarser
        c = copy.copy(cam)  # (their gradient and the folds' spread need no finer one)
        c.params = params
        d = deltas(c, size, scale, 4 * step)
        return d["delta_avg_px"], d["delta_max_px"]

    with quiet_log():
        cov = camera_covariance(r, cam.camera_id, ss, n) if converged else None
    fixed = set(cam.principal_point_idxs())
    variable = [i for i in range(len(cam.params)) if i not in fixed]
    std_avg, std_max = posterior_std(list(cam.params), variable, cov, measure)
    fi = cam.focal_length_idxs()[0]  # fx's std, in the OpenCV camera's pixels
    f = variable.index(fi)
    focal_std = math.inf if cov is None else math.sqrt(max(float(cov[f, f]), 0.0)) * float(km[0, 0]) / cam.params[fi]
    jk_avg, jk_max, errors = [], [], []
    for train, fold_errors in _folds(r, n_blocks):
        d = measure(np.asarray(camera_of(train).params, dtype=float))
        jk_avg.append(d[0])
        jk_max.append(d[1])
        errors.append(fold_errors)
    jk_std = jackknife_std(jk_avg)
    k = len(cam.params) - 2  # the principal point is held
    return {"camera": cam, "delta": dl, "errors": errors, "jackknife": jk_avg, "row": {
        "bic": 2 * n * math.log(max(ss, 1e-300) / (2 * n)) + k * math.log(2 * n), "delta_avg_px": dl["delta_avg_px"],
        "delta_avg_std_px": std_avg, "delta_max_px": dl["delta_max_px"], "delta_max_std_px": std_max,
        "jackknife_std_px": jk_std, "reprojection_px": math.sqrt(ss / max(n, 1)),
        "heldout_rms_px": heldout_rms([e for fold in errors for e in fold]),
        "rotation_deg": rotation_spread_deg(r), "camera_matrix": km.tolist(), "dist_coeffs": dm.tolist(),
        "focal_std_px": focal_std, "converged": converged, "iterations": adjusted.iterations}}


def copy_reconstruction(rec):
    """A deep copy of a ``pycolmap.Reconstruction``."""
    return pycolmap_or_error().Reconstruction(rec)


def thinned(rec, most: int, *, seed: int):
    """``rec``, or a copy keeping a seeded random share of its 3-D points, with at most ``most`` observations.

    The points are drawn in a seeded random order (``numpy``'s ``default_rng(seed)``) and kept while their
    observations (their tracks' lengths) add up to at most ``most``: a uniform share of the tracks over
    the frames and the frame's area. ``rec`` itself where it holds ``most`` observations or fewer.

    Returns:
        ``(reconstruction, observations)``: the reconstruction to weigh the models on and its observations.
    """
    if not (isinstance(most, int) and not isinstance(most, bool) and most >= 1):
        raise ValueError(f"most must be a positive int, got {most!r}")
    ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    lengths = np.array([rec.point3D(int(i)).track.length() for i in ids], dtype=np.int64)
    if lengths.sum() <= most:
        return rec, int(lengths.sum())
    order = np.random.default_rng(seed).permutation(len(ids))
    keep = np.zeros(len(ids), dtype=bool)
    keep[order[np.cumsum(lengths[order]) <= most]] = True
    out = copy_reconstruction(rec)
    for point_id in ids[~keep]:
        out.delete_point3D(int(point_id))
    return out, int(lengths[keep].sum())


def held_camera(
    camera_matrix, dist_coeffs, *, focal: float, camera_id: int, width: int, height: int, scale: float = 1.0
):
    """Another path's OpenCV camera (in pixels scaled by ``scale``) as COLMAP's FULL_OPENCV at focal length ``focal``.

    The lens map in pixels is kept (module docstring): every pixel goes to the same ideal pixel.
    ``dist_coeffs`` hold OpenCV's 5 or 8 coefficients; the inverse of
    :func:`~lensdist_torch.geometry.opencv_model.opencv_from_colmap` for the principal point.
    """
    pc = pycolmap_or_error()
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64)
    d = torch.cat([d, d.new_zeros(8 - d.numel())])
    a = float(k[0, 0]) / scale / focal
    powers = torch.tensor([2, 4, 1, 1, 6, 2, 4, 6], dtype=torch.float64)  # k1 k2 p1 p2 k3 k4 k5 k6
    centre = [(float(k[i, 2]) + 0.5) / scale for i in (0, 1)]  # opencv_from_colmap's inverse
    params = [focal, focal * float(k[1, 1] / k[0, 0]), *centre, *(d / a**powers).tolist()]
    camera = pc.Camera.create_from_model_name(camera_id, "FULL_OPENCV", focal, width, height)
    camera.params = params
    return camera


def fit_held_camera(rec, camera, n_blocks: int) -> dict:
    """``camera`` held on ``rec``'s tracks: the structure and poses adjusted, its held-out errors per fold.

    Returns ``{"errors": per fold the held-out frames' squared errors, "reprojection_px": RMS on the
    tracks, "heldout_rms_px", "converged", "iterations"}`` (as :func:`fit_model`'s, for the same folds).
    """
    r = copy_reconstruction(rec)
    r.cameras[camera.camera_id] = camera
    adjusted = adjust(r, held=True)
    ss, n = adjusted.rss, adjusted.observations
    errors = [fold_errors for _, fold_errors in _folds(r, n_blocks, held=True)]
    return {"errors": errors, "reprojection_px": math.sqrt(ss / max(n, 1)),
            "heldout_rms_px": heldout_rms([e for fold in errors for e in fold]),
            "converged": adjusted.converged, "iterations": adjusted.iterations}
