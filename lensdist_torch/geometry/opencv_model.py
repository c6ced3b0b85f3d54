"""Eq. 4 (docs/method.md, section 6) as OpenCV camera parameters, in pure torch.

OpenCV's lens model maps an ideal normalised point x = (p - c) / f to its distorted one,

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6),   r = |x|

(``dist_coeffs`` = (k1, k2, p1, p2, k3[, k4, k5, k6]), the tangential p1 = p2 = 0 here), and
``cv2.undistortPoints(p_d, K, dist, P=K)`` inverts it: distorted pixel -> ideal pixel. Eq. 4 goes
the other way, p = p0 + (1 + k2 r_d^2 + k4 r_d^4) (p_d - p0), a polynomial in the *distorted*
radius, so OpenCV's coefficients are fitted, not converted:

1. K = [[f, 0, cx], [0, f, cy], [0, 0, 1]], (cx, cy) = p0 the frame centre, f the half diagonal
   (or a focal length the caller knows; the fit's quality does not depend on f, the
   coefficients do).
2. A grid over the distorted frame (every ``step`` px and the last row and column): p_d and its
   ideal point p by eq. 4; x = (p - c) / f, x_d = (p_d - c) / f.
3. Linear least squares in pixels: ``standard`` (5 coefficients) solves
   f (x_d - x) = f x (k1 r^2 + k2 r^4 + k3 r^6); ``rational`` (8) solves
   f (x_d - x) = f x (k1 r^2 + k2 r^4 + k3 r^6) - f x_d (k4 r^2 + k5 r^4 + k6 r^6), the model
   times its denominator.
4. Verification: every grid point p_d is undistorted with the fitted model exactly as
   ``cv2.undistortPoints(..., P=K)`` does (:func:`opencv_undistort_points`: OpenCV's default of
   5 fixed-point iterations, not converged for strong distortion) and compared with eq. 4's p:
   ``fit_error_mean_px`` and ``fit_error_max_px``. The forward model's own error (ideal ->
   distorted, what ``cv2.undistort`` and ``cv2.initUndistortRectifyMap`` use) is reported
   beside it.

Measured against cv2 itself (the tests check it), standard model, at 1/8, 1/2 and 7/8 of the
largest coefficients of section 6 (scaled with the frame): mean undistortPoints error 1e-4,
0.017 and 0.054 px at 320 x 424 (max 0.001, 0.39, 1.3 px, in the far corners), 1e-4, 0.025 and
0.079 px at 480 x 640, 2e-4, 0.033 and 0.12 px at 1080 x 1920. The rational model fits the
forward map to 1e-3 px, but OpenCV's 5 iterations leave 0.002-0.02 px on average there (and up
to 11 px in the corners of strong pincushion): prefer ``standard`` unless the forward map
matters most.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from lensdist_torch.geometry.distortion import distortion_center, undistort_points
from lensdist_torch.geometry.frame import grid_points

__all__ = [
    "OpenCVCamera",
    "MODELS",
    "FOLLOWS_PX",
    "opencv_camera",
    "opencv_camera_from_map",
    "opencv_export",
    "opencv_distort_normalized",
    "opencv_distort_full",
    "opencv_undistort_points",
    "opencv_ideal_points",
    "radial_monotone",
    "opencv_delta",
    "grid_points",
    "map_grid_step",
    "opencv_from_colmap",
]

MODELS = ("standard", "rational")

#: An export whose mean error against the lens it was fitted to exceeds this (px) does not follow
#: it: ``lensdist calibrate`` then names the other export (a wide lens of about 100 px is followed
#: by the 8 rational coefficients, not by the standard 5: docs/guide/calibrate.md).
FOLLOWS_PX = 1.0


class OpenCVCamera(NamedTuple):
    """OpenCV camera parameters of one frame size.

    camera_matrix: (3, 3) float64 K. dist_coeffs: (5,) (standard) or (8,) (rational) float64,
    OpenCV's order. fit_error_mean_px, fit_error_max_px: ``cv2.undistortPoints``' error
    against eq. 4 over the frame (module docstring); forward_error_mean_px, forward_error_max_px:
    the forward model's (ideal -> distorted, what ``cv2.undistort`` and
    ``cv2.initUndistortRectifyMap`` use), in distorted pixels. model: "standard" or "rational".

    Example:
        >>> cam = opencv_camera(0.0, 0.0, 320, 424)  # no distortion: f the half diagonal, c the centre
        >>> [round(v, 2) for v in cam.camera_matrix[:2].flatten().tolist()], float(cam.dist_coeffs.abs().max())
        ([264.9, 0.0, 211.5, 0.0, 264.9, 159.5], 0.0)
        >>> barrel = opencv_camera(1e-6, 0.0, 320, 424)
        >>> barrel.model, bool(barrel.dist_coeffs[0] < 0), barrel.fit_error_max_px < 0.05
        ('standard', True, True)
    """

    camera_matrix: torch.Tensor
    dist_coeffs: torch.Tensor
    fit_error_mean_px: float
    fit_error_max_px: float
    forward_error_mean_px: float
    forward_error_max_px: float
    model: str


def _radial(r2: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV's radial factor F and its derivative dF/d(r^2) at squared normalised radii r2."""
    num = 1 + r2 * (dist[0] + r2 * (dist[1] + r2 * dist[4]))
    dnum = dist[0] + r2 * (2 * dist[1] + 3 * r2 * dist[4])
    if dist.numel() < 8:
        return num, dnum
    den = 1 + r2 * (dist[5] + r2 * (dist[6] + r2 * dist[7]))
    dden = dist[5] + r2 * (2 * dist[6] + 3 * r2 * dist[7])
    return num / den, (dnum * den - num * dden) / (den * den)


