"""A camera's lens distortion from many views by bundle adjustment on COLMAP (pycolmap).

One pair of a scene with relief cannot tell relief from distortion (docs/method.md, section 10);
many views with varied motion can, once the relief belongs to the scene (free 3-D points) and
the distortion to the camera (one shared camera). That is bundle adjustment with
self-calibration, and an established engine does it: COLMAP, through its Python bindings
``pycolmap`` (an optional dependency: ``pip install pycolmap``).

1. :func:`reconstruct`: COLMAP's SIFT on every frame (at most ``max_image_side`` px and
   :func:`feature_cap` features), exhaustive matching (or sequential for long videos), geometric
   verification, incremental mapping with one shared RADIAL camera whose principal point stays at
   the frame centre (the data rarely pin it, and refining it was measured to go wrong). A frame
   that sees too few of the 3-D points to be posed is left out: COLMAP's structure-less fallback,
   which poses it from its 2-D matches alone, takes seconds per frame. One mapping answers
   (``reconstructions``); with a caller's ``stop`` up to ``extra_mappings`` further seeds are
   tried where a mapping registers too few frames (a wrong initial pair).
2. :func:`self_calibrate_reconstruction`: every model of ``models`` is fitted by a global bundle
   adjustment on the same tracks (structure, poses, focal length and the model's distortion
   free), stopping when an iteration lowers the cost by less than ``BA_FUNCTION_TOLERANCE`` of it
   (Ceres' default; COLMAP's 0 crawled along the valley of a poorly conditioned camera).
3. **Which model, and how sure** (:mod:`~lensdist_torch.geometry.multiview_evidence`): each
   model's posterior of Delta from the adjustment's covariance, its evidence from predicting
   frames held out in ``jackknife_blocks`` blocks, the models weighed by it (pseudo-BMA+); the
   model of most weight answers, the interval is the weighted mixture of their posteriors.
   Degenerate motion (translation over relief) shows as a wide posterior. The same folds' fits
   are each model's jackknife, the check of its posterior: where they scatter more, the
   posterior is widened to them (:func:`~lensdist_torch.geometry.multiview_evidence.checked_scale`).
   With several ``reconstructions`` their spread joins in quadrature
   (:mod:`~lensdist_torch.geometry.multiview_runs`).
4. **In the user's pixels and OpenCV's terms**: COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV and
   FULL_OPENCV are OpenCV's model with some coefficients 0, so the OpenCV camera is exact (the
   principal point moves by -0.5 px: COLMAP's pixel centres lie at +0.5). Delta is
   |p - ideal(p)| of the converged inverse over the pixels where the model inverts
   (:func:`~lensdist_torch.geometry.opencv_model.opencv_delta`); eq. 4's (k2, k4) are fitted to
   that map by least squares and ``eq4_fit_error_px`` says how well eq. 4 can follow the lens.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import torch

from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.geometry.distortion import fit_eq4, paper_frame_delta_avg
from lensdist_torch.geometry.multiview_evidence import (
    camera_covariance,
    checked_scale,
    dispersion,
    evidence_weights,
    heldout_rms,
    heldout_squared_errors,
    mixture_interval,
    posterior_std,
    unit_log_evidence,
)
from lensdist_torch.geometry.opencv_model import grid_points, map_grid_step, opencv_delta, opencv_from_colmap, opencv_ideal_points
from lensdist_torch.geometry.sequence_class import interval_too_wide, sequence_class

__all__ = ["MultiViewCalibration", "pycolmap_or_error", "feature_cap", "extract_and_match", "reconstruct", "self_calibrate_reconstruction", "opencv_from_colmap",
           "rotation_spread_deg", "BA_FUNCTION_TOLERANCE"]

#: Relative cost decrease below which a bundle adjustment stops (module docstring, step 2).
BA_FUNCTION_TOLERANCE = 1e-6


class MultiViewCalibration(NamedTuple):
    """The result of :func:`self_calibrate_reconstruction`, in the user's pixels; NaN where unknown.

    model: the COLMAP model of most evidence; camera_matrix (3, 3) and dist_coeffs (5 or 8, OpenCV's
    order) its exact OpenCV camera; delta_avg_user_px, delta_max_user_px over the pixels where
    the model inverts (``invertible_fraction`` of them), with ``confidence`` intervals;
    k2_user, k4_user: eq. 4 fitted to the camera, ``eq4_fit_error_px`` its RMS error;
    class_label or None with ``reason``; registered of ``frames``; points3D; reprojection_px
    (RMS of the chosen model); models: per fitted model its evidence ``weight``, Delta_avg and
    Delta_max (over where it inverts) with their posterior stds, the jackknife's std
    (``jackknife_std_px``, the check), RMS on its tracks and on held-out frames
    (``heldout_rms_px``), BIC, rotation spread and OpenCV camera (``camera_matrix``,
    ``dist_coeffs``: Delta on another footprint from it);
    jackknife: the chosen model's leave-a-block-out Delta_avg values; rotation_spread_deg: the
    largest rotation between two frames of the mapping (a diagnostic);
    reconstructions: per seed of the mapping its numbers (set by
    :func:`~lensdist_torch.geometry.multiview_runs.combine_reconstructions`), and
    reconstruction_spread_px the largest |Delta_avg - this one's| among them;
    paper_delta_avg_px: the Delta_avg of eq. 4's fit at the paper's frame, whose class is given
    (:func:`~lensdist_torch.geometry.sequence_class.sequence_class`); dispersion: the jackknife's scale (>= 1).
    """

    model: str
    camera_matrix: list
    dist_coeffs: list
    delta_avg_user_px: float
    delta_avg_user_interval: tuple[float, float]
    delta_max_user_px: float
    delta_max_user_interval: tuple[float, float]
    invertible_fraction: float
    k2_user: float
    k4_user: float
    eq4_fit_error_px: float
    class_label: str | None
    reason: str
    registered: int
    frames: int
    points3D: int
    reprojection_px: float
    models: dict
    jackknife: list
    rotation_spread_deg: float
    reconstructions: tuple = ()
    reconstruction_spread_px: float = 0.0
    paper_delta_avg_px: float = math.nan
    dispersion: float = 1.0


def pycolmap_or_error():
    """The ``pycolmap`` module, or a one-line ``ValueError`` saying how to install it."""
    try:
        import pycolmap
    except ImportError:
        raise ValueError("the multi-view calibration needs pycolmap (COLMAP's Python bindings): pip install pycolmap, "
                         "or --method direct") from None
    return pycolmap


@contextlib.contextmanager
def _quiet():
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


# ------------------------------------------------------------------ the reconstruction
def feature_cap(config: MultiViewConfig, image_size: tuple[int, int] | None = None) -> int:
    """SIFT features per frame at most (``max_features``, and by area where the frames' size is known).

    ``features_per_megapixel`` of the frame's area as SIFT reads it (at most ``max_image_side``
    long) where ``image_size`` (H, W) is given; never below 64.

    Example:
        >>> feature_cap(MultiViewConfig(), (288, 384)), feature_cap(MultiViewConfig(), (1080, 1920))
        (906, 8192)
    """
    if image_size is None:
        return config.max_features
    h, w = image_size
    shrink = min(1.0, config.max_image_side / max(h, w))
    return max(64, min(config.max_features, math.ceil(config.features_per_megapixel * h * w * shrink * shrink / 1e6)))


def reconstruct(image_dir: str | Path, names: list[str], config: MultiViewConfig | None = None,
                stop: Callable[[int, object], bool] | None = None, image_size: tuple[int, int] | None = None,
                on_matches: Callable[[Path], None] | None = None) -> list:
    """COLMAP's sparse reconstructions of frames ``names`` in ``image_dir`` (module docstring, step 1).

    The features and the verified matches are computed once (geometric verification seeded by
    ``seed``); the incremental mapping runs ``reconstructions`` times on them, with the seeds
    ``seed``, ``seed`` + 1, ... (the engine's run-to-run variation, which the interval takes in:
    :mod:`~lensdist_torch.geometry.multiview_runs`).

    Args:
        image_dir: the folder of the frames.
        names: the frames' file names in it, in recording order.
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        stop: called after each mapping with its index and its reconstruction (or None), outside
            the silenced log; True skips the remaining mappings (each costs as much as the
            first: 40-45 s on 22 frames of 384 x 288 on 2 cores). With ``stop`` up to
            ``reconstructions + extra_mappings`` mappings run, without it ``reconstructions``.
        image_size: the frames' (H, W), for the features' cap (:func:`feature_cap`); None: ``max_features``.
        on_matches: called with the database's path once the features and verified matches are in
            it, before the first mapping (the homography model reads them:
            :func:`~lensdist_torch.geometry.planar_features.read_verified_matches`).

    Returns:
        Per mapping run the largest ``pycolmap.Reconstruction`` (one shared camera), or None where
        COLMAP reconstructed nothing.
    """
    pc, cfg = pycolmap_or_error(), or_defaults(config, MultiViewConfig)
    out = []
    with tempfile.TemporaryDirectory(prefix="lensdist-colmap-") as tmp:
        db = Path(tmp) / "db.db"
        extract_and_match(db, image_dir, names, cfg, image_size)
        if on_matches is not None:
            on_matches(db)
        for i in range(cfg.reconstructions + (cfg.extra_mappings if stop is not None else 0)):
            pc.set_random_seed(cfg.seed + i)
            mapping = pc.IncrementalPipelineOptions()
            mapping.num_threads, mapping.random_seed, mapping.ba_refine_principal_point = cfg.num_threads, cfg.seed + i, False
            mapping.ba_global_function_tolerance = mapping.ba_local_function_tolerance = BA_FUNCTION_TOLERANCE
            mapping.structure_less_registration_fallback = False  # seconds per frame; such frames add little
            with _quiet():
                recs = pc.incremental_mapping(db, image_dir, Path(tmp) / f"sparse{i}", options=mapping)
            out.append(max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D())) if recs else None)
            if stop is not None and stop(i, out[-1]):
                break
    return out


def extract_and_match(database: str | Path, image_dir: str | Path, names: list[str], config: MultiViewConfig | None = None,
                      image_size: tuple[int, int] | None = None) -> None:
    """COLMAP's SIFT features of frames ``names`` and their verified matches, into a new ``database`` (step 1).

    Exhaustive matching up to ``exhaustive_below`` frames, sequential beyond; one shared RADIAL
    camera; the geometric verification's RANSAC seeded by ``seed``. :func:`reconstruct` maps on it;
    :func:`~lensdist_torch.geometry.planar_features.read_verified_matches` reads its matches.
    """
    pc, cfg = pycolmap_or_error(), or_defaults(config, MultiViewConfig)
    pc.set_random_seed(cfg.seed)
    reader = pc.ImageReaderOptions()
    reader.camera_model = "RADIAL"
    extraction = pc.FeatureExtractionOptions()
    extraction.num_threads, extraction.max_image_size, extraction.use_gpu = cfg.num_threads, cfg.max_image_side, False
    extraction.sift.max_num_features = feature_cap(cfg, image_size)
    matching = pc.FeatureMatchingOptions()
    matching.num_threads, matching.use_gpu = cfg.num_threads, False
    verification = pc.TwoViewGeometryOptions()
    verification.ransac.random_seed = cfg.seed  # COLMAP's default (-1) seeds every RANSAC from the clock
    with _quiet():
        pc.extract_features(database, image_dir, image_names=list(names), camera_mode=pc.CameraMode.SINGLE,
                            reader_options=reader, extraction_options=extraction, device=pc.Device.cpu)
        if len(names) <= cfg.exhaustive_below:
            pc.match_exhaustive(database, matching_options=matching, verification_options=verification, device=pc.Device.cpu)
        else:
            pairing = pc.SequentialPairingOptions()
            pairing.overlap = cfg.sequential_overlap
            pc.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                verification_options=verification, device=pc.Device.cpu)


# ------------------------------------------------------------------ models on the tracks
def _camera(rec):
    cams = list(rec.cameras.values())
    if len(cams) != 1:
        raise ValueError(f"reconstruction must hold one shared camera, got {len(cams)}")
    return cams[0]


def _rss(rec) -> tuple[float, int]:
    """Sum of squared reprojection errors (px^2) and the number of observations."""
    import numpy as np

    cam, ss, n = _camera(rec), 0.0, 0
    for image_id in rec.reg_image_ids():
        image = rec.image(image_id)
        obs = [(p.xy, rec.point3D(p.point3D_id).xyz) for p in image.points2D if p.has_point3D()]
        if not obs:
            continue
        xy, xyz = np.array([o[0] for o in obs]), np.array([o[1] for o in obs])
        proj = cam.img_from_cam(image.cam_from_world() * xyz)
        ss, n = ss + float(np.nansum((proj - xy) ** 2)), n + len(obs)
    return ss, n


def _adjust(rec) -> None:
    pc = pycolmap_or_error()
    options = pc.BundleAdjustmentOptions()
    options.refine_principal_point, options.print_summary = False, False
    options.ceres.solver_options.function_tolerance = BA_FUNCTION_TOLERANCE
    with _quiet():
        pc.bundle_adjustment(rec, options)


def _with_model(rec, model: str):
    """A copy of ``rec`` whose camera is ``model`` (focal and the first radial terms carried over), adjusted."""
    pc = pycolmap_or_error()
    out, cam = _pycolmap_copy(rec), _camera(rec)
    new = pc.Camera.create_from_model_name(cam.camera_id, model, cam.mean_focal_length(), cam.width, cam.height)
    params = new.params.copy()
    old_extra, new_extra = list(cam.extra_params_idxs()), list(new.extra_params_idxs())
    for i, j in zip(old_extra[:2], new_extra[:2]):  # k1 (and k2) mean the same in every model here
        params[j] = cam.params[i]
    new.params = params
    out.cameras[cam.camera_id] = new
    _adjust(out)
    return out


def _deltas(camera, size: tuple[int, int], scale: float, step: int) -> dict:
    k, d = opencv_from_colmap(camera, scale)
    return opencv_delta(k, d, *size, step=step)


def _eq4_fit(camera, size: tuple[int, int], scale: float, step: int) -> tuple[float, float, float]:
    """Eq. 4's (k2, k4) about the frame centre fitted to the camera's ideal points, and the RMS error (px)."""
    h, w = size
    k, d = opencv_from_colmap(camera, scale)
    p = grid_points(h, w, step)
    ideal, ok = opencv_ideal_points(p, k, d)
    return fit_eq4(p[ok], ideal[ok], h, w)


def rotation_spread_deg(rec) -> float:
    """The largest rotation (degrees) between two registered frames' orientations.

    Under translation alone a relief of the scene imitates radial distortion however many
    frames there are (docs/method.md, section 11): the bundle adjustment then has a valley, not
    a minimum, and every jackknife replicate stops at the same point of it.
    """
    import numpy as np

    rots = np.stack([rec.image(i).cam_from_world().rotation.matrix() for i in rec.reg_image_ids()])
    rel = np.einsum("aij,bkj->abik", rots, rots)  # R_a R_b^T
    cos = np.clip((np.trace(rel, axis1=2, axis2=3) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def _blocks(rec, n_blocks: int) -> list[list[int]]:
    """Registered frame ids in contiguous blocks by image name (recording order)."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    n = len(images)
    return [[im.frame_id for im in images[g * n // n_blocks:(g + 1) * n // n_blocks]] for g in range(n_blocks)]


def _fit_model(rec, model: str, size: tuple[int, int], scale: float, step: int, n_blocks: int) -> dict:
    """One model on ``rec``'s tracks: its adjustment, posterior, delete-a-block fits and held-out errors."""
    import numpy as np

    r = _with_model(rec, model)
    ss, n = _rss(r)
    cam = _camera(r)
    km, dm = opencv_from_colmap(cam, scale)
    dl = opencv_delta(km, dm, *size, step=step)

    def measure(params):  # Delta_avg and Delta_max of the camera with other intrinsics, on a grid 16 times coarser
        c = copy.copy(cam)  # (their gradient and the folds' spread need no finer one)
        c.params = params
        d = _deltas(c, size, scale, 4 * step)
        return d["delta_avg_px"], d["delta_max_px"]

    with _quiet():
        cov = camera_covariance(r, cam.camera_id, ss, n)
    fixed = set(cam.principal_point_idxs())
    std_avg, std_max = posterior_std(list(cam.params), [i for i in range(len(cam.params)) if i not in fixed], cov, measure)
    jk_avg, jk_max, errors = [], [], []
    for block in _blocks(r, n_blocks):
        train = _pycolmap_copy(r)
        for frame_id in block:
            train.deregister_frame(frame_id)
        _adjust(train)
        d = measure(np.asarray(_camera(train).params, dtype=float))
        jk_avg.append(d[0])
        jk_max.append(d[1])
        errors.append(heldout_squared_errors(train, _camera(train), r, block))
    jk_std = math.sqrt((len(jk_avg) - 1) / len(jk_avg) * float(np.sum((np.asarray(jk_avg) - np.mean(jk_avg)) ** 2)))
    k = len(cam.params) - 2  # the principal point is held
    return {"rec": r, "delta": dl, "errors": errors, "jackknife": jk_avg, "row": {
        "bic": 2 * n * math.log(max(ss, 1e-300) / (2 * n)) + k * math.log(2 * n), "delta_avg_px": dl["delta_avg_px"],
        "delta_avg_std_px": std_avg, "delta_max_px": dl["delta_max_px"], "delta_max_std_px": std_max,
        "jackknife_std_px": jk_std, "reprojection_px": math.sqrt(ss / max(n, 1)),
        "heldout_rms_px": heldout_rms([e for fold in errors for e in fold]),
        "rotation_deg": rotation_spread_deg(r), "camera_matrix": km.tolist(), "dist_coeffs": dm.tolist()}}


def self_calibrate_reconstruction(
    rec,
    config: MultiViewConfig | None = None,
    settings: LensdistConfig | None = None,
    *,
    frames: int | None = None,
    image_size: tuple[int, int] | None = None,
    scale: float = 1.0,
    on_model: Callable[[str], None] | None = None,
) -> MultiViewCalibration:
    """The camera's distortion from a reconstruction's tracks (module docstring, steps 2-4).

    Args:
        rec: a ``pycolmap.Reconstruction`` with one shared camera (it is not changed).
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        settings: the library's config (the class rule and the paper's frame).
        frames: the sequence's number of frames (default: the registered ones).
        image_size: the user's (H, W) (default: the camera's, times ``scale``).
        scale: user px per reconstruction px.
        on_model: called with each model's name once it is fitted with its folds (a progress bar).

    Returns:
        :class:`MultiViewCalibration`.
    """
    cfg, st = or_defaults(config, MultiViewConfig), or_defaults(settings, LensdistConfig, "settings")
    if rec.num_reg_images() < 3:
        raise ValueError(f"rec must hold at least 3 registered frames, got {rec.num_reg_images()}")
    if rec.num_points3D() == 0:  # a mapping can register frames and keep no point (tiny frames)
        raise ValueError(f"rec must hold 3-D points, got none ({rec.num_reg_images()} frames registered)")
    size = image_size or (round(_camera(rec).height * scale), round(_camera(rec).width * scale))
    step = map_grid_step(*size)
    n_blocks = min(cfg.jackknife_blocks, rec.num_reg_images())  # each fold keeps >= 2 frames
    fits = {}
    for model in cfg.models:
        fits[model] = _fit_model(rec, model, size, scale, step, n_blocks)
        if on_model is not None:
            on_model(model)
    rows = [f["row"] for f in fits.values()]
    spread = dispersion([r["delta_avg_std_px"] for r in rows], [r["jackknife_std_px"] for r in rows])
    weights = evidence_weights(unit_log_evidence([f["errors"] for f in fits.values()]) / spread, cfg.evidence_draws, cfg.seed)
    table = {m: {**r, "weight": float(w)} for m, r, w in zip(fits, rows, weights)}
    best = max(table, key=lambda m: table[m]["weight"])
    chosen, dl, cam = fits[best]["rec"], fits[best]["delta"], _camera(fits[best]["rec"])
    widen = [checked_scale(spread, r["delta_avg_std_px"], r["jackknife_std_px"]) for r in rows]
    intervals = [tuple(max(0.0, v) for v in mixture_interval([r[f"{fig}_px"] for r in rows], [r[f"{fig}_std_px"] * math.sqrt(w)
                 for r, w in zip(rows, widen)], weights, cfg.confidence)) for fig in ("delta_avg", "delta_max")]
    k2u, k4u, fit_err = _eq4_fit(cam, size, scale, step)
    half_avg = max(intervals[0][1] - dl["delta_avg_px"], dl["delta_avg_px"] - intervals[0][0])
    label, reason = None, ""
    dc = paper_frame_delta_avg(k2u, k4u, size, st)  # eq. 4 at the paper's frame, same normalised lens
    if interval_too_wide(half_avg, dl["delta_avg_px"], cfg):
        shared = ", ".join(f"{m} {v['delta_avg_px']:.2f} px at {v['weight']:.2f}" for m, v in
                           sorted(table.items(), key=lambda kv: -kv[1]["weight"]) if v["weight"] >= 0.01)
        reason = f"interval too wide: +-{half_avg:.2f} px" + (f" (the models' evidence is shared: {shared})" if
                                                               table[best]["weight"] <= 0.95 else "")
    else:
        label, reason = sequence_class(dc, dl["delta_avg_px"], half_avg, st)
    k, d = opencv_from_colmap(cam, scale)
    return MultiViewCalibration(
        model=best, camera_matrix=k.tolist(),
        dist_coeffs=(d if d.numel() == 8 else torch.cat([d, d.new_zeros(5 - d.numel())])).tolist(),
        delta_avg_user_px=dl["delta_avg_px"], delta_avg_user_interval=intervals[0], delta_max_user_px=dl["delta_max_px"],
        delta_max_user_interval=intervals[1], invertible_fraction=dl["invertible_fraction"], k2_user=k2u, k4_user=k4u,
        eq4_fit_error_px=fit_err, class_label=label, reason=reason, registered=chosen.num_reg_images(),
        frames=frames or chosen.num_reg_images(), points3D=chosen.num_points3D(),
        reprojection_px=table[best]["reprojection_px"], models=table, jackknife=fits[best]["jackknife"],
        rotation_spread_deg=rotation_spread_deg(rec), paper_delta_avg_px=dc, dispersion=spread)


def _pycolmap_copy(rec):
    return pycolmap_or_error().Reconstruction(rec)
