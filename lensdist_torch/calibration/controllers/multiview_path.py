"""The multi-view path of ``lensdist calibrate``, and how its answer and the direct one combine.

:func:`multiview_path` hands at most ``multiview.mapped_frames`` frames, evenly spaced over the
sequence, of a folder (as they are) or of a video (written once as lossless grey PNG into a
temporary folder) to COLMAP (:mod:`~lensdist_torch.calibration.multiview`;
``multiview.reconstructions`` mappings, each self-calibrated, combined by
:mod:`~lensdist_torch.calibration.multiview_runs`) and returns a strict-JSON-ready dict, or the
reason it has no answer (no mapping registered enough frames). The homography model
(:func:`planar_path`) runs on a copy of the matches beside the mapping, which COLMAP runs on one
thread. Every path is one candidate in
one comparison: the direct path's camera and the homography model's (:func:`held_answers`) are
held on COLMAP's tracks beside its models and scored on the same held-out frames, and
:func:`combine` makes that comparison's answer the one of
:func:`~lensdist_torch.calibration.controllers.calibrate.calibrate_path`; without a
reconstruction, the more precise of the direct path and the homography model answers.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from tqdm import tqdm

from lensdist_torch.calibration.guided_matching import self_calibrate_guided
from lensdist_torch.calibration.multiview import pycolmap_or_error, reconstruct, self_calibrate_reconstruction
from lensdist_torch.calibration.multiview_runs import combine_reconstructions
from lensdist_torch.calibration.planar_features import PLANAR_MIN_INLIER_SHARE
from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.frames import list_frames, read_frames
from lensdist_torch.core.images import load_image
from lensdist_torch.core.png import encode_png, to_uint8

__all__ = ["MIN_REGISTERED", "PLANAR_MAX_RELIEF_Z", "HELD_PATHS", "COLMAP_SUFFIXES", "evenly_spaced",
           "multiview_path", "planar_path", "held_answers", "combine"]

#: Image files COLMAP reads as they are; other frames are written as PNG first.
COLMAP_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
#: the fewest frames a multi-view calibration takes
MIN_FRAMES = 3
#: Fewer registered frames than this share of the frames (or than :data:`MIN_FRAMES`): "cannot tell" (the engine
#: could not reconstruct the sequence).
MIN_REGISTERED = 0.5
#: The homography model answers only where the direct path's plane + parallax test finds no relief beyond this z
#: (``relief_z``): under one homography per pair a scene's relief passes for distortion (docs/method.md, 12).
PLANAR_MAX_RELIEF_Z = 2.0
#: The paths whose answers :func:`held_answers` holds on COLMAP's tracks, as the multi-view comparison names them.
HELD_PATHS = ("direct", "planar")


def _encode(frame: torch.Tensor) -> bytes:
    return encode_png(to_uint8(frame[0]))


def evenly_spaced(n: int, most: int) -> list[int]:
    """Indices of at most ``most`` of ``n`` frames, evenly spaced, the first and the last included.

    Example:
        >>> evenly_spaced(300, 5), evenly_spaced(4, 5)
        ([0, 75, 150, 224, 299], [0, 1, 2, 3])
    """
    if n <= most:
        return list(range(n))
    return [round(i * (n - 1) / (most - 1)) for i in range(most)]


def multiview_path(path: str | Path, image_size: tuple[int, int], *, config: MultiViewConfig | None = None,
                   settings: LensdistConfig | None = None, max_frames: int | None = 300, quiet: bool = True,
                   direct: dict | Callable[[], dict] | None = None, idle: threading.Event | None = None) -> dict:
    """The multi-view calibration of a folder of frames or a video, as a dict (module docstring).

    Args:
        path: a folder of frames or a video (already read once by the caller, who knows their size).
        image_size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        settings: the library's config (the class rule).
        max_frames: at most this many frames (None: all), of which ``multiview.mapped_frames`` evenly
            spaced (:func:`evenly_spaced`) go to COLMAP.
        quiet: no progress bar (its stages: features and matches, each mapping, each model).
        direct: the direct path's answer (``calibrate_path``'s dict), or a function that returns it
            once the mapping is done (the direct path then runs beside the features and the mapping),
            held on the tracks beside COLMAP's models with the homography model's
            (:func:`held_answers`); None: COLMAP's models and the homography model's.
        idle: set while COLMAP leaves one of its ``num_threads`` cores idle (its matching, its
            mapping once the homography model beside it is done), cleared while it takes them
            all: work beside it (the direct path) may run while it is set.

    Returns:
        A dict with ``ok`` (False: ``reason`` says why there is no answer) and, when ok, the
        fields of :class:`~lensdist_torch.calibration.multiview.MultiViewCalibration`.
    """
    cfg = or_defaults(config, MultiViewConfig)
    try:
        pycolmap_or_error()
    except ValueError as exc:
        return {"ok": False, "reason": str(exc)}
    path = Path(path)
    with tempfile.TemporaryDirectory(prefix="lensdist-frames-") as tmp:
        files = list_frames(path) if path.is_dir() else []
        if files and all(p.suffix.lower() in COLMAP_SUFFIXES for p in files):
            files = files[: max_frames or len(files)]
            folder, names = path, [files[i].name for i in evenly_spaced(len(files), cfg.mapped_frames)]
        else:  # a video, whose length is known once read: every stride-th frame is written, the stride
            folder, kept, stride = Path(tmp), [], 1  # doubled (every other file removed) past 2 x mapped_frames
            for i, (_, img) in enumerate(read_frames(path, True, max_frames)):
                if i % stride:
                    continue
                (folder / f"{i:06d}.png").write_bytes(_encode(img))
                kept.append(f"{i:06d}.png")
                if len(kept) > 2 * cfg.mapped_frames:
                    for name in kept[1::2]:
                        (folder / name).unlink()
                    kept, stride = kept[::2], 2 * stride
            names = [kept[i] for i in evenly_spaced(len(kept), cfg.mapped_frames)]
        if len(names) < MIN_FRAMES:
            return {
                "ok": False,
                "reason": f"the multi-view calibration needs at least {MIN_FRAMES} frames, got {len(names)}",
            }
        least = max(MIN_FRAMES, math.ceil(MIN_REGISTERED * len(names)))
        runs, got, planar = [], 0, {}  # planar: the homography model's future, once the matches are in

        def homography_model(database: Path) -> None:  # the same matches, beside the mapping (it runs on one thread)
            bar.update(1)
            if cfg.planar_terms:
                own = Path(tmp) / "homography.db"  # its own copy: the mapping's goes when the mappings end
                shutil.copyfile(database, own)
                planar["future"] = pool.submit(
                    planar_path, own, names, image_size, config=cfg, settings=settings, folder=folder
                )
                planar["future"].add_done_callback(lambda _: stage(*running))
            bar.set_postfix_str("mapping and the homography model")

        running = ["features", cfg.num_threads]  # COLMAP's stage now, and its threads

        def stage(name: str, threads: int) -> None:  # a core left idle: work beside may run
            running[:] = [name, threads]
            beside = "future" in planar and not planar["future"].done()
            if idle is not None:
                (idle.set if threads + beside < cfg.num_threads else idle.clear)()

        def homography_answer() -> dict | None:
            return planar["future"].result() if "future" in planar else None

        def take(i: int, rec) -> bool:  # one mapping's answer; True: enough mappings succeeded
            nonlocal got
            n = 0 if rec is None else rec.num_reg_images()
            got = max(got, n)
            if n < least:
                runs.append((cfg.seed + i, f"{n} of {len(names)} frames registered"))
            elif rec.num_points3D() == 0:
                runs.append((cfg.seed + i, f"{n} of {len(names)} frames registered, but no 3-D point kept"))
            else:
                bar.update(1)
                bar.set_postfix_str(f"{n} of {len(names)} frames registered, models")
                runs.append((cfg.seed + i, self_calibrate_reconstruction(
                    rec, cfg, settings, frames=len(names), image_size=tuple(image_size), on_model=model_done,
                    others=held_answers(direct() if callable(direct) else direct, homography_answer()))))
                return sum(not isinstance(r, str) for _, r in runs) >= cfg.reconstructions
            bar.total += 1  # a failed mapping: another seed (reconstruct's EXTRA_MAPPINGS)
            bar.update(1)
            return False

        def model_done(model: str) -> None:
            bar.update(1)
            bar.set_postfix_str(f"{model} fitted")

        stages = 1 + cfg.reconstructions * (1 + len(cfg.models))  # features and matches, then per mapping
        with tqdm(
            total=stages, disable=quiet, desc=f"multi-view, {len(names)} frames", unit="stage", leave=False
        ) as bar, ThreadPoolExecutor(1) as pool:
            bar.set_postfix_str("features and matches")
            reconstruct(folder, names, config=cfg, stop=take, image_size=tuple(image_size), on_matches=homography_model,
                        on_stage=stage)
            homography = homography_answer()
        if all(isinstance(r, str) for _, r in runs):
            tries = f" in any of {len(runs)} reconstructions" if len(runs) > 1 else ""
            return {
                "ok": False,
                "reason": f"the engine could not reconstruct the sequence: {got} of {len(names)} frames "
                f"registered at most{tries} (at least {least} needed)",
                "planar": homography,
                "planar_max_relief_z": PLANAR_MAX_RELIEF_Z,
            }
        res = combine_reconstructions(runs, cfg, settings=settings)
    return {"ok": True, **res.to_dict(), "planar": homography, "planar_max_relief_z": PLANAR_MAX_RELIEF_Z}


def planar_path(database: Path, names: list[str], image_size: tuple[int, int], *, config: MultiViewConfig,
                settings: LensdistConfig | None, folder: Path | None = None) -> dict:
    """The homography model on a COLMAP database (its verified matches, then guided and refined ones), as a dict.

    ``folder`` holds the frames ``names`` (the refinement reads them; None: no refinement).
    ``ok`` False with a ``reason`` where it has no answer (too few pairs of matches); otherwise ``plane``
    (False: "not a plane", no estimate for :func:`combine`) and the
    fields of :class:`~lensdist_torch.calibration.planar_features.PlanarCalibration` (strict-JSON-ready).
    """
    images = None if folder is None else (lambda v: load_image(Path(folder) / names[v], max_pixels=None)[0, 0])
    res = self_calibrate_guided(database, names, image_size, config=config, settings=settings, images=images)
    if not math.isfinite(res.delta_avg_user_px):
        return {"ok": False, "reason": res.reason}
    return {"ok": True, "plane": res.inlier_share >= PLANAR_MIN_INLIER_SHARE, **res.to_dict()}


def _overlap(a: tuple, b: tuple) -> bool:
    return a[0] <= b[1] and b[0] <= a[1]


def _take_multiview(out: dict, mv: dict) -> None:
    """``out`` gets the COLMAP model's lens: eq. 4's fit, its camera as the exact OpenCV export (:func:`combine`).

    COLMAP's models are OpenCV's; :func:`combine` adds the comparison's numbers and class.
    """
    exact = {"camera_matrix": mv["camera_matrix"], "dist_coeffs": mv["dist_coeffs"], "fit_error_mean_px": 0.0,
             "fit_error_max_px": 0.0, "forward_error_mean_px": 0.0, "forward_error_max_px": 0.0}
    out.update({k: mv[k] for k in ("k2_user", "k4_user", "invertible_fraction", "eq4_fit_error_px")})
    out.update(camera_model=mv["model"], opencv=exact if len(mv["dist_coeffs"]) == 5 else None,
               opencv_rational=exact if len(mv["dist_coeffs"]) == 8 else None)


def _summary(res: dict, keys: tuple[str, ...]) -> dict:
    return {k: res.get(k) for k in keys}


_KEYS = (
    "class",
    "reason",
    "delta_avg_user_px",
    "delta_avg_user_interval",
    "delta_max_user_px",
    "delta_max_user_interval",
)


def held_answers(direct: dict | None, planar: dict | None) -> dict[str, dict]:
    """The direct path's and the homography model's answers as cameras to hold on COLMAP's tracks.

    What :func:`~lensdist_torch.calibration.multiview.self_calibrate_reconstruction` takes as
    ``others``: per path (:data:`HELD_PATHS`) its OpenCV camera (the 8 rational coefficients where
    exported, else the 5), Delta_avg and Delta_max with their intervals. A path without a finite
    answer or an OpenCV camera is left out.

    Example:
        >>> cam = {"camera_matrix": [[200.0, 0, 99.5], [0, 200.0, 74.5], [0, 0, 1]], "dist_coeffs": [-0.1, 0, 0, 0, 0]}
        >>> d = {"delta_avg_user_px": 3.0, "delta_avg_user_interval": [2.0, 4.0], "delta_max_user_px": 9.0,
        ...      "delta_max_user_interval": [7.0, 11.0], "opencv": cam, "opencv_rational": None}
        >>> sorted(held_answers(d, None)), held_answers(d, {"ok": False, "reason": "too few pairs"}).keys()
        (['direct'], dict_keys(['direct']))
    """
    out = {}
    for name, res in zip(HELD_PATHS, (direct, planar)):
        if res is None or not res.get("ok", True):
            continue
        cam = res.get("opencv_rational") or res.get("opencv")
        values = [res.get(k) for k in ("delta_avg_user_px", "delta_max_user_px")]
        if cam is None or not all(v is not None and math.isfinite(v) for v in values):
            continue
        out[name] = {"camera_matrix": cam["camera_matrix"], "dist_coeffs": cam["dist_coeffs"],
                     "invertible_fraction": res.get("invertible_fraction", 1.0),
                     **{k: res.get(k) for k in _KEYS[2:]}}
    return out


def combine(direct: dict, mv: dict | None) -> dict:
    """One answer from the direct result (``calibrate_path``'s dict) and the multi-view one (or None).

    Where COLMAP reconstructed the sequence, the multi-view answer is the answer: its comparison
    held the direct path's and the homography model's cameras on the tracks beside COLMAP's
    models (:func:`held_answers`), and the candidate that predicts the held-out frames best
    answers, with the interval of all of them mixed by their evidence (docs/method.md, section 11).
    ``method`` names the path whose camera won: "multiview" (a COLMAP model), "direct" or
    "planar", that path's own numbers and lens with the comparison's interval and class.

    Where it did not, the direct path and the homography model remain, and no held-out frames
    weigh them: the more precise of those whose scene model holds answers (the homography model
    where it found a plane and the direct path's plane + parallax test no relief beyond
    :data:`PLANAR_MAX_RELIEF_Z`), with its class where the other's interval meets its own, else
    "cannot tell" naming both. Adds ``method``, ``direct``, ``multiview`` and ``planar`` (each
    path's own numbers; None where it did not run).

    Example:
        >>> d = {"class": "2", "reason": None, "delta_avg_user_px": 6.0, "delta_avg_user_interval": [5.0, 7.0],
        ...      "delta_max_user_px": 12.0, "delta_max_user_interval": [10.0, 14.0]}
        >>> out = combine(d, None)
        >>> out["method"], out["class"], out["multiview"]
        ('direct', '2', None)
    """
    out = dict(direct, method="direct")
    out["direct"] = _summary(direct, _KEYS)
    out["multiview"] = None if mv is None else _multiview_view(mv)
    planar = (mv or {}).get("planar")
    out["planar"] = None if planar is None else _planar_view(planar)
    if mv is not None and mv["ok"]:  # the winner's own lens; the comparison's numbers, interval and class
        winner = mv["model"] if mv["model"] in HELD_PATHS else "multiview"
        if winner == "multiview":
            _take_multiview(out, mv)
        elif winner == "planar":
            _take_planar(out, planar)
        out.update({k: mv[k] for k in _KEYS[2:]}, method=winner,
                   **{"class": mv["class_label"], "reason": mv["reason"] or None})
        return out
    found, relief = _estimates(direct, mv)
    if relief:
        out["planar"]["reason"] = relief
    if not found:
        return out
    name = min(found, key=lambda n: found[n][1] - found[n][0])
    if name == "planar":
        _take_planar(out, planar)
    chosen = found[name]
    apart = [n for n, iv in found.items() if not _overlap(chosen, iv)]
    if apart:
        each = "; ".join(f"{_NAMES[n]} {_path(n, direct, mv)['delta_avg_user_px']:.2f} px [{iv[0]:.2f}, {iv[1]:.2f}]"
                         for n, iv in found.items())
        out.update({"class": None, "reason": f"the paths disagree beyond their intervals ({each}); the numbers are "
                                             f"the {_NAMES[name]} path's, the most precise"})
    return out


#: How the text and the reasons name each path.
_NAMES = {"direct": "direct", "multiview": "multi-view", "planar": "homography model"}


def _path(name: str, direct: dict, mv: dict | None) -> dict:
    return {"direct": direct, "multiview": mv, "planar": (mv or {}).get("planar")}[name]


def _estimates(direct: dict, mv: dict | None) -> tuple[dict[str, tuple[float, float]], str]:
    """Each path's Delta_avg interval in the user's pixels, where its scene model holds (:func:`combine`).

    And why the homography model does not count where it found a plane but the direct path's plane +
    parallax test found relief, or could not run ("" otherwise): relief imitates distortion under
    one homography per pair (docs/method.md, section 12).
    """
    z, most = direct.get("relief_z"), (mv or {}).get("planar_max_relief_z", math.inf)
    measured = z is not None and math.isfinite(z)
    found, relief = {}, ""
    for name in _NAMES:
        res = _path(name, direct, mv)
        if res is None or not res.get("ok", True) or (name == "planar" and not res.get("plane", True)):
            continue
        if name == "planar" and not (measured and z <= most):
            relief = "relief: the direct path's plane + parallax test " + (
                f"finds relief (z = {z:.1f}, at most {most:g})" if measured else "could not run")
            continue
        iv = res.get("delta_avg_user_interval")
        if iv is not None and None not in iv and all(math.isfinite(v) for v in iv):
            found[name] = (float(iv[0]), float(iv[1]))
    return found, relief


def _multiview_view(mv: dict) -> dict:
    """The multi-view path's own numbers, as the JSON's ``multiview`` block."""
    if not mv["ok"]:
        return {"reason": mv["reason"]}
    return {
        "class": mv["class_label"],
        "reason": mv["reason"] or None,
        "model": mv["model"],
        **{k: mv[k] for k in _KEYS[2:]},
        **{k: mv[k] for k in ("invertible_fraction", "eq4_fit_error_px", "registered", "points3D", "observations",
                              "reprojection_px", "rotation_spread_deg", "camera_matrix", "dist_coeffs", "models")},
        "reconstructions": list(mv.get("reconstructions", ())),
        "reconstruction_spread_px": mv.get("reconstruction_spread_px", 0.0),
        "dispersion": mv.get("dispersion", 1.0),
    }


#: The homography model's fields in the JSON's ``planar`` block, beside :data:`_KEYS`.
_PLANAR_KEYS = ("pairs", "inliers", "matches", "inlier_share", "reprojection_px", "models", "jackknife", "dispersion",
                "coefficients", "model", "centre",
                "bending_halfwidth_px", "matched_fraction", "invertible_fraction", "eq4_fit_error_px", "opencv",
                "opencv_rational")


def _planar_view(planar: dict) -> dict:
    """The homography model's own numbers, as the JSON's ``planar`` block."""
    if not planar["ok"]:
        return {"reason": planar["reason"]}
    return {"class": planar["class_label"], "reason": planar["reason"] or None, "terms": planar["terms"],
            **{k: planar[k] for k in (*_KEYS[2:], *_PLANAR_KEYS)},
            "guided": planar.get("guided"), "refined": planar.get("refined")}


def _take_planar(out: dict, planar: dict) -> None:
    """``out`` gets the homography model's numbers, class and OpenCV exports."""
    out.update({k: planar[k] for k in ("k2_user", "k4_user", *_KEYS[2:], "invertible_fraction", "eq4_fit_error_px")})
    out.update(method="planar", camera_model=planar["model"], opencv=planar["opencv"],
               opencv_rational=planar["opencv_rational"], **{"class": planar["class_label"],
                                                             "reason": planar["reason"] or None})
