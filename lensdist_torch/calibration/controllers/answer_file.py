"""A calibration's answer file: how ``lensdist calibrate`` writes it, what ``undistort --from`` reads back.

:func:`answer_text` is the answer as JSON (what ``--json`` prints) and :func:`write_answer` writes
it as ``calibration.json``, atomically; :func:`read_calibration` reads and checks it.

FILE is the JSON of ``lensdist calibrate`` (``--out``'s calibration.json, or ``--json``) or of
``lensdist analyze --json`` (the self-calibration's answer). Undistorting needs eq. 4's
``k2_user`` and ``k4_user`` (the frames' pixels) and the frame size they are for (calibrate's
``image_size``, analyze's ``input_size``); the OpenCV export also takes the focal length of
``opencv.camera_matrix``. Each is checked, and so is every field that could contradict them;
each problem is one ValueError naming the file and the field:

- ``k2_user``, ``k4_user``: finite numbers, or both null (no estimate); the size: two positive
  integers (``image_size`` and ``input_size`` agree where both are given), and analyze's
  ``analysed_region_user_px`` a box inside it;
- ``class``: present (both commands write it), one of ``CLASS_LABELS`` or null. Null with
  numbers is "could not tell": refused, with the ``--k2 --k4`` that use them anyway. A class
  must be the one its coefficients give: Delta_avg at the paper's frame of the same normalised
  lens (:func:`~lensdist_torch.geometry.distortion.paper_frame_delta_avg`) within
  ``FROM_CLASS_TOLERANCE`` of the class's bounds (the default classes; R's bound is the
  producer's default, a sequence's ``sequence_class.NO_DISTORTION_PX`` or one pair's
  ``analysis.no_distortion_px``: either is accepted);
- ``verification`` (calibrate): null, or :func:`~lensdist_torch.calibration.controllers.verify.verify_undistortion`'s
  counts with their shares and the verdict that follows from them
  (:func:`~lensdist_torch.calibration.controllers.verify.verdict`); there is one only for a distortion class,
  and "not lowered" withholds the class;
- ``opencv``: null or absent, or a ``camera_matrix`` [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] of
  positive focal lengths with its principal point inside the frame;
- the answer's own lens, where eq. 4 only approximates it (``eq4_fit_error_px`` says how far,
  in px RMS over the frame). Where the homography model answered (calibrate's
  ``method`` "planar"): ``planar.coefficients``, one to ``MAX_LENS_TERMS`` finite numbers (the
  normalised radius's, :mod:`~lensdist_torch.geometry.radial_lens`), and ``planar.centre``, (x,
  y) inside the frame. Where the multi-view path answered (``method`` "multiview"): its COLMAP
  camera, ``opencv`` (5 coefficients) or ``opencv_rational`` (8), the one given, its camera
  matrix as above and its coefficients finite. Undistort applies that lens, so its class must be
  the file's: eq. 4 fitted to it over the frame where it inverts (as calibrate fits
  ``k2_user``, ``k4_user``) is checked as the coefficients are.

Fields undistort ignores (Deltas, intervals, warnings ...) are not checked.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple

from lensdist_torch.calibration.controllers.answer_lens import answer_lens, lens_ideal
from lensdist_torch.calibration.controllers.verify import COUNTS, VERDICTS, verdict
from lensdist_torch.calibration.sequence_class import NO_DISTORTION_PX
from lensdist_torch.config import FROM_CLASS_TOLERANCE, LensdistConfig
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.geometry.distortion import CLASS_LABELS, class_bounds, fit_eq4, paper_frame_delta_avg
from lensdist_torch.geometry.opencv_model import grid_points, map_grid_step

__all__ = ["ANSWER_FILE", "Calibration", "MAX_LENS_TERMS", "answer_text", "read_calibration", "write_answer"]

#: the file name of a calibration's answer in ``lensdist calibrate --out DIR``
ANSWER_FILE = "calibration.json"


def answer_text(answer: dict) -> str:
    r"""The answer of :func:`~lensdist_torch.calibration.controllers.calibrate.calibrate_path` as strict JSON.

    Example:
        >>> answer_text({"class": None, "delta_avg_user_px": 1.5})
        '{\n  "class": null,\n  "delta_avg_user_px": 1.5\n}'
    """
    return json.dumps(answer, indent=2, allow_nan=False)


def write_answer(answer: dict, folder: str | Path) -> Path:
    r"""Write ``answer`` as ``folder/calibration.json`` (the folder made where missing), atomically; its path.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     write_answer({"class": "2"}, Path(tmp) / "calib").read_text()
        '{\n  "class": "2"\n}\n'
    """
    path = Path(folder) / ANSWER_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, answer_text(answer) + "\n")
    return path


_WHAT = "a calibration written by lensdist calibrate or lensdist analyze --json"

#: The most radial terms a ``--from`` lens may have (the homography model fits up to 3).
MAX_LENS_TERMS = 3


class Calibration(NamedTuple):
    """What a ``--from`` file gives: coefficients (None: no estimate), the frame, why not, OpenCV's focal, the lens.

    ``lens``: the answer's own lens where eq. 4's ``k2``, ``k4`` only approximate it, else None:
    {"kind": "radial", "coefficients", "centre"} (the homography model's) or {"kind": "opencv",
    "camera_matrix", "dist_coeffs"} (the multi-view path's COLMAP camera).
    """

    k2: float | None
    k4: float | None
    height: int
    width: int
    reason: str
    focal: float | None
    lens: dict | None = None


def _number(x: Any) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def _count(x: Any) -> bool:
    return type(x) is int and x >= 0  # type(): a bool is not a count


def _coefficient(data: dict, field: str, src: Path) -> float | None:
    value = data[field]
    if value is not None and not _number(value):
        raise ValueError(f"{src}: field {field!r} must be a finite number, got {value!r:.60}")
    return None if value is None else float(value)


def _size(data: dict, src: Path) -> tuple[int, int]:
    sizes = []
    for field in ("image_size", "input_size"):
        if field not in data:
            continue
        size = data[field]
        if not (isinstance(size, list) and len(size) == 2 and all(type(v) is int and v > 0 for v in size)):
            raise ValueError(f"{src}: field {field!r} must be [height, width], two positive integers, got {size!r:.60}")
        sizes.append(tuple(size))
    if not sizes:
        raise ValueError(f"{src} is not {_WHAT} (no field 'image_size')")
    if len(sizes) == 2 and sizes[0] != sizes[1]:
        raise ValueError(f"{src}: fields 'image_size' {list(sizes[0])} and 'input_size' {list(sizes[1])} disagree")
    return sizes[0]


def _reference(data: dict, size: tuple[int, int], src: Path) -> tuple[int, int]:
    """The frame (user px) whose normalised lens the class was given for: analyze's analysed region, else the frame."""
    box = data.get("analysed_region_user_px")
    if box is None:
        return size
    if not (isinstance(box, list) and len(box) == 4 and all(_count(v) for v in box) and box[2] > 0 and box[3] > 0
            and box[0] + box[2] <= size[0] and box[1] + box[3] <= size[1]):
        raise ValueError(f"{src}: field 'analysed_region_user_px' must be [top, left, height, width] inside the "
                         f"{size[0]} x {size[1]} frame, got {box!r:.60}")
    return box[2], box[3]


def _check_class(label, k2, k4, ref: tuple[int, int], src: Path, what: str | None = None) -> None:
    """Refuse a class that its coefficients do not give (module docstring); ``what`` names them where not the file's."""
    cfg = LensdistConfig()
    dc = paper_frame_delta_avg(k2, k4, ref, cfg)
    ts = sorted({NO_DISTORTION_PX, cfg.analysis.no_distortion_px})  # calibrate's, analyze's R
    lo, hi = class_bounds(label, "delta_avg", cfg, ts[0])[0], class_bounds(label, "delta_avg", cfg, ts[-1])[1]
    if lo * (1 - FROM_CLASS_TOLERANCE) <= dc <= hi * (1 + FROM_CLASS_TOLERANCE):
        return
    bounds = f"below {hi:g} px" if lo == 0 else f"above {lo:.2f} px" if math.isinf(hi) else f"{lo:.2f}-{hi:.2f} px"
    h, w = cfg.image.size
    what = what or f"'k2_user' = {k2:.4g}, 'k4_user' = {k4:.4g}"
    raise ValueError(f"{src}: field 'class' is {label!r}, but {what} give "
                     f"Delta_avg {dc:.2f} px at the paper's {h} x {w} frame (class {label!r}: {bounds}): the file "
                     "contradicts itself")


def _check_verification(data: dict, label, src: Path) -> None:
    """The verification block: well formed, its verdict the one its numbers give, agreeing with the class."""
    check = data.get("verification")
    if check is None:
        return
    if not isinstance(check, dict):
        raise ValueError(f"{src}: field 'verification' must be null or an object, got {check!r:.60}")
    for field in COUNTS:
        if not _count(check.get(field)):
            raise ValueError(f"{src}: field 'verification.{field}' must be an int >= 0, got {check.get(field)!r:.60}")
    for when in ("before", "after"):
        if check[f"registered_{when}"] > check["pairs"] or check[f"error_blocks_{when}"] > check[f"blocks_{when}"]:
            raise ValueError(f"{src}: field 'verification' counts more registered pairs or error blocks {when} than "
                             "pairs or blocks")
        share, blocks = check.get(f"error_share_{when}"), check[f"blocks_{when}"]
        want = check[f"error_blocks_{when}"] / blocks if blocks else None
        if not (share is None and want is None or _number(share) and want is not None and abs(share - want) <= 1e-9):
            raise ValueError(f"{src}: field 'verification.error_share_{when}' must be error_blocks_{when} / "
                             f"blocks_{when} ({want!r}), got {share!r:.60}")
    given = check.get("verdict")
    if given not in VERDICTS:
        raise ValueError(f"{src}: field 'verification.verdict' must be one of {', '.join(map(repr, VERDICTS))}, "
                         f"got {given!r:.60}")
    if given not in (verdict(check), verdict(check, count_gained=False)):  # an earlier file: its rule's verdict stands
        raise ValueError(f"{src}: field 'verification.verdict' is {given!r}, but its shares and counts say "
                         f"{verdict(check)!r}")
    if label == CLASS_LABELS[-1] or given == "not lowered":
        why = (
            "class 'R' is never verified"
            if label == CLASS_LABELS[-1]
            else "a verdict 'not lowered' withholds the class"
        )
        raise ValueError(f"{src}: fields 'class' ({label!r}) and 'verification' contradict each other: {why}")


def _camera_matrix(cv: Any, size: tuple[int, int], src: Path, name: str = "opencv") -> list:
    """``name``'s camera matrix, checked (module docstring)."""
    m = cv.get("camera_matrix") if isinstance(cv, dict) else None
    ok = (
        isinstance(m, list)
        and len(m) == 3
        and all(isinstance(r, list) and len(r) == 3 and all(map(_number, r)) for r in m)
        and m[0][0] > 0
        and m[1][1] > 0
        and m[0][1] == m[1][0] == m[2][0] == m[2][1] == 0
        and m[2][2] == 1
        and 0 <= m[0][2] <= size[1] - 1
        and 0 <= m[1][2] <= size[0] - 1
    )
    if not ok:
        raise ValueError(f"{src}: field '{name}.camera_matrix' must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, "
                         f"fy > 0 and (cx, cy) inside the {size[0]} x {size[1]} frame, got {m!r:.80}")
    return m


def _focal(data: dict, size: tuple[int, int], src: Path) -> float | None:
    cv = data.get("opencv")
    return None if cv is None else float(_camera_matrix(cv, size, src)[0][0])


def _check_lens_class(label, lens: dict, size: tuple[int, int], src: Path) -> None:
    """Refuse a lens whose own class is not the file's: eq. 4 fitted to it (as calibrate did) must give ``label``."""
    h, w = size
    p = grid_points(h, w, map_grid_step(h, w))
    ideal, ok = lens_ideal(lens, p, h, w)
    field = "planar.coefficients" if lens["kind"] == "radial" else "opencv.dist_coeffs"
    if int(ok.sum()) < 3:
        raise ValueError(f"{src}: field {field!r} gives a lens that inverts nowhere in the {h} x {w} frame")
    k2, k4, _ = fit_eq4(p[ok], ideal[ok], h, w)
    _check_class(label, k2, k4, size, src, f"field {field!r} (the lens applied; eq. 4 fitted to it: k2 = {k2:.4g}, "
                                           f"k4 = {k4:.4g})")


def _lens(data: dict, size: tuple[int, int], src: Path) -> dict | None:
    """The answer's own lens where eq. 4 approximates it (module docstring), else None."""
    method = data.get("method")
    if method not in ("planar", "multiview") or data.get("k2_user") is None:
        return None
    if method == "multiview":
        name = "opencv" if data.get("opencv") is not None else "opencv_rational"
        cam = data.get(name)
        d = cam.get("dist_coeffs") if isinstance(cam, dict) else None
        if not (isinstance(d, list) and len(d) in (4, 5, 8) and all(map(_number, d))):
            raise ValueError(
                f"{src}: field '{name}.dist_coeffs' must be 4, 5 or 8 finite numbers (OpenCV's order) where "
                f"the multi-view path answered ('method' \"multiview\"), got {d!r:.60}"
            )
        _camera_matrix(cam, size, src, name)
        return answer_lens(data)
    block = data.get("planar")
    a = block.get("coefficients") if isinstance(block, dict) else None
    if not (isinstance(a, list) and 1 <= len(a) <= MAX_LENS_TERMS and all(map(_number, a))):
        raise ValueError(f"{src}: field 'planar.coefficients' must be 1 to {MAX_LENS_TERMS} finite numbers where the "
                         f"homography model answered ('method' \"planar\"), got {a!r:.60}")
    c = block.get("centre")
    if not (isinstance(c, list) and len(c) == 2 and all(map(_number, c)) and 0 <= c[0] <= size[1] - 1
            and 0 <= c[1] <= size[0] - 1):
        raise ValueError(f"{src}: field 'planar.centre' must be (x, y) inside the {size[0]} x {size[1]} frame, "
                         f"got {c!r:.60}")
    return answer_lens(data)


def read_calibration(src: Path) -> Calibration:
    """The fields ``--from`` uses, each checked with those that could contradict them (module docstring)."""
    if not src.is_file():
        raise FileNotFoundError(f"calibration file not found: {src}")
    try:
        data = json.loads(src.read_text())
    except (ValueError, OSError, RecursionError) as exc:  # UnicodeDecodeError, JSONDecodeError: ValueErrors
        why = "nested too deeply" if isinstance(exc, RecursionError) else type(exc).__name__
        raise ValueError(f"{src} is not {_WHAT} ({why})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{src} is not {_WHAT} (not a JSON object)")
    for field in ("k2_user", "k4_user"):
        if field not in data:
            raise ValueError(f"{src} is not {_WHAT} (no field {field!r})")
    size = _size(data, src)
    k2, k4 = _coefficient(data, "k2_user", src), _coefficient(data, "k4_user", src)
    if (k2 is None) != (k4 is None):
        raise ValueError(f"{src}: fields 'k2_user' and 'k4_user' must both be numbers or both null")
    if "class" not in data:
        raise ValueError(f"{src} is not {_WHAT} (no field 'class')")
    label = data["class"]
    if label is not None and label not in CLASS_LABELS:
        raise ValueError(f"{src}: field 'class' must be one of {', '.join(map(repr, CLASS_LABELS))} or null, "
                         f"got {label!r:.60}")
    reason = data.get("reason")
    reason = " ".join(reason.split()) if isinstance(reason, str) and reason.strip() else "no reason given"
    if label is not None and k2 is None:
        raise ValueError(f"{src}: field 'class' is {label!r}, but 'k2_user' and 'k4_user' are null: the file "
                         "contradicts itself")
    if k2 is not None and label is None:  # an estimate, but not an answer
        raise ValueError(f"{src} could not tell ({reason}): its numbers are not an answer; to use "
                         f"them anyway, pass them as --k2 {k2:.6g} --k4 {k4:.6g}")
    if label is not None:
        _check_class(label, k2, k4, _reference(data, size, src), src)
    _check_verification(data, label, src)
    lens = _lens(data, size, src)
    if lens is not None and label is not None:
        _check_lens_class(label, lens, size, src)
    return Calibration(
        k2=k2, k4=k4, height=size[0], width=size[1], reason=reason, focal=_focal(data, size, src), lens=lens)
