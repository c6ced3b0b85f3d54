"""Undistort the frames of a folder or a video: ``lensdist undistort`` (docs/method.md, section 6).

``undistort_path(path, out_dir, k2=, k4=)`` (or ``from_json=`` a saved calibration) writes every
corrected frame as a PNG (grey or colour, as the input) and its validity mask in
``out_dir/masks/``. The contract, checked before anything is written:

- **Coefficients.** Given as numbers (finite; a bool is not a number) or read from the JSON of
  ``lensdist calibrate`` or ``lensdist analyze --json``: ``k2_user``, ``k4_user``, the frame size
  and every field that could contradict them (the class, the verification, OpenCV's camera) are
  checked by :mod:`~lensdist_torch.calibration.controllers.answer_file`; each bad field is a one-line
  error naming the file and the field. Pixels that eq. 4 folds over
  (past the monotone branch of its radius, :func:`~lensdist_torch.geometry.undistort.monotone_branch`)
  are 0 in the mask and in the image. Coefficients that fold before the nearest edge of the frame
  are refused: no lens does that, it is most often coefficients in another unit. So are
  coefficients whose radial stretch 1 + k2 r^2 + k4 r^4 exceeds ``MAX_STRETCH`` inside the frame
  (largest at the farthest corner unless k4 < 0): the ideal image would be that many times the
  frame (``--k2=1e-3`` at 320 x 424: 71 times), and the output a silent zoom on its centre.
- **The lens.** Where the ``--from`` answer's lens is not eq. 4 (``lensdist calibrate``'s
  ``method`` "planar": the homography model's, up to three radial terms about its own
  distortion centre; "multiview": COLMAP's OpenCV camera), that lens is applied
  (:func:`~lensdist_torch.geometry.undistort.lens_undistortion_grid`,
  :func:`~lensdist_torch.geometry.undistort.opencv_undistortion_grid`), not eq. 4's
  ``k2_user``, ``k4_user``, which only approximate it (``eq4_fit_error_px``); the same checks
  (folding before the nearest edge, the stretch at the corners) and views hold for it.
- **Names.** Frame ``NAME.EXT`` is written as ``NAME.png`` (a video's frames as
  ``frame_000000.png`` ...). Two inputs with one stem (``frame_01.png`` and ``frame_01.jpg``, or
  names that differ only in letter case) are refused: one would overwrite the other.
- **Nothing destroyed.** The output folder may not be the input folder, and no output may be one
  of the inputs (a frame, the video, the calibration file), even with ``overwrite``. An existing
  file of a name it would write (for a video: any ``frame_NNNNNN.png``) is refused unless
  ``overwrite=True`` (``--overwrite``).
- **Nothing half-written.** The frames and masks are written into a staging folder beside
  ``out_dir`` (:func:`~lensdist_torch.core.storage.staged_folder`) and move into it only once
  every frame is written; a frame that cannot be read leaves ``out_dir`` as it was, and the rerun
  after fixing it needs no ``overwrite``.
- **Output size.** The frames keep their size. ``alpha`` None (the default, as before) keeps the
  input's scale and centre (``cv2.undistort``'s default: barrel distortion loses the frame's
  edges, pincushion leaves its corners empty); 0 to 1 chooses the view as OpenCV's
  ``getOptimalNewCameraMatrix`` does (:func:`~lensdist_torch.geometry.undistort.optimal_view`):
  0 only valid pixels, 1 every source pixel kept, in between interpolated.
- **The camera.** ``OUT/undistortion.json`` (written last, atomically) holds what was applied:
  eq. 4's k2, k4 in the frames' pixels (``lens`` and ``applied`` say when the answer's own lens was
  applied instead: then OpenCV's camera is the multi-view path's, or the rational fit to the
  homography model's lens), alpha, the input and output sizes, the view, and the
  OpenCV equivalent: ``camera_matrix`` and ``dist_coeffs`` (the standard model fitted to eq. 4,
  :func:`~lensdist_torch.geometry.opencv_model.opencv_export`; the focal length of the
  ``--from`` calibration's, else the half diagonal) and ``new_camera_matrix``, the camera of the
  undistorted frames (``cv2.undistort(frame, camera_matrix, dist_coeffs,
  newCameraMatrix=new_camera_matrix)`` gives the same frames to OpenCV's model fit).
- **Bit depth.** A frame read from a file with more than 8 bits a sample (a 16-bit PNG; a 16-bit
  or float TIFF whose samples are finer than 8 bits) is written as a 16-bit PNG, every other frame
  as an 8-bit one; the masks are 8-bit (0 or 255).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import torch

from lensdist_torch.calibration.controllers.answer_file import Calibration, read_calibration
from lensdist_torch.calibration.controllers.answer_lens import (
    eq4_lens,
    lens_grid,
    lens_ideal,
    lens_view,
    radial_lens_opencv,
    scale_lens,
)
from lensdist_torch.core.frames import frames_of_one_size, list_frames
from lensdist_torch.core.outputs import refuse_data_sets
from lensdist_torch.core.png import deep_samples, encode_png, to_uint8, to_uint16
from lensdist_torch.core.storage import atomic_write_text, staged_folder
from lensdist_torch.geometry.distortion import distortion_center, sample_at_pixels
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.opencv_model import opencv_export, radial_monotone
from lensdist_torch.geometry.radial_lens import monotone_radius
from lensdist_torch.geometry.undistort import monotone_branch

__all__ = ["MAX_STRETCH", "undistort_path"]

_VIDEO_NAME = re.compile(r"frame_\d{6}\.png")
CAMERA_FILE = "undistortion.json"

#: The largest radial stretch 1 + k2 r^2 + k4 r^4 (ideal radius / distorted radius) that undistort
#: accepts inside the frame. An equidistant fisheye of half field theta stretches its corner by
#: tan(theta) / theta: 10 is theta = 86 degrees, a 172-degree diagonal field, which eq. 4's two
#: terms cannot describe (a fisheye needs another model). The protocol's strongest lens stretches
#: by 1.30 at 320 x 424; a wide action-camera lens fitted by eq. 4, about twice.
MAX_STRETCH = 10.0


# ------------------------------------------------------------------ coefficients
def _coefficients_for(size: tuple[int, int], k2, k4, from_json, cal: Calibration | None = None) -> tuple[float, float]:
    """(k2, k4) for frames of ``size``: given, or from the JSON (/ s^2, / s^4 for frames scaled by s).

    ``cal``: ``from_json`` already read (:func:`read_calibration`), so that it is read once.
    """
    if from_json is None:
        if k2 is None and k4 is None:
            raise ValueError("give `k2` or `k4` (the other is 0), or `from_json`")
        k2, k4 = 0.0 if k2 is None else k2, 0.0 if k4 is None else k4
        for name, value in (("k2", k2), ("k4", k4)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"`{name}` must be a finite number, got {value!r}")
        return float(k2), float(k4)
    if k2 is not None or k4 is not None:
        raise ValueError("give the coefficients (`k2`, `k4`) or `from_json`, not both")
    src = Path(from_json)
    cal = read_calibration(src) if cal is None else cal
    k2, k4, hc, wc, reason = cal.k2, cal.k4, cal.height, cal.width, cal.reason
    if k2 is None:
        raise ValueError(f"{src} holds no estimate: {' '.join(reason.split())}")
    s = size[1] / wc
    if abs(size[0] / hc - s) > 5e-3 * s:
        raise ValueError(
            f"frames are {size[0]} x {size[1]}, the calibration in {src.name} is for {hc} x {wc}: not a rescaling"
        )
    return k2 / s**2, k4 / s**4


def _lens_for(size: tuple[int, int], cal: Calibration | None) -> dict | None:
    """The ``--from`` answer's own lens for frames of ``size`` (None: eq. 4 is the answer)."""
    return None if cal is None or cal.lens is None else scale_lens(cal.lens, size[1] / cal.width)


