"""The lens an answer of ``lensdist calibrate`` stands for: what ``undistort --from`` applies and the verifier checks.

An answer's ``k2_user``, ``k4_user`` are eq. 4 about the frame centre. Where another model
answered, eq. 4 only approximates it (``eq4_fit_error_px``, px RMS over the frame),
and the answer's own lens is what undistorting and verifying must use:

- ``method`` "planar" (the homography model): {"kind": "radial", "coefficients", "centre"}, up
  to three radial terms of the normalised radius about its own distortion centre
  (:mod:`~lensdist_torch.geometry.radial_lens`);
- ``method`` "multiview" (COLMAP): {"kind": "opencv", "camera_matrix", "dist_coeffs"}, its
  OpenCV camera (tangential terms included).

Eq. 4 itself is a lens too, {"kind": "eq4", "k2", "k4"} (:func:`eq4_lens`), so undistorting and
verifying take one path whichever answered. Pixels here are those of the answer's
``image_size``; :func:`scale_lens` moves a lens to frames scaled by a factor (the normalised
coefficients stay, the centre, principal point and focal length scale about pixel centres at
integers: (c + 0.5) s - 0.5).
"""

from __future__ import annotations

import torch

from lensdist_torch.geometry.distortion import distortion_center, undistort_points
from lensdist_torch.geometry.opencv_model import FOLLOWS_PX, map_grid_step, opencv_camera_from_map, opencv_ideal_points
from lensdist_torch.geometry.radial_lens import lens_ideal_points, lens_inverts
from lensdist_torch.geometry.undistort import (
    lens_optimal_view,
    lens_undistortion_grid,
    monotone_branch,
    opencv_optimal_view,
    opencv_undistortion_grid,
    optimal_view,
    undistortion_grid,
)

__all__ = ["answer_lens", "eq4_lens", "scale_lens", "lens_ideal", "lens_grid", "lens_view", "radial_lens_opencv",
           "opencv_to_use"]


def answer_lens(res: dict) -> dict | None:
    """The answer's own lens (module docstring), or None where eq. 4 is the answer (or there is none).

    Example:
        >>> answer_lens({"method": "planar", "k2_user": 1e-7, "planar": {"coefficients": [0.3], "centre": [10.0, 8.0]}})
        {'kind': 'radial', 'coefficients': [0.3], 'centre': [10.0, 8.0]}
        >>> answer_lens({"method": "direct", "k2_user": 1e-7}) is None
        True
    """
    if res.get("k2_user") is None:
        return None
    if res.get("method") == "planar":
        return {
            "kind": "radial",
            "coefficients": list(res["planar"]["coefficients"]),
            "centre": list(res["planar"]["centre"]),
        }
    if res.get("method") == "multiview":
        cam = res.get("opencv") or res.get("opencv_rational")
        return {
            "kind": "opencv",
            "camera_matrix": [list(r) for r in cam["camera_matrix"]],
            "dist_coeffs": list(cam["dist_coeffs"]),
        }
    return None


def opencv_to_use(res: dict) -> dict | None:
    """The OpenCV camera an answer tells its user to paste: 5 coefficients, or 8 rational ones where 5 cannot follow.

    The 5 coefficients (``opencv``) do not follow the lens where their undistortPoints or
    cv2.undistort error is over ``FOLLOWS_PX`` px mean; the rational camera (``opencv_rational``)
    is then the one to use (``lensdist calibrate``'s text says so). None where the answer has neither.

    Example:
        >>> five = {"fit_error_mean_px": 4.3, "forward_error_mean_px": 2.4, "dist_coeffs": [0.1] * 5}
        >>> eight = {"fit_error_mean_px": 0.002, "forward_error_mean_px": 0.003, "dist_coeffs": [0.1] * 8}
        >>> len(opencv_to_use({"opencv": five, "opencv_rational": eight})["dist_coeffs"])
        8
        >>> five["fit_error_mean_px"] = five["forward_error_mean_px"] = 0.01
        >>> len(opencv_to_use({"opencv": five, "opencv_rational": eight})["dist_coeffs"])
        5
    """
    standard, rational = res.get("opencv"), res.get("opencv_rational")
    if standard and rational and max(standard["fit_error_mean_px"],
                                     standard.get("forward_error_mean_px", 0.0)) > FOLLOWS_PX:
        return rational
    return standard or rational


def eq4_lens(k2: float, k4: float) -> dict:
    """Eq. 4's (k2, k4) (pixels) as a lens of this module.

    Example:
        >>> eq4_lens(1e-6, 0.0)
        {'kind': 'eq4', 'k2': 1e-06, 'k4': 0.0}
    """
    return {"kind": "eq4", "k2": float(k2), "k4": float(k4)}