def opencv_distort_normalized(x: torch.Tensor, dist_coeffs: torch.Tensor) -> torch.Tensor:
    """OpenCV's forward model (radial part): ideal normalised points (..., 2) -> distorted.

    Example:
        >>> d = torch.tensor([-0.4, 0, 0, 0, 0], dtype=torch.float64)  # k1 = -0.4: barrel
        >>> opencv_distort_normalized(torch.tensor([[0.5, 0.0]], dtype=torch.float64), d).tolist()
        [[0.45, 0.0]]
    """
    d = torch.as_tensor(dist_coeffs, dtype=x.dtype, device=x.device)
    return x * _radial((x * x).sum(-1, keepdim=True), d)[0]


def opencv_undistort_points(
    points: torch.Tensor, camera_matrix: torch.Tensor, dist_coeffs: torch.Tensor, iterations: int = 5
) -> torch.Tensor:
    """Distorted pixels (..., 2) -> ideal pixels, as ``cv2.undistortPoints(p, K, dist, P=K)``.

    OpenCV's own algorithm: x = x_d / F(|x|^2) repeated ``iterations`` times from x = x_d
    (its default criteria are 5 iterations), a point whose 1 / F turns negative falling back to
    x_d; float64. It is a fixed-point iteration, not converged for strong distortion, so it is
    what the fit is verified against. Tangential coefficients must be 0.

    Example:
        >>> K = torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]], dtype=torch.float64)
        >>> d = torch.tensor([-0.4, 0, 0, 0, 0], dtype=torch.float64)  # (95, 40) is ideal (100, 40)
        >>> [round(v, 3) for v in opencv_undistort_points(torch.tensor([[95.0, 40.0]]), K, d)[0].tolist()]
        [99.998, 40.0]
    """
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64).reshape(-1)
    if d.numel() not in (5, 8) or bool(d[2:4].ne(0).any()):
        raise ValueError("dist_coeffs must hold 5 or 8 values with p1 = p2 = 0")
    f = torch.stack([k[0, 0], k[1, 1]])
    c = k[:2, 2]
    x0 = (points.to(torch.float64) - c) / f
    x = x0
    stopped = torch.zeros_like(x0[..., :1], dtype=torch.bool)
    for _ in range(iterations):
        icdist = 1.0 / _radial((x * x).sum(-1, keepdim=True), d)[0]
        stopped = stopped | (icdist < 0)
        x = torch.where(stopped, x0, x0 * icdist)
    return x * f + c