def _check_lens(lens: dict, height: int, width: int, from_json) -> None:
    """Refuse a lens that folds before the frame's nearest edge or stretches it past ``MAX_STRETCH`` (module docstring).

    Eq. 4 by :func:`_check_fold` and :func:`_check_stretch`; the answer's own lens the same way.
    """
    if lens["kind"] == "eq4":
        _check_fold(lens["k2"], lens["k4"], height, width, from_json)
        _check_stretch(lens["k2"], lens["k4"], height, width, from_json)
        return
    big_r = half_diagonal(height, width)
    if lens["kind"] == "radial":
        a, (cx, cy) = torch.tensor(lens["coefficients"], dtype=torch.float64), lens["centre"]
        what = f"the lens of {from_json} (planar.coefficients {[round(float(v), 4) for v in a]})"
        top = monotone_radius(a) * big_r  # px from the centre where the radius stops increasing
    else:
        k, d = (
            torch.tensor(lens["camera_matrix"], dtype=torch.float64),
            torch.tensor(lens["dist_coeffs"], dtype=torch.float64),
        )
        (cx, cy), f = k[:2, 2].tolist(), float(k[0, 0] + k[1, 1]) / 2
        what = f"the camera of {from_json} (dist_coeffs {[round(float(v), 4) for v in d]})"
        r = torch.linspace(0.0, 2 * big_r / f, 2001, dtype=torch.float64)  # ideal radii, normalised by f
        folds = (~radial_monotone(r * r, d)).nonzero()
        top = math.inf if not len(folds) else float(r[int(folds[0, 0])]) * f
    edge = min(cx, cy, width - 1 - cx, height - 1 - cy)
    if top <= edge:
        raise ValueError(f"{what} folds (its radius stops increasing) {top:.1f} px from its centre, inside the "
                         f"{height} x {width} frames: no lens does that")
    corners = torch.tensor([[x, y] for x in (0.0, width - 1.0) for y in (0.0, height - 1.0)], dtype=torch.float64)
    ideal, ok = lens_ideal(lens, corners, height, width)
    c = torch.tensor([cx, cy], dtype=torch.float64)
    stretch = float(((ideal - c).norm(dim=-1) / (corners - c).norm(dim=-1))[ok].max()) if bool(ok.any()) else 1.0
    if stretch > MAX_STRETCH:
        raise ValueError(
            f"{what} stretches the {height} x {width} frames {stretch:.3g}-fold at a corner, expected at most "
            f"{MAX_STRETCH:g}: no lens that it describes (a fisheye needs another model)"
        )


