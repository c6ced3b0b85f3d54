"""The lens an answer of ``lensdist calibrate`` stands for: what ``undistort --from`` applies and the verifier checks.

An answer's ``k2_user``, ``k4_user`` are eq. 4 about the frame centre. Where another model
answered, eq. 4 only approximates it (``eq4_fit_error_px``: 12.7 px RMS on the GoPro HERO4's wide
lens), and the answer's own lens is what undistorting and verifying must use:

- ``method`` "planar" (the homography model): {"kind": "radial", "coefficients", "centre"}, up
  to three radial terms of the normalised radius about its own distortion centre
  (:mod:`~lensdist_torch.geometry.radial_lens`);
- ``method`` "multiview" (COLMAP): {"kind": "opencv", "camera_matrix", "dist_coeffs"}, its
  OpenCV camera (tangential terms included).

Pixels here are those of the answer's ``image_size``; :func:`scale_lens` moves a lens to frames
scaled by a factor (the normalised coefficients stay, the centre, principal point and focal
length scale about pixel centres at integers: (c + 0.5) s - 0.5).
"""

from __future__ import annotations

import torch

from lensdist_torch.geometry.undistort import (
    lens_optimal_view,
    lens_undistortion_grid,
    opencv_optimal_view,
    opencv_undistortion_grid,
)

__all__ = ["answer_lens", "scale_lens", "lens_grid", "lens_view"]


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
        return {"kind": "radial", "coefficients": list(res["planar"]["coefficients"]), "centre": list(res["planar"]["centre"])}
    if res.get("method") == "multiview":
        cam = res.get("opencv") or res.get("opencv_rational")
        return {"kind": "opencv", "camera_matrix": [list(r) for r in cam["camera_matrix"]], "dist_coeffs": list(cam["dist_coeffs"])}
    return None


def scale_lens(lens: dict | None, s: float) -> dict | None:
    """``lens`` for frames ``s`` times the size (module docstring).

    Example:
        >>> scale_lens({"kind": "radial", "coefficients": [0.3], "centre": [9.5, 7.5]}, 0.5)["centre"]
        [4.5, 3.5]
    """
    if lens is None:
        return None
    if lens["kind"] == "radial":
        return {**lens, "centre": [(v + 0.5) * s - 0.5 for v in lens["centre"]]}
    (fx, _, cx), (_, fy, cy), _ = lens["camera_matrix"]
    return {**lens, "camera_matrix": [[fx * s, 0.0, (cx + 0.5) * s - 0.5], [0.0, fy * s, (cy + 0.5) * s - 0.5], [0.0, 0.0, 1.0]]}


def _args(lens: dict) -> tuple:
    return (lens["coefficients"], lens["centre"]) if lens["kind"] == "radial" else (lens["camera_matrix"], lens["dist_coeffs"])


def lens_grid(lens: dict, height: int, width: int, dtype: torch.dtype = torch.float32, device=None, view=None):
    """(grid (1, H, W, 2), valid (1, 1, H, W)): where each ideal pixel lies in the distorted frame, under ``lens``."""
    grid = lens_undistortion_grid if lens["kind"] == "radial" else opencv_undistortion_grid
    return grid(*_args(lens), height, width, dtype, device, view)


def lens_view(lens: dict, height: int, width: int, alpha: float) -> tuple[float, float, float, float]:
    """The view of OpenCV's ``getOptimalNewCameraMatrix(..., alpha)`` under ``lens``."""
    view = lens_optimal_view if lens["kind"] == "radial" else opencv_optimal_view
    return view(*_args(lens), height, width, alpha)