def _design(x: torch.Tensor, xd: torch.Tensor, model: str) -> torch.Tensor:
    """(N, 2) ideal and distorted normalised points -> (2N, 3 or 6) columns of the linear fit."""
    r2 = (x * x).sum(-1, keepdim=True)
    cols = [x * r2, x * r2**2, x * r2**3]
    if model == "rational":
        cols += [-xd * r2, -xd * r2**2, -xd * r2**3]
    return torch.stack(cols, -1).reshape(-1, len(cols))


def opencv_camera(
    k2, k4, height: int, width: int, *, focal: float | None = None, model: str = "standard", step: int = 4
) -> OpenCVCamera:
    """Fit OpenCV's K and dist_coeffs to eq. 4's (k2, k4) of a (height, width) frame.

    Args:
        k2: eq. 4's k2 in the frame's pixels (a number or a one-element tensor).
        k4: eq. 4's k4, the same way.
        height: the frame's height; its centre is eq. 4's p0 and K's (cx, cy).
        width: the frame's width.
        focal: fx = fy in pixels; the half diagonal when None.
        model: "standard" (k1, k2, 0, 0, k3) or "rational" (k1, k2, 0, 0, k3, k4, k5, k6).
        step: spacing in pixels of the fitting and verification grid.

    Returns:
        :class:`OpenCVCamera`.

    Example:
        >>> cam = opencv_camera(1e-6, 1e-11, 320, 424)
        >>> cam.dist_coeffs.shape, cam.fit_error_mean_px < 0.05
        (torch.Size([5]), True)
    """
    k2 = torch.as_tensor(k2, dtype=torch.float64).reshape(-1)[:1]
    k4 = torch.as_tensor(k4, dtype=torch.float64).reshape(-1)[:1]
    centre = distortion_center(height, width) if type(height) is int and type(width) is int else (0.0, 0.0)
    return opencv_camera_from_map(lambda pd: undistort_points(pd[None], k2, k4, centre)[0], height, width, focal=focal,
                                  model=model, step=step)