def _focal_for(size: tuple[int, int], cal: Calibration | None) -> float | None:
    """The OpenCV focal length of a ``--from`` calibration in the frames' pixels (None: none there)."""
    if cal is None or cal.focal is None:
        return None
    return cal.focal * size[1] / cal.width


def _check_fold(k2: float, k4: float, height: int, width: int, from_json) -> None:
    """Refuse coefficients whose eq. 4 folds before the nearest edge of the frame (module docstring)."""
    edge = min(distortion_center(height, width))  # p0 to the nearest edge pixel centre
    if bool(monotone_branch(torch.tensor(edge * edge, dtype=torch.float64), k2, k4)):
        return
    what = f"the coefficients of {from_json} (k2_user, k4_user)" if from_json is not None else "--k2/--k4"
    raise ValueError(f"{what} k2 = {k2:.4g}, k4 = {k4:.4g} make eq. 4 fold (its radius stops increasing) less than "
                     f"{edge:.1f} px from the centre, inside the {height} x {width} frames: no lens does that; "
                     "give the coefficients in the frames' own pixels")


def _check_stretch(k2: float, k4: float, height: int, width: int, from_json) -> None:
    """Refuse coefficients whose radial stretch exceeds ``MAX_STRETCH`` inside the frame (module docstring)."""
    top = math.hypot(*distortion_center(height, width)) ** 2  # r^2 at the farthest corner pixel centre
    # 1 + k2 s + k4 s^2 on [0, top], s = r^2: largest at the corner or, where k4 < 0, at its vertex
    s2 = min(max(-k2 / (2 * k4), 0.0), top) if k4 < 0 else top
    stretch = 1 + k2 * s2 + k4 * s2 * s2
    if stretch <= MAX_STRETCH:
        return
    what = f"the coefficients of {from_json} (k2_user, k4_user)" if from_json is not None else "--k2/--k4"
    where = "the farthest corner" if s2 == top else "inside"
    raise ValueError(f"{what} k2 = {k2:.4g}, k4 = {k4:.4g} stretch the {height} x {width} frames {stretch:.3g}-fold "
                     f"(1 + k2 r^2 + k4 r^4 at r = {math.sqrt(s2):.1f} px, {where}), expected at most {MAX_STRETCH:g}: "
                     "no lens that eq. 4 describes (a fisheye needs another model); give the coefficients in the "
                     "frames' own pixels")


