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
   (``reconstructions``); with a caller's ``stop`` up to ``EXTRA_MAPPINGS`` further seeds are
   tried where a mapping registers too few frames (a wrong initial pair).
2. :func:`self_calibrate_reconstruction`: every model of ``models`` is fitted by a global bundle
   adjustment on the same tracks (structure, poses, focal length and the model's distortion free;
   a seeded share of the tracks beyond ``MAX_OBSERVATIONS`` observations:
   :func:`~lensdist_torch.calibration.multiview_fits.thinned`), stopping when an iteration lowers
   the cost by less than ``BA_FUNCTION_TOLERANCE`` of it (Ceres' default; COLMAP's 0 crawled along
   the valley of a poorly conditioned camera). On many observations the candidates are fitted
   side by side in ``num_threads`` worker processes
   (:mod:`~lensdist_torch.calibration.multiview_workers`).
3. **Which model, and how sure** (:mod:`~lensdist_torch.calibration.multiview_evidence`): each
   model's posterior of Delta from the adjustment's covariance, its evidence from predicting
   frames held out in ``jackknife_blocks`` blocks, the models weighed by it (pseudo-BMA+). Other
   cameras (``others``, e.g. another path's answer) can be held on the same tracks and scored on
   the same folds (:func:`~lensdist_torch.calibration.multiview_fits.fit_held_camera`); ``lensdist
   calibrate`` holds the direct path's and the homography model's (docs/method.md, section 11). The
   candidate of the highest expected log predictive density answers, the interval is the
   weighted mixture of all their posteriors; a model whose posterior is unbounded (one the
   tracks do not determine) gets no weight. Degenerate motion
   (translation over relief) shows as a wide posterior. The same folds' fits are each model's
   jackknife, the check of its posterior: where they scatter more, the posterior is widened to
   them (:func:`~lensdist_torch.calibration.multiview_evidence.checked_scale`). With several
   ``reconstructions`` their spread joins in quadrature
   (:mod:`~lensdist_torch.calibration.multiview_runs`).
4. **In the user's pixels and OpenCV's terms**: COLMAP's SIMPLE_RADIAL, RADIAL, OPENCV and
   FULL_OPENCV are OpenCV's model with some coefficients 0, so the OpenCV camera is exact (the
   principal point moves by -0.5 px: COLMAP's pixel centres lie at +0.5). Delta is
   |p - ideal(p)| of the converged inverse over the pixels where the model inverts
   (:func:`~lensdist_torch.geometry.opencv_model.opencv_delta`); eq. 4's (k2, k4) are fitted to
   that map by least squares and ``eq4_fit_error_px`` says how well eq. 4 can follow the lens.

References:
    J. L. Schönberger, J.-M. Frahm, "Structure-from-Motion Revisited", CVPR 2016 (COLMAP: features,
    matching, incremental mapping, bundle adjustment).
    B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment: a modern synthesis",
    Vision Algorithms: Theory and Practice, 2000.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist

import torch

from lensdist_torch.calibration.features import EXHAUSTIVE_BELOW, SEQUENTIAL_OVERLAP, extract_and_match, feature_cap
from lensdist_torch.calibration.lens_answer import LensAnswer
from lensdist_torch.calibration.multiview_evidence import weigh_models
from lensdist_torch.calibration.multiview_fits import (
    BA_FUNCTION_TOLERANCE,
    MAX_OBSERVATIONS,
    camera_of,
    held_camera,
    pycolmap_or_error,
    quiet_log,
    rotation_spread_deg,
    thinned,
)
from lensdist_torch.calibration.multiview_workers import candidate_fits
from lensdist_torch.calibration.sequence_class import interval_class
from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.config.sequence import MULTIVIEW_MODELS
from lensdist_torch.geometry.distortion import fit_eq4, paper_frame_delta_avg
from lensdist_torch.geometry.opencv_model import grid_points, map_grid_step, opencv_from_colmap, opencv_ideal_points

__all__ = [
    "EVIDENCE_DRAWS",
    "EXHAUSTIVE_BELOW",
    "EXTRA_MAPPINGS",
    "SEQUENTIAL_OVERLAP",
    "MultiViewCalibration",
    "pycolmap_or_error",
    "feature_cap",
    "extract_and_match",
    "reconstruct",
    "self_calibrate_reconstruction",
    "opencv_from_colmap",
    "rotation_spread_deg",
    "BA_FUNCTION_TOLERANCE",
]

#: Bayesian-bootstrap draws over the folds for the models' evidence weights (docs/method.md, section 11).
EVIDENCE_DRAWS = 1000
#: Mappings tried with further seeds where one registers too few frames (a wrong initial pair: the focal length
#: runs off and the mapping ends early).
EXTRA_MAPPINGS = 3


@dataclass(frozen=True, kw_only=True)
class MultiViewCalibration(LensAnswer):
    """The result of :func:`self_calibrate_reconstruction`: the lens answer and the multi-view diagnostics.

    The core fields are :class:`~lensdist_torch.calibration.lens_answer.LensAnswer`'s: Delta_avg
    and Delta_max over the pixels where the model inverts, with ``confidence`` intervals; (k2,
    k4) eq. 4 fitted to the camera.

    Attributes:
        model: the COLMAP camera model of most evidence.
        camera_matrix: (3, 3) its OpenCV camera matrix (a COLMAP model's exactly).
        dist_coeffs: its OpenCV distortion coefficients (5 or 8, OpenCV's order).
        invertible_fraction: the share of the frame's pixels where the model inverts.
        eq4_fit_error_px: RMS error (px) of eq. 4's fit to the camera.
        registered: frames the mapping registered.
        frames: frames handed to the mapping.
        points3D: 3-D points of the reconstruction.
        observations: the observations the models were weighed on: all of the reconstruction's, or
            a seeded share of its 3-D points' beyond ``multiview_fits.MAX_OBSERVATIONS``
            (:func:`~lensdist_torch.calibration.multiview_fits.thinned`).
        reprojection_px: RMS reprojection error (px) of the chosen model.
        models: per fitted model its evidence ``weight``, Delta_avg and Delta_max (over where it
            inverts) with their posterior stds, the jackknife's std (``jackknife_std_px``, the
            check), RMS on its tracks and on held-out frames (``heldout_rms_px``), BIC, rotation
            spread and OpenCV camera (``camera_matrix``, ``dist_coeffs``, and fx's posterior std
            ``focal_std_px``, inf where the tracks do not determine the camera), and whether its
            adjustment ``converged`` (in how many ``iterations``; one that did not has no posterior).
        jackknife: the chosen model's leave-a-block-out Delta_avg values (px).
        rotation_spread_deg: the largest rotation between two frames of the mapping (a diagnostic).
        reconstructions: per seed of the mapping its numbers (set by
            :func:`~lensdist_torch.calibration.multiview_runs.combine_reconstructions`).
        reconstruction_spread_px: the largest |Delta_avg - this one's| among them.
        paper_delta_avg_px: the Delta_avg of eq. 4's fit at the paper's frame, whose class is given
            (:func:`~lensdist_torch.calibration.sequence_class.sequence_class`).
        dispersion: the jackknife's scale of the posteriors (>= 1).
    """

    model: str
    camera_matrix: list
    dist_coeffs: list
    invertible_fraction: float
    eq4_fit_error_px: float
    registered: int
    frames: int
    points3D: int
    observations: int
    reprojection_px: float
    models: dict
    jackknife: list
    rotation_spread_deg: float
    reconstructions: tuple = ()
    reconstruction_spread_px: float = 0.0
    paper_delta_avg_px: float = math.nan
    dispersion: float = 1.0


# ------------------------------------------------------------------ the reconstruction
def reconstruct(image_dir: str | Path, names: list[str], *, config: MultiViewConfig | None = None,
                stop: Callable[[int, object], bool] | None = None, image_size: tuple[int, int] | None = None,
                on_matches: Callable[[Path], None] | None = None,
                on_stage: Callable[[str, int], None] | None = None) -> list:
    """COLMAP's sparse reconstructions of frames ``names`` in ``image_dir`` (module docstring, step 1).

    The features and the verified matches are computed once (geometric verification seeded by
    ``seed``); the incremental mapping runs ``reconstructions`` times on them, with the seeds
    ``seed``, ``seed`` + 1, ... (the engine's run-to-run variation, which the interval takes in:
    :mod:`~lensdist_torch.calibration.multiview_runs`).

    Args:
        image_dir: the folder of the frames.
        names: the frames' file names in it, in recording order.
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        stop: called after each mapping with its index and its reconstruction (or None), outside
            the silenced log; True skips the remaining mappings (each costs as much as the
            first). With ``stop`` up to
            ``reconstructions +`` :data:`EXTRA_MAPPINGS` mappings run, without it ``reconstructions``.
        image_size: the frames' (H, W), for the features' cap (:func:`feature_cap`); None: ``max_features``.
        on_matches: called with the database's path once the features and verified matches are in
            it, before the first mapping (the homography model reads them:
            :func:`~lensdist_torch.calibration.matches.read_verified_matches`).
        on_stage: called as each of COLMAP's stages starts, with its name ("extraction", "matching",
            "verification", "mapping") and the threads it runs on.

    Returns:
        Per mapping run the largest ``pycolmap.Reconstruction`` (one shared camera), or None where
        COLMAP reconstructed nothing.
    """
    pc, cfg = pycolmap_or_error(), or_defaults(config, MultiViewConfig)
    out, stage = [], on_stage or (lambda name, threads: None)
    with tempfile.TemporaryDirectory(prefix="lensdist-colmap-") as tmp:
        db = Path(tmp) / "db.db"
        extract_and_match(db, image_dir, names, config=cfg, image_size=image_size, on_stage=on_stage)
        if on_matches is not None:
            on_matches(db)
        for i in range(cfg.reconstructions + (EXTRA_MAPPINGS if stop is not None else 0)):
            pc.set_random_seed(cfg.seed + i)
            mapping = pc.IncrementalPipelineOptions()
            mapping.num_threads, mapping.random_seed, mapping.ba_refine_principal_point = (
                1,  # with more it did not repeat, and was no faster (docs/method.md, section 11)
                cfg.seed + i,
                False,
            )
            mapping.ba_global_function_tolerance = mapping.ba_local_function_tolerance = BA_FUNCTION_TOLERANCE
            mapping.structure_less_registration_fallback = False  # seconds per frame; such frames add little
            stage("mapping", mapping.num_threads)
            with quiet_log():
                recs = pc.incremental_mapping(db, image_dir, Path(tmp) / f"sparse{i}", options=mapping)
            out.append(max(recs.values(), key=lambda r: (r.num_reg_images(), r.num_points3D())) if recs else None)
            if stop is not None and stop(i, out[-1]):
                break
    return out


def _eq4_fit(k: torch.Tensor, d: torch.Tensor, size: tuple[int, int], step: int) -> tuple[float, float, float]:
    """Eq. 4's (k2, k4) about the frame centre fitted to an OpenCV camera's ideal points, and the RMS error (px)."""
    h, w = size
    p = grid_points(h, w, step)
    ideal, ok = opencv_ideal_points(p, k, d)
    return fit_eq4(p[ok], ideal[ok], h, w)


def _other_rows(submit, others: dict, fits: dict, scale: float, n_blocks: int, confidence: float) -> dict:
    """Other paths' cameras held on the tracks (:func:`~lensdist_torch.calibration.multiview_fits.fit_held_camera`).

    At the focal length of the COLMAP model that predicts the held-out frames best; each path's
    own Delta with its own interval as a normal std. A path without a finite answer is left out.
    ``submit``: :func:`~lensdist_torch.calibration.multiview_workers.candidate_fits`'s.
    """
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    ranked = min(fits, key=lambda m: fits[m]["row"]["heldout_rms_px"])
    base = fits[ranked]["camera"]
    futures = {}
    for name, o in others.items():
        values = [o.get(k) for k in ("delta_avg_user_px", "delta_max_user_px")]
        ivs = [o.get(k) for k in ("delta_avg_user_interval", "delta_max_user_interval")]
        if not all(v is not None and math.isfinite(v) for v in values) or any(iv is None or None in iv for iv in ivs):
            continue
        cam = held_camera(
            o["camera_matrix"],
            o["dist_coeffs"],
            focal=base.mean_focal_length(),
            camera_id=base.camera_id,
            width=base.width,
            height=base.height,
            scale=scale,
        )
        futures[name] = (submit("held", camera=cam, n_blocks=n_blocks), values, ivs)
    out = {}
    for name, (future, values, ivs) in futures.items():
        o, fit = others[name], future.result()
        stds = [max(hi - v, v - lo) / z for v, (lo, hi) in zip(values, ivs)]
        out[name] = {
            **fit,
            "row": {
                "path": name,
                "delta_avg_px": values[0],
                "delta_avg_std_px": stds[0],
                "delta_max_px": values[1],
                "delta_max_std_px": stds[1],
                "reprojection_px": fit["reprojection_px"],
                "heldout_rms_px": fit["heldout_rms_px"],
                "converged": fit["converged"],
                "iterations": fit["iterations"],
                "invertible_fraction": o.get("invertible_fraction", 1.0),
                "camera_matrix": [list(r) for r in o["camera_matrix"]],
                "dist_coeffs": list(o["dist_coeffs"]),
            },
        }
    return out


def self_calibrate_reconstruction(
    rec,
    config: MultiViewConfig | None = None,
    settings: LensdistConfig | None = None,
    *,
    frames: int | None = None,
    image_size: tuple[int, int] | None = None,
    scale: float = 1.0,
    others: dict[str, dict] | None = None,
    on_model: Callable[[str], None] | None = None,
) -> MultiViewCalibration:
    """The camera's distortion from a reconstruction's tracks (module docstring, steps 2-4).

    Args:
        rec: a ``pycolmap.Reconstruction`` with one shared camera (it is not changed).
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        settings: the library's config (the intervals' coverage ``calibration.confidence``, the class rule
            and the paper's frame).
        frames: the sequence's number of frames (default: the registered ones).
        image_size: the user's (H, W) (default: the camera's, times ``scale``).
        scale: user px per reconstruction px.
        others: other cameras' answers (another path's), weighed on the same held-out frames with
            their cameras held (step 3): per name a dict with ``camera_matrix`` (3, 3) and ``dist_coeffs`` (OpenCV's 5
            or 8, in the user's pixels), ``delta_avg_user_px``, ``delta_max_user_px`` and their
            ``_interval``s (read as normal at ``confidence``); a path that wins answers with its own
            numbers and camera.
        on_model: called with each model's name once it is fitted with its folds (a progress bar).

    Returns:
        :class:`MultiViewCalibration`.
    """
    cfg, st = or_defaults(config, MultiViewConfig), or_defaults(settings, LensdistConfig, "settings")
    if rec.num_reg_images() < 3:
        raise ValueError(f"rec must hold at least 3 registered frames, got {rec.num_reg_images()}")
    if rec.num_points3D() == 0:  # a mapping can register frames and keep no point (tiny frames)
        raise ValueError(f"rec must hold 3-D points, got none ({rec.num_reg_images()} frames registered)")
    size = image_size or (round(camera_of(rec).height * scale), round(camera_of(rec).width * scale))
    step = map_grid_step(*size)
    n_blocks = min(cfg.jackknife_blocks, rec.num_reg_images())  # each fold keeps >= 2 frames
    weighed, observations = thinned(rec, MAX_OBSERVATIONS, seed=cfg.seed)  # the tracks the models are weighed on
    fits = {}
    with candidate_fits(weighed, observations, processes=cfg.num_threads) as submit:
        futures = {m: submit("model", model=m, size=size, scale=scale, step=step, n_blocks=n_blocks)
                   for m in sorted(cfg.models, key=MULTIVIEW_MODELS.index, reverse=True)}  # the most parameters first
        for model in cfg.models:
            fits[model] = futures[model].result()
            if on_model is not None:
                on_model(model)
        held = _other_rows(submit, others or {}, fits, scale, n_blocks, st.calibration.confidence)
    rows = [f["row"] for f in fits.values()]
    fits, checked = {**fits, **held}, [True] * len(rows) + [False] * len(held)
    rows += [h["row"] for h in held.values()]
    weighed = weigh_models(rows, [f["errors"] for f in fits.values()], checked=checked,
                           confidence=st.calibration.confidence, draws=EVIDENCE_DRAWS, seed=cfg.seed)
    weights, lpd, carried, intervals = (weighed[k] for k in ("weights", "lpd", "carried", "intervals"))
    spread = weighed["dispersion"]
    table = {m: {**r, "weight": float(w), "elpd": float(e)} for m, r, w, e in zip(fits, rows, weights, lpd.sum(axis=1))}
    best = max(
        (m for m, c in zip(table, carried) if c), key=lambda m: table[m]["elpd"]
    )  # near-twins split weight, not elpd
    if best in held:
        row = table[best]
        k, d = (
            torch.tensor(row["camera_matrix"], dtype=torch.float64),
            torch.tensor(row["dist_coeffs"], dtype=torch.float64),
        )
        dl = {"delta_avg_px": row["delta_avg_px"], "delta_max_px": row["delta_max_px"],
              "invertible_fraction": row["invertible_fraction"]}
    else:
        k, d = opencv_from_colmap(fits[best]["camera"], scale)
        dl = fits[best]["delta"]
    k2u, k4u, fit_err = _eq4_fit(k, d, size, step)
    dc = paper_frame_delta_avg(k2u, k4u, size, st)  # eq. 4 at the paper's frame, same normalised lens
    label, reason = interval_class(dc, dl["delta_avg_px"], intervals[0], st)
    if label is None and table[best]["weight"] <= 0.95:
        shared = ", ".join(f"{m} {v['delta_avg_px']:.2f} px at {v['weight']:.2f}" for m, v in
                           sorted(table.items(), key=lambda kv: -kv[1]["weight"]) if v["weight"] >= 0.01)
        reason += f" (the models' evidence is shared: {shared})"
    return MultiViewCalibration(
        model=best,
        camera_matrix=k.tolist(),
        dist_coeffs=(d if d.numel() == 8 else torch.cat([d, d.new_zeros(5 - d.numel())])).tolist(),
        delta_avg_user_px=dl["delta_avg_px"],
        delta_avg_user_interval=intervals[0],
        delta_max_user_px=dl["delta_max_px"],
        delta_max_user_interval=intervals[1],
        invertible_fraction=dl["invertible_fraction"],
        k2_user=k2u,
        k4_user=k4u,
        eq4_fit_error_px=fit_err,
        class_label=label,
        reason=reason,
        registered=rec.num_reg_images(),
        frames=frames or rec.num_reg_images(),
        points3D=rec.num_points3D(),
        observations=observations,
        reprojection_px=table[best]["reprojection_px"],
        models=table,
        jackknife=fits[best].get("jackknife", []),
        rotation_spread_deg=rotation_spread_deg(rec),
        paper_delta_avg_px=dc,
        dispersion=spread,
    )