def opencv_camera_from_map(
    ideal, height: int, width: int, *, focal: float | None = None, model: str = "standard", step: int = 4,
    centre: tuple[float, float] | None = None,
) -> OpenCVCamera:
    """Fit OpenCV's K and dist_coeffs to any radial lens map about its centre (module docstring, steps 1-4).

    Args:
        ideal: a function from (N, 2) float64 distorted pixels to their (N, 2) ideal pixels.
        height: the frame's height.
        width: the frame's width.
        focal: fx = fy in pixels; the half diagonal when None.
        model: "standard" or "rational", as :func:`opencv_camera`.
        step: spacing in pixels of the fitting and verification grid.
        centre: the map's centre (x, y) in pixels, K's (cx, cy); the frame centre when None.

    Returns:
        :class:`OpenCVCamera`.

    Example:
        >>> cam = opencv_camera_from_map(lambda p: p, 120, 160)  # the identity: no distortion
        >>> float(cam.dist_coeffs.abs().max()), cam.fit_error_max_px < 1e-9
        (0.0, True)
    """
    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if not (type(height) is int and type(width) is int and height > 1 and width > 1):
        raise ValueError(f"height and width must be ints > 1, got {height!r} and {width!r}")
    if type(step) is not int or step < 1:
        raise ValueError(f"step must be a positive int, got {step!r}")
    f = 0.5 * math.hypot(width - 1, height - 1) if focal is None else float(focal)
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"focal must be a positive number of pixels, got {focal!r}")
    centre = distortion_center(height, width) if centre is None else tuple(float(v) for v in centre)
    if len(centre) != 2 or not all(math.isfinite(v) for v in centre):
        raise ValueError(f"centre must be two finite pixel coordinates (x, y), got {centre!r}")
    xs = torch.cat(
        [torch.arange(0, width - 1, step, dtype=torch.float64), torch.tensor([width - 1.0], dtype=torch.float64)]
    )
    ys = torch.cat(
        [torch.arange(0, height - 1, step, dtype=torch.float64), torch.tensor([height - 1.0], dtype=torch.float64)]
    )
    pd = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    p = ideal(pd)
    c = torch.tensor(centre, dtype=torch.float64)
    x, xd = (p - c) / f, (pd - c) / f
    a = _design(x, xd, model) * f
    scale = a.norm(dim=0).clamp_min(1e-300)
    sol = torch.linalg.lstsq(a / scale, ((xd - x).reshape(-1, 1)) * f, driver="gelsd").solution[:, 0] / scale
    dist = torch.zeros(8 if model == "rational" else 5, dtype=torch.float64)
    dist[[0, 1, 4]] = sol[:3]
    if model == "rational":
        dist[5:] = sol[3:]
    cam = torch.tensor([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]], dtype=torch.float64)
    err = torch.nan_to_num((opencv_undistort_points(pd, cam, dist) - p).norm(dim=-1), nan=float("inf"))
    fwd = torch.nan_to_num((opencv_distort_normalized(x, dist) - xd).norm(dim=-1) * f, nan=float("inf"))
    return OpenCVCamera(
        camera_matrix=cam, dist_coeffs=dist, fit_error_mean_px=float(err.mean()), fit_error_max_px=float(err.max()),
        forward_error_mean_px=float(fwd.mean()), forward_error_max_px=float(fwd.max()), model=model)


def opencv_export(
    k2: float, k4: float, height: int, width: int, *, focal: float | None = None, model: str = "standard"
):
    """:func:`opencv_camera` as plain JSON-ready values, or None where (k2, k4) is not finite.

    Args:
        k2: eq. 4's k2 in the frame's pixels.
        k4: eq. 4's k4 in the frame's pixels.
        height: the frame's height (px).
        width: the frame's width (px).
        focal: fx = fy in pixels; the half diagonal when None.
        model: "standard" (k1, k2, p1, p2, k3) or "rational" (8 coefficients).

    Returns:
        A dict: ``camera_matrix`` (3 x 3 list), ``dist_coeffs`` (list), ``fit_error_mean_px``,
        ``fit_error_max_px``, ``forward_error_mean_px``, ``forward_error_max_px``.

    Example:
        >>> sorted(opencv_export(1e-6, 1e-11, 320, 424))[:2]
        ['camera_matrix', 'dist_coeffs']
    """
    if not (math.isfinite(k2) and math.isfinite(k4)):
        return None
    cam = opencv_camera(k2, k4, height, width, focal=focal, model=model)
    return {k: (v.tolist() if isinstance(v, torch.Tensor) else v) for k, v in cam._asdict().items() if k != "model"}