# ------------------------------------------------------------------ the outputs
def _plan(path: Path, out: Path, max_frames: int | None, from_json, overwrite: bool) -> list[Path] | None:
    """The input files of a folder (None for a video), once every output was checked (module docstring)."""
    if path.is_dir() and out.resolve() == path.resolve():
        raise ValueError(f"`out_dir` must differ from the input folder {path}")
    refuse_data_sets(out, "`out_dir`", out)
    files = list_frames(path)[:max_frames] if path.is_dir() else None
    names = [p.stem for p in files] if files is not None else None
    if names is not None:
        seen: dict[str, Path] = {}
        for p in files:
            if p.stem.lower() in seen:
                raise ValueError(f"{seen[p.stem.lower()].name} and {p.name} would both be written as {p.stem}.png; "
                                 "rename one of them or move it out of the folder")
            seen[p.stem.lower()] = p
    protected = {p.resolve() for p in (files or [path])} | (
        {Path(from_json).resolve()} if from_json is not None else set()
    )
    if out.exists() and not out.is_dir():
        raise ValueError(f"`out_dir` {out} exists and is not a folder")
    for folder in (out, out / "masks"):
        if not folder.is_dir():
            continue
        for existing in folder.iterdir():
            mine = (existing.stem.lower() in {n.lower() for n in names} and existing.suffix.lower() == ".png"
                    if names is not None else bool(_VIDEO_NAME.fullmatch(existing.name)))
            mine = mine or (folder == out and existing.name.lower() == CAMERA_FILE)
            if not mine:
                continue
            if existing.resolve() in protected:
                raise ValueError(f"{existing} is one of the inputs; choose another `out_dir`")
            if not overwrite:
                raise ValueError(f"{existing} exists; choose an empty `out_dir` or pass `overwrite=True` "
                                 "to replace what a previous run wrote")
    return files


def undistort_path(
    path: str | Path,
    out_dir: str | Path,
    *,
    k2: float | None = None,
    k4: float | None = None,
    from_json: str | Path | None = None,
    max_frames: int | None = None,
    quiet: bool = True,
    device: torch.device | str | None = None,
    overwrite: bool = False,
    alpha: float | None = None,
) -> dict:
    """Undistort every frame of a folder or video into ``out_dir`` (PNG), masks in ``out_dir/masks``.

    A mask is 255 where the corrected pixel came from inside the frame on the lens's monotone
    branch (eq. 4's, or the ``from_json`` answer's own lens), 0 elsewhere. What is refused, the
    names, the output size, ``undistortion.json`` and the bit depth: the module docstring.

    Args:
        path: a folder of images or a video.
        out_dir: the output folder (created; not the input folder).
        k2: eq. 4's k2 in the frames' pixels (0 where only k4 is given; or from_json).
        k4: eq. 4's k4 in the frames' pixels (0 where only k2 is given).
        from_json: instead of k2, k4: the JSON of ``lensdist calibrate`` or ``analyze --json``.
        max_frames: at most this many frames (None: all).
        quiet: no progress bar.
        device: where the frames are resampled (default: the CPU).
        overwrite: replace existing files of the names it writes (never an input).
        alpha: None (the input's scale and centre) or 0 (only valid pixels) to 1 (every source
            pixel kept), as OpenCV's ``getOptimalNewCameraMatrix``.

    Returns:
        dict: frames, out_dir, k2, k4 (as applied, or eq. 4's approximation of ``lens``), lens (the
        answer's own lens where applied, its ``kind`` "radial" or "opencv", else None),
        valid_fraction (mean of the masks), bits (the sample depths written, e.g. [16]), alpha,
        camera (what ``undistortion.json`` holds) and camera_file (its path).

    Example:
        >>> import tempfile
        >>> frame = encode_png(torch.zeros(1, 24, 32, dtype=torch.uint8))  # a 24 x 32 grey PNG
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     (Path(tmp) / "in").mkdir()
        ...     for name in ("a", "b"):
        ...         _ = (Path(tmp) / "in" / f"{name}.png").write_bytes(frame)
        ...     res = undistort_path(Path(tmp) / "in", Path(tmp) / "out", k2=0.0, k4=0.0)
        ...     written = sorted(p.name for p in (Path(tmp) / "out").iterdir())
        >>> res["frames"], res["valid_fraction"], res["bits"], written  # no distortion: every pixel valid
        (2, 1.0, [8], ['a.png', 'b.png', 'masks', 'undistortion.json'])
    """
    path, out = Path(path), Path(out_dir)
    if not path.exists():
        raise FileNotFoundError(f"path not found: {path}")
    if max_frames is not None and (type(max_frames) is not int or max_frames < 1):
        raise ValueError(f"`max_frames` must be a positive int or None, got {max_frames!r}")
    if type(overwrite) is not bool:
        raise TypeError(f"`overwrite` must be a bool, got {overwrite!r}")
    if alpha is not None and (isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0 <= alpha <= 1):
        raise ValueError(f"`alpha` must be a number from 0 to 1 or None, got {alpha!r}")
    # the file read once (what is checked is what is used); every coefficient checked before any frame is read
    cal = read_calibration(Path(from_json)) if from_json is not None and k2 is None and k4 is None else None
    _coefficients_for((1, 1) if cal is None else (cal.height, cal.width), k2, k4, from_json, cal)
    files = _plan(path, out, max_frames, from_json, overwrite)
    grid, n, valid_sum, dev, bits = None, 0, 0.0, torch.device(device or "cpu"), set()
    with staged_folder(out) as stage:  # a frame that fails to read or write: nothing reaches out_dir
        frames = frames_of_one_size(path, grey=False, max_frames=max_frames, quiet=quiet, desc="undistorting")
        for i, (name, img) in enumerate(frames):
            if grid is None:
                size = tuple(img.shape[-2:])
                k2, k4 = _coefficients_for(size, k2, k4, from_json, cal)
                lens = _lens_for(size, cal)  # None: eq. 4 is the answer
                applied = lens or eq4_lens(k2, k4)
                _check_lens(applied, *size, from_json)
                view = None if alpha is None else lens_view(applied, *size, float(alpha))
                grid, valid = lens_grid(applied, *size, view=view)
                camera = _camera(k2, k4, size, _focal_for(size, cal), alpha, view, lens)
                grid, valid = grid.to(dev), valid.to(dev)
                (stage / "masks").mkdir()
            deep = deep_samples(files[i] if files is not None else None, img)
            corrected = (sample_at_pixels(img.to(dev), grid) * valid)[0].cpu()
            (stage / f"{name}.png").write_bytes(encode_png(to_uint16(corrected) if deep else to_uint8(corrected)))
            (stage / "masks" / f"{name}.png").write_bytes(encode_png(to_uint8(valid[0]).cpu()))
            n, valid_sum, bits = n + 1, valid_sum + float(valid.mean()), bits | {16 if deep else 8}
        if n == 0:
            raise ValueError(f"path {path} holds no frames")
    camera["frames"], camera["valid_fraction"] = n, valid_sum / n
    atomic_write_text(out / CAMERA_FILE, json.dumps(camera, indent=2, allow_nan=False) + "\n")
    return {
        "frames": n,
        "out_dir": str(out),
        "k2": k2,
        "k4": k4,
        "lens": camera["lens"],
        "valid_fraction": valid_sum / n,
        "bits": sorted(bits),
        "alpha": alpha,
        "camera": camera,
        "camera_file": str(out / CAMERA_FILE),
    }