def scale_lens(lens: dict | None, s: float) -> dict | None:
    """``lens`` for frames ``s`` times the size (module docstring).

    Example:
        >>> scale_lens({"kind": "radial", "coefficients": [0.3], "centre": [9.5, 7.5]}, 0.5)["centre"]
        [4.5, 3.5]
    """
    if lens is None:
        return None
    if lens["kind"] == "eq4":
        return eq4_lens(lens["k2"] / s**2, lens["k4"] / s**4)
    if lens["kind"] == "radial":
        return {**lens, "centre": [(v + 0.5) * s - 0.5 for v in lens["centre"]]}
    (fx, _, cx), (_, fy, cy), _ = lens["camera_matrix"]
    return {
        **lens,
        "camera_matrix": [[fx * s, 0.0, (cx + 0.5) * s - 0.5], [0.0, fy * s, (cy + 0.5) * s - 0.5], [0.0, 0.0, 1.0]],
    }


#: Each kind's parameters, in the order its grid and view functions take them.
_PARAMETERS = {"eq4": ("k2", "k4"), "radial": ("coefficients", "centre"), "opencv": ("camera_matrix", "dist_coeffs")}
_GRIDS = {"eq4": undistortion_grid, "radial": lens_undistortion_grid, "opencv": opencv_undistortion_grid}
_VIEWS = {"eq4": optimal_view, "radial": lens_optimal_view, "opencv": opencv_optimal_view}


def _args(lens: dict) -> tuple:
    return tuple(lens[k] for k in _PARAMETERS[lens["kind"]])


def lens_ideal(lens: dict, points: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(ideal (..., 2), ok (...,)): ideal pixels of distorted ``points`` (float64) under ``lens``, and where it inverts.

    Example:
        >>> lens = {"kind": "opencv", "camera_matrix": [[100.0, 0, 50], [0, 100, 40], [0, 0, 1]],
        ...         "dist_coeffs": [-0.4, 0, 0, 0]}
        >>> ideal, ok = lens_ideal(lens, torch.tensor([[95.0, 40.0]], dtype=torch.float64), 80, 100)
        >>> [round(v, 6) for v in ideal[0].tolist()], ok.tolist()
        ([100.0, 40.0], [True])
        >>> from lensdist_torch.geometry.frame import half_diagonal  # eq. 4 and the radial lens it is, alike
        >>> p = torch.tensor([[0.0, 0.0], [30.0, 5.0]], dtype=torch.float64)
        >>> radial = {"kind": "radial", "coefficients": [1e-4 * half_diagonal(48, 64) ** 2], "centre": [31.5, 23.5]}
        >>> bool((lens_ideal(eq4_lens(1e-4, 0.0), p, 48, 64)[0] - lens_ideal(radial, p, 48, 64)[0]).abs().max() < 1e-9)
        True
    """
    if lens["kind"] == "eq4":
        c = distortion_center(height, width)
        d = points - points.new_tensor(c)
        ideal = undistort_points(points.reshape(1, -1, 2), lens["k2"], lens["k4"], c).reshape(points.shape)
        return ideal, monotone_branch((d * d).sum(-1), lens["k2"], lens["k4"])
    if lens["kind"] == "radial":
        a, c = lens["coefficients"], lens["centre"]
        return lens_ideal_points(points, a, height, width, centre=c), lens_inverts(points, a, height, width, centre=c)
    return opencv_ideal_points(points, torch.tensor(lens["camera_matrix"], dtype=torch.float64),
                               torch.tensor(lens["dist_coeffs"], dtype=torch.float64))


def lens_grid(lens: dict, height: int, width: int, *, dtype: torch.dtype = torch.float32, device=None, view=None):
    """(grid (1, H, W, 2), valid (1, 1, H, W)): where each ideal pixel lies in the distorted frame, under ``lens``."""
    return _GRIDS[lens["kind"]](*_args(lens), height, width, dtype=dtype, device=device, view=view)


def lens_view(lens: dict, height: int, width: int, alpha: float) -> tuple[float, float, float, float]:
    """The view of OpenCV's ``getOptimalNewCameraMatrix(..., alpha)`` under ``lens``."""
    return _VIEWS[lens["kind"]](*_args(lens), height, width, alpha=alpha)


def radial_lens_opencv(
    lens: dict, height: int, width: int, *, focal: float | None = None, model: str = "rational"
) -> dict:
    """OpenCV's camera fitted to a "radial" ``lens`` about its centre, strict-JSON-ready (the fit's ``model`` left out).

    ``focal``: fx = fy in pixels (the half diagonal when None); ``model`` "standard" (5
    coefficients) or "rational" (8).

    Example:
        >>> lens = {"kind": "radial", "coefficients": [0.05], "centre": [31.5, 23.5]}
        >>> cam = radial_lens_opencv(lens, 48, 64, focal=100.0)
        >>> cam["camera_matrix"][0][0], len(cam["dist_coeffs"]), cam["fit_error_mean_px"] < 0.05
        (100.0, 8, True)
    """
    fit = opencv_camera_from_map(
        lambda p: lens_ideal(lens, p, height, width)[0],
        height,
        width,
        focal=focal,
        model=model,
        step=map_grid_step(height, width),
        centre=lens["centre"],
    )
    return {k: (v.tolist() if isinstance(v, torch.Tensor) else v) for k, v in fit._asdict().items() if k != "model"}