def _forward_full(x: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV's forward model with tangential terms at (..., 2) ideal points, and its (..., 2, 2) Jacobian."""
    d = torch.cat([d, d.new_zeros(8 - d.numel())]) if d.numel() < 8 else d
    u, v = x[..., 0], x[..., 1]
    r2 = u * u + v * v
    f, df = _radial(r2[..., None], d)
    f, df = f[..., 0], df[..., 0]
    p1, p2 = d[2], d[3]
    xd = torch.stack(
        [u * f + 2 * p1 * u * v + p2 * (r2 + 2 * u * u), v * f + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v], -1
    )
    j = torch.stack(
        [
            torch.stack([f + 2 * u * u * df + 2 * p1 * v + 6 * p2 * u, 2 * u * v * df + 2 * p1 * u + 2 * p2 * v], -1),
            torch.stack([2 * u * v * df + 2 * p1 * u + 2 * p2 * v, f + 2 * v * v * df + 6 * p1 * v + 2 * p2 * u], -1),
        ],
        -2,
    )
    return xd, j


def opencv_distort_full(x: torch.Tensor, dist_coeffs) -> torch.Tensor:
    """OpenCV's forward model with its tangential terms: ideal normalised points (..., 2) -> distorted.

    What ``cv2.initUndistortRectifyMap`` evaluates (4, 5 or 8 coefficients, OpenCV's order).

    Example:
        >>> d = torch.tensor([-0.4, 0, 0.01, 0, 0], dtype=torch.float64)  # p1 = 0.01 adds 2 p1 x y and p1 (r^2 + 2 y^2)
        >>> [round(v, 6) for v in opencv_distort_full(torch.tensor([[0.5, 0.0]], dtype=torch.float64), d)[0].tolist()]
        [0.45, 0.0025]
    """
    d = torch.as_tensor(dist_coeffs, dtype=x.dtype, device=x.device).reshape(-1)
    if d.numel() not in (4, 5, 8):
        raise ValueError(f"dist_coeffs must hold 4, 5 or 8 values (OpenCV's order), got {d.numel()}")
    return _forward_full(x, d)[0]


def opencv_ideal_points(
    points: torch.Tensor, camera_matrix: torch.Tensor, dist_coeffs: torch.Tensor, iterations: int = 30
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distorted pixels (..., 2) -> ideal pixels by a *converged* inverse of OpenCV's model, and where it holds.

    Newton on the full model (radial, rational and tangential terms) from the distorted point,
    with K's focal lengths and principal point (skew 0). ``valid`` is True where Newton
    converged (below 1e-9 normalised units, about 1e-6 px) on the monotone branch of the radial
    part (``d(r F(r^2)) / dr > 0`` from the centre out to the found radius): beyond it the model
    does not invert, and no ideal point is claimed. Unlike :func:`opencv_undistort_points`
    (OpenCV's 5 fixed-point iterations) it is exact for strong distortion.

    Returns:
        ideal: (..., 2) float64 pixels; valid: (...,) bool.

    Example:
        >>> K = torch.tensor([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]], dtype=torch.float64)
        >>> d = torch.tensor([-0.4, 0, 0, 0, 0], dtype=torch.float64)  # (95, 40) is ideal (100, 40)
        >>> ideal, ok = opencv_ideal_points(torch.tensor([[95.0, 40.0]]), K, d)
        >>> [round(v, 6) for v in ideal[0].tolist()], bool(ok[0])
        ([100.0, 40.0], True)
    """
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64).reshape(-1)
    if d.numel() not in (4, 5, 8):
        raise ValueError(f"dist_coeffs must hold 4, 5 or 8 values (OpenCV's order), got {d.numel()}")
    f, c = torch.stack([k[0, 0], k[1, 1]]), k[:2, 2]
    xd = (points.to(torch.float64) - c) / f
    x = xd.clone()
    for _ in range(iterations):
        fx, j = _forward_full(x, d)
        step = torch.linalg.solve(j, (fx - xd)[..., None])[..., 0]
        x = x - torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0).clamp(-0.5, 0.5)
    err = (_forward_full(x, d)[0] - xd).norm(dim=-1)
    valid = torch.isfinite(err) & (err < 1e-9) & radial_monotone((x * x).sum(-1), d)
    return x * f + c, valid


def radial_monotone(r2: torch.Tensor, dist_coeffs: torch.Tensor) -> torch.Tensor:
    """(...,) bool: OpenCV's radial map r -> r F(r^2) increases from the centre out to r, r2 = r^2 (normalised).

    ``d(r F(r^2)) / dr = F + 2 r^2 F' > 0`` at 16 radii evenly along [0, r]: where it fails the
    model folds back, and no point beyond is its image.

    Example:
        >>> d = torch.tensor([-0.4, 0, 0, 0, 0], dtype=torch.float64)  # 1 - 3 * 0.4 r^2 > 0 below r^2 = 0.83
        >>> radial_monotone(torch.tensor([0.5, 1.0], dtype=torch.float64), d).tolist()
        [True, False]
    """
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64, device=r2.device).reshape(-1)
    t = torch.linspace(0.0625, 1.0, 16, dtype=torch.float64, device=r2.device)
    s2 = r2[..., None] * t * t  # squared radii along the ray
    fr, dfr = _radial(s2, torch.cat([d, d.new_zeros(5 - d.numel())]) if d.numel() < 5 else d)
    return ((fr + 2 * s2 * dfr) > 0).all(-1)


def map_grid_step(height: int, width: int) -> int:
    """The step (px) of the grid of about 20,000 pixels a lens map is measured, fitted and exported on.

    Example:
        >>> map_grid_step(960, 1280), map_grid_step(120, 160)
        (8, 1)
    """
    return max(1, round(math.sqrt(height * width / 20000)))


def opencv_delta(camera_matrix, dist_coeffs, height: int, width: int, *, step: int = 4) -> dict:
    """Delta over a (height, width) frame of an OpenCV camera: |p - ideal(p)| in pixels.

    The mean and the largest offset over every ``step``-th pixel where the model inverts
    (:func:`opencv_ideal_points`), and the share of pixels where it does. This is the Delta of
    ``undistortPoints(p, K, dist, P=K)`` run to convergence.

    Example:
        >>> K = torch.tensor([[200.0, 0, 79.5], [0, 200, 59.5], [0, 0, 1]], dtype=torch.float64)
        >>> out = opencv_delta(K, torch.zeros(5, dtype=torch.float64), 120, 160)
        >>> round(out["delta_avg_px"], 9), out["invertible_fraction"]
        (0.0, 1.0)
    """
    p = grid_points(height, width, step)
    ideal, ok = opencv_ideal_points(p, camera_matrix, dist_coeffs)
    off = (ideal - p).norm(dim=-1)[ok]
    if off.numel() == 0:
        return {"delta_avg_px": float("nan"), "delta_max_px": float("nan"), "invertible_fraction": 0.0}
    return {
        "delta_avg_px": float(off.mean()),
        "delta_max_px": float(off.max()),
        "invertible_fraction": float(ok.double().mean()),
    }


def opencv_from_colmap(camera, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """COLMAP camera -> OpenCV's K (3, 3) and dist_coeffs (5 or 8), float64, in pixels scaled by ``scale``.

    Exact for SIMPLE_PINHOLE (no distortion), SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV (OpenCV's
    model with some coefficients 0); the principal point moves by -0.5 px (COLMAP's pixel centres lie at +0.5).
    ``camera`` needs ``params`` and ``model_name`` (a ``pycolmap.Camera``).

    Example:
        >>> from types import SimpleNamespace
        >>> k, d = opencv_from_colmap(SimpleNamespace(model_name="RADIAL", params=[500.0, 320.0, 240.0, -0.1, 0.02]))
        >>> k[0].tolist(), d.tolist()
        ([500.0, 0.0, 319.5], [-0.1, 0.02, 0.0, 0.0, 0.0])
    """
    p, name = [float(v) for v in camera.params], camera.model_name
    if name == "SIMPLE_PINHOLE":  # no distortion
        fx = fy = p[0]
        cx, cy, dist = p[1], p[2], [0.0] * 5
    elif name in ("SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy, extra = p[1], p[2], p[3:]
        dist = [extra[0], extra[1] if len(extra) > 1 else 0.0, 0.0, 0.0, 0.0]
    elif name in ("OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy, extra = p[0], p[1], p[2], p[3], p[4:]
        dist = extra + [0.0] if name == "OPENCV" else extra
    else:
        raise ValueError(
            f"camera model must be one of SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV, got {name}")
    k = torch.tensor([[scale * fx, 0.0, scale * cx - 0.5], [0.0, scale * fy, scale * cy - 0.5], [0.0, 0.0, 1.0]],
                     dtype=torch.float64)
    return k, torch.tensor(dist, dtype=torch.float64)