def _camera(k2: float, k4: float, size: tuple[int, int], focal: float | None, alpha, view, lens=None) -> dict:
    """What ``undistortion.json`` holds (module docstring): eq. 4 or the lens applied, the view and OpenCV's cameras.

    With the answer's own ``lens`` (:func:`_lens_for`): ``lens`` and ``applied`` name it (``k2``,
    ``k4`` are then its eq. 4 approximation, not applied); OpenCV's camera is the multi-view
    path's own, or fitted to the homography model's map about its centre, the rational model (8
    coefficients: the 5 of the standard one cannot follow a lens that strong).
    """
    h, w = size
    if lens is None:
        cv, model = opencv_export(k2, k4, h, w, focal=focal, model="standard"), "standard"
    elif lens["kind"] == "radial":
        cv, model = radial_lens_opencv(lens, h, w, focal=focal, model="rational"), "rational"
    else:  # the camera itself: exact
        cv = {"camera_matrix": lens["camera_matrix"], "dist_coeffs": lens["dist_coeffs"], "fit_error_mean_px": 0.0,
              "fit_error_max_px": 0.0}
        model = "rational" if len(lens["dist_coeffs"]) == 8 else "standard"
    sx, sy, tx, ty = (1.0, 1.0, 0.0, 0.0) if view is None else view
    (f, _, cx), (_, _, cy) = cv["camera_matrix"][0], cv["camera_matrix"][1]
    new = [[sx * f, 0.0, sx * cx + tx], [0.0, sy * f, sy * cy + ty], [0.0, 0.0, 1.0]]
    applied = ("eq. 4" if lens is None else "the homography model's lens" if lens["kind"] == "radial" else
               "the multi-view path's camera")
    return {"k2": k2, "k4": k4, "lens": lens, "applied": applied, "alpha": alpha,
            "input_size": [h, w], "output_size": [h, w],
            "view": {"sx": sx, "sy": sy, "tx": tx, "ty": ty}, "camera_matrix": cv["camera_matrix"],
            "dist_coeffs": cv["dist_coeffs"], "new_camera_matrix": new, "opencv_model": model,
            "opencv_fit_error_mean_px": cv["fit_error_mean_px"], "opencv_fit_error_max_px": cv["fit_error_max_px"]}
