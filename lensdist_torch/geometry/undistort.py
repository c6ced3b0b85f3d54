"""Undistorted images: the inverse warp of eq. 4 (docs/method.md, section 6), batched, differentiable.

A distorted image was rendered as I_d(p_d) = I(p(p_d)), p = p0 + (1 + k2 r^2 + k4 r^4) (p_d - p0)
the ideal point of the distorted pixel p_d. Undistorting samples the distorted image, for every
ideal pixel p of the output, at its distorted position p_d = distort(p), the Newton inverse of
eq. 4 (:func:`~lensdist_torch.geometry.distortion.distort_points`):

    I(p) = I_d(distort(p)),   one ``grid_sample`` per image, ``align_corners=True``.

The output has the input's size. By default it keeps the input's scale and centre (an ideal pixel
p is output pixel p: ``cv2.undistort``'s default new camera matrix, the input's own): barrel
distortion loses the frame's edges, pincushion leaves its corners empty. A ``view``
(sx, sy, tx, ty) maps the ideal pixel (u, v) to the output pixel (sx u + tx, sy v + ty);
:func:`optimal_view` chooses it as OpenCV's ``getOptimalNewCameraMatrix`` does, by ``alpha``: 0
only valid pixels (the largest axis-aligned rectangle inside the undistorted frame fills the
output), 1 every source pixel kept (the rectangle around the undistorted frame fills it), in
between the linear interpolation of the two. Its validity mask is 1 where distort(p) lies inside
the distorted image (1e-3 px of slack for rounding), the Newton inverse is exact there (a round
trip through eq. 4 within 0.01 px) and distort(p) lies on eq. 4's monotone branch: on the same
side of p0 as p, at a distorted radius r where r (1 + k2 r^2 + k4 r^4) still increases on all of
[0, r] (:func:`monotone_branch`). Strongly negative coefficients make eq. 4 fold over: past the
fold an ideal radius has no preimage or a second one (a mirrored or folded-back position whose
round trip is exact all the same); such pixels are marked invalid, never filled with a wrong
sample. Outside the mask the image is 0. Gradients flow to the image and to k2, k4 (as for any
bilinear warp, the gradient with respect to the coordinates is that of the bilinear
interpolant).

A lens that eq. 4 cannot follow (the homography model's: up to three radial terms about its own
distortion centre, :mod:`~lensdist_torch.geometry.radial_lens`) has its own grid and view,
:func:`lens_undistortion_grid` and :func:`lens_optimal_view`: the same rules, its inverse by
Newton's method on the radius, valid on its monotone branch.

Kornia-style: the pure function :func:`undistort_image` and the thin module :class:`Undistort`.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from lensdist_torch.core.images import check_image
from lensdist_torch.geometry.distortion import (
    distort_points,
    distortion_center,
    radial_derivative,
    sample_at_pixels,
    undistort_points,
)
from lensdist_torch.geometry.frame import pixel_grid
from lensdist_torch.geometry.opencv_model import opencv_distort_full, opencv_ideal_points, radial_monotone
from lensdist_torch.geometry.radial_lens import lens_distorted_points, lens_ideal_points, lens_inverts

__all__ = ["monotone_branch", "optimal_view", "lens_optimal_view", "opencv_optimal_view", "undistortion_grid",
           "lens_undistortion_grid", "opencv_undistortion_grid", "undistort_image", "Undistort"]

_SLACK_PX = 1e-3
_ROUND_TRIP_PX = 1e-2


def _coefficient(value, name: str, like: torch.Tensor) -> torch.Tensor:
    k = torch.as_tensor(value, dtype=like.dtype, device=like.device) if not isinstance(value, torch.Tensor) else value
    if not k.is_floating_point():
        k = k.to(like.dtype)
    k = k.to(device=like.device).reshape(-1)
    if k.numel() == 0:
        raise ValueError(f"{name} must hold one value or one per image, got none")
    if not bool(torch.isfinite(k.detach()).all()):
        raise ValueError(f"{name} must be finite")
    return k.to(like.dtype)


def monotone_branch(r2: torch.Tensor, k2, k4) -> torch.Tensor:
    """True where eq. 4's radius map r -> r (1 + k2 r^2 + k4 r^4) increases on all of [0, r], r2 = r^2.

    Its derivative (:func:`~lensdist_torch.geometry.distortion.radial_derivative`) is a quadratic
    in s = r^2 equal to 1 at s = 0, so its least value on [0, r2] is at r2 or, where k4 > 0, at
    the quadratic's vertex -3 k2 / (10 k4) when that lies inside; both must be positive. k2, k4
    broadcast against r2.

    Example:
        >>> monotone_branch(torch.tensor([100.0, 400.0]), -1e-3, 0.0).tolist()  # folds at r = 18.3 px
        [True, False]
    """
    k2 = torch.as_tensor(k2, dtype=r2.dtype, device=r2.device)
    k4 = torch.as_tensor(k4, dtype=r2.dtype, device=r2.device)
    curved = k4 > 0
    vertex = -3.0 * k2 / (10.0 * torch.where(curved, k4, torch.ones_like(k4)))
    low = torch.where(curved, torch.minimum(vertex.clamp_min(0.0), r2), r2)
    return (radial_derivative(r2, k2, k4) > 0) & (radial_derivative(low, k2, k4) > 0)


def optimal_view(k2: float, k4: float, height: int, width: int, *, alpha: float) -> tuple[float, float, float, float]:
    """The view (sx, sy, tx, ty) of OpenCV's ``getOptimalNewCameraMatrix(..., alpha)`` for eq. 4.

    The frame's border pixels are brought to their ideal positions by eq. 4 (those on its
    monotone branch, :func:`monotone_branch`). The inner rectangle runs from the innermost ideal
    x of the left edge to that of the right edge (y: top and bottom edges), the outer one around
    all of them; each is mapped onto the output's pixel centres 0 ... W - 1 and 0 ... H - 1
    (separate x and y scales, as OpenCV), and the two maps are interpolated linearly by
    ``alpha``: 0 the inner rectangle (no invalid pixel), 1 the outer one (no source pixel lost).
    With OpenCV's K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] about the frame centre, the new camera
    matrix is [[sx f, 0, sx cx + tx], [0, sy f, sy cy + ty], [0, 0, 1]].

    Example:
        >>> sx, sy, tx, ty = optimal_view(1e-5, 0.0, 120, 160, alpha=0.0)  # barrel: zoom out to the valid rectangle
        >>> round(sx, 3), round(sy, 3)
        (0.941, 0.966)
        >>> optimal_view(0.0, 0.0, 120, 160, alpha=1.0)  # no distortion: the frame itself
        (1.0, 1.0, 0.0, 0.0)
    """
    def ideal(pts: torch.Tensor) -> torch.Tensor:  # the pixels on eq. 4's monotone branch, at their ideal positions
        d = pts - pts.new_tensor(centre)
        keep = monotone_branch((d * d).sum(-1), float(k2), float(k4))
        return undistort_points(pts[keep][None], float(k2), float(k4), centre)[0]

    centre = distortion_center(height, width) if type(height) is int and type(width) is int else None
    return _view(ideal, height, width, alpha, f"k2 = {k2:.4g}, k4 = {k4:.4g}", "eq. 4")


def lens_optimal_view(
    coefficients, centre, height: int, width: int, *, alpha: float
) -> tuple[float, float, float, float]:
    """:func:`optimal_view` for the radial lens a_1 .. a_n about ``centre``.

    The lens of :mod:`~lensdist_torch.geometry.radial_lens`.

    Example:
        >>> from lensdist_torch.geometry.frame import half_diagonal
        >>> big_r = half_diagonal(120, 160)  # eq. 4's k2 = 1e-5 as the lens's a_1 about the frame centre
        >>> [round(v, 6) for v in lens_optimal_view([1e-5 * big_r**2], None, 120, 160, alpha=0.0)] == [
        ...     round(v, 6) for v in optimal_view(1e-5, 0.0, 120, 160, alpha=0.0)]
        True
    """
    a = torch.as_tensor(coefficients, dtype=torch.float64)

    def ideal(pts: torch.Tensor) -> torch.Tensor:
        return lens_ideal_points(
            pts[lens_inverts(pts, a, height, width, centre=centre)], a, height, width, centre=centre
        )

    return _view(ideal, height, width, alpha, f"the lens {[round(float(v), 4) for v in a]}", "the lens")


def _view(ideal, height: int, width: int, alpha: float, what: str, model: str) -> tuple[float, float, float, float]:
    """The view of :func:`optimal_view` from ``ideal``.

    ``ideal``: a frame edge's (N, 2) pixels to those it keeps, at their ideal positions.
    """
    if not (type(height) is int and type(width) is int and height > 1 and width > 1):
        raise ValueError(f"height and width must be ints above 1, got {height!r} and {width!r}")
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float)) or not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be a number from 0 to 1, got {alpha!r}")
    xs = torch.arange(width, dtype=torch.float64)
    ys = torch.arange(height, dtype=torch.float64)
    edges = {
        "left": torch.stack([torch.zeros_like(ys), ys], -1),
        "right": torch.stack([torch.full_like(ys, width - 1.0), ys], -1),
        "top": torch.stack([xs, torch.zeros_like(xs)], -1),
        "bottom": torch.stack([xs, torch.full_like(xs, height - 1.0)], -1),
    }
    ideal = {name: ideal(pts) for name, pts in edges.items()}
    if any(len(v) == 0 for v in ideal.values()):
        raise ValueError(f"{what} fold {model} before a whole edge of the {height} x {width} frame")
    every = torch.cat(list(ideal.values()))
    inner = (float(ideal["left"][:, 0].max()), float(ideal["top"][:, 1].max()),
             float(ideal["right"][:, 0].min()), float(ideal["bottom"][:, 1].min()))
    outer = (float(every[:, 0].min()), float(every[:, 1].min()), float(every[:, 0].max()), float(every[:, 1].max()))
    if not (inner[2] > inner[0] and inner[3] > inner[1]):
        raise ValueError(f"{what} leave no valid rectangle in the undistorted {height} x {width} frame")

    def fit(x0: float, y0: float, x1: float, y1: float) -> tuple[float, float, float, float]:
        sx, sy = (width - 1) / (x1 - x0), (height - 1) / (y1 - y0)
        return sx, sy, -sx * x0, -sy * y0

    a, b = fit(*inner), fit(*outer)
    return tuple(float(u * (1 - alpha) + v * alpha) + 0.0 for u, v in zip(a, b))  # + 0.0: no -0.0


def _check_view(view) -> tuple[float, float, float, float] | None:
    if view is None:
        return None
    try:
        sx, sy, tx, ty = (float(v) for v in view)
    except (TypeError, ValueError):
        raise ValueError(f"view must be (sx, sy, tx, ty), four numbers, or None, got {view!r:.80}") from None
    if not (math.isfinite(tx) and math.isfinite(ty) and math.isfinite(sx) and math.isfinite(sy) and sx > 0 and sy > 0):
        raise ValueError(f"view must hold positive finite scales and finite offsets, got {view!r:.80}")
    return sx, sy, tx, ty


def undistortion_grid(
    k2, k4, height: int, width: int, *, dtype: torch.dtype = torch.float32, device=None, view=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """For every ideal pixel of a (height, width) frame, its position in the distorted image.

    Args:
        k2: eq. 4's k2 in pixels, a number or a (B,) tensor.
        k4: eq. 4's k4, as many values as k2.
        height: the frame's height (its centre is eq. 4's p0).
        width: the frame's width.
        dtype: of the returned grid.
        device: of the returned grid.
        view: (sx, sy, tx, ty): output pixel q shows the ideal pixel ((q_x - tx) / sx, (q_y - ty) / sy)
            (:func:`optimal_view`); None: q itself (the input's scale and centre).

    Returns:
        grid: (B, H, W, 2) pixel coordinates (x, y) of distort(p) in the distorted image.
        valid: (B, 1, H, W) of 0 and 1 (module docstring), ``dtype``.

    Example:
        >>> grid, valid = undistortion_grid(torch.tensor([1e-4, -1e-4]), torch.zeros(2), 32, 48)
        >>> tuple(grid.shape), valid.mean(dim=(1, 2, 3)).lt(1).tolist()  # pincushion's corners lie outside
        ((2, 32, 48, 2), [False, True])
    """
    if not (type(height) is int and type(width) is int and height > 0 and width > 0):
        raise ValueError(f"height and width must be positive ints, got {height!r} and {width!r}")
    view = _check_view(view)
    ref = torch.empty(0, dtype=dtype, device=device)
    k2, k4 = _coefficient(k2, "k2", ref), _coefficient(k4, "k4", ref)
    if k2.shape != k4.shape:
        raise ValueError(f"k2 and k4 must have the same number of values, got {k2.numel()} and {k4.numel()}")
    centre = distortion_center(height, width)
    ideal = pixel_grid(height, width, dtype, device)
    if view is not None:
        ideal = (ideal - ideal.new_tensor(view[2:])) / ideal.new_tensor(view[:2])
    ideal = ideal.expand(k2.numel(), height, width, 2)
    src = distort_points(ideal, k2, k4, centre)
    back = undistort_points(src.detach(), k2.detach(), k4.detach(), centre)
    exact = ((back - ideal).abs().amax(-1) <= _ROUND_TRIP_PX) & torch.isfinite(src.detach()).all(-1)
    d_src, d_ideal = src.detach() - src.new_tensor(centre), ideal - ideal.new_tensor(centre)
    same_side = (d_src * d_ideal).sum(-1) >= 0  # a negative Newton root is the mirrored position
    shape = (-1, 1, 1)
    branch = monotone_branch((d_src * d_src).sum(-1), k2.detach().view(shape), k4.detach().view(shape))
    exact = exact & same_side & branch
    inside = ((src.detach()[..., 0] >= -_SLACK_PX) & (src.detach()[..., 0] <= width - 1 + _SLACK_PX)
              & (src.detach()[..., 1] >= -_SLACK_PX) & (src.detach()[..., 1] <= height - 1 + _SLACK_PX))
    valid = (exact & inside).unsqueeze(1).to(dtype)
    return torch.nan_to_num(src, nan=-1e6, posinf=-1e6, neginf=-1e6), valid


def lens_undistortion_grid(
    coefficients, centre, height: int, width: int, *, dtype: torch.dtype = torch.float32, device=None, view=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`undistortion_grid` for the radial lens a_1 .. a_n about ``centre``.

    The lens of :mod:`~lensdist_torch.geometry.radial_lens`; ``centre``: (x, y) in pixels, or None for
    the frame centre. Valid where the inverse is exact and on the lens's monotone branch
    (:func:`~lensdist_torch.geometry.radial_lens.lens_distorted_points`) and inside the distorted frame.

    Returns:
        grid: (1, H, W, 2) pixel coordinates of each ideal pixel in the distorted image.
        valid: (1, 1, H, W) of 0 and 1, ``dtype``.

    Example:
        >>> from lensdist_torch.geometry.frame import half_diagonal
        >>> a = [2e-5 * half_diagonal(32, 48) ** 2]  # eq. 4's k2 = 2e-5 as the lens's a_1
        >>> g1, v1 = lens_undistortion_grid(a, None, 32, 48, dtype=torch.float64)
        >>> g2, v2 = undistortion_grid(2e-5, 0.0, 32, 48, dtype=torch.float64)
        >>> bool((g1 - g2).abs().max() < 1e-6), bool((v1 == v2).all())
        (True, True)
    """
    if not (type(height) is int and type(width) is int and height > 0 and width > 0):
        raise ValueError(f"height and width must be positive ints, got {height!r} and {width!r}")
    view = _check_view(view)
    ideal = pixel_grid(height, width, torch.float64, device)
    if view is not None:
        ideal = (ideal - ideal.new_tensor(view[2:])) / ideal.new_tensor(view[:2])
    src, exact = lens_distorted_points(ideal, coefficients, height, width, centre=centre)
    inside = ((src[..., 0] >= -_SLACK_PX) & (src[..., 0] <= width - 1 + _SLACK_PX)
              & (src[..., 1] >= -_SLACK_PX) & (src[..., 1] <= height - 1 + _SLACK_PX))
    valid = (exact & inside & torch.isfinite(src).all(-1)).reshape(1, 1, height, width).to(dtype)
    return torch.nan_to_num(src, nan=-1e6, posinf=-1e6, neginf=-1e6).to(dtype).reshape(1, height, width, 2), valid


def opencv_undistortion_grid(camera_matrix, dist_coeffs, height: int, width: int, *, dtype: torch.dtype = torch.float32,
                             device=None, view=None) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`undistortion_grid` for an OpenCV camera (K, dist_coeffs: 4, 5 or 8 of them, tangential terms included).

    Each ideal pixel q goes to K distort(K^-1 q) (OpenCV's forward model,
    :func:`~lensdist_torch.geometry.opencv_model.opencv_distort_full`: what
    ``cv2.initUndistortRectifyMap`` with ``newCameraMatrix`` = K computes); valid where the model's
    radial part does not fold between the centre and q's radius
    (:func:`~lensdist_torch.geometry.opencv_model.radial_monotone`) and the sample lies inside the frame.

    Returns:
        grid: (1, H, W, 2) pixel coordinates of each ideal pixel in the distorted image.
        valid: (1, 1, H, W) of 0 and 1, ``dtype``.

    Example:
        >>> K = [[60.0, 0.0, 23.5], [0.0, 60.0, 15.5], [0.0, 0.0, 1.0]]
        >>> grid, valid = opencv_undistortion_grid(K, [0.0] * 5, 32, 48,  # no distortion: every pixel itself
        ...                                        dtype=torch.float64)
        >>> bool((grid[0] - pixel_grid(32, 48, torch.float64)).abs().max() < 1e-12), float(valid.mean())
        (True, 1.0)
    """
    if not (type(height) is int and type(width) is int and height > 0 and width > 0):
        raise ValueError(f"height and width must be positive ints, got {height!r} and {width!r}")
    view = _check_view(view)
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64).reshape(-1)
    ideal = pixel_grid(height, width, torch.float64, device)
    if view is not None:
        ideal = (ideal - ideal.new_tensor(view[2:])) / ideal.new_tensor(view[:2])
    f, c = torch.stack([k[0, 0], k[1, 1]]).to(ideal.device), k[:2, 2].to(ideal.device)
    x = (ideal - c) / f
    src = opencv_distort_full(x, d.to(ideal.device)) * f + c
    inside = ((src[..., 0] >= -_SLACK_PX) & (src[..., 0] <= width - 1 + _SLACK_PX)
              & (src[..., 1] >= -_SLACK_PX) & (src[..., 1] <= height - 1 + _SLACK_PX))
    ok = inside & torch.isfinite(src).all(-1) & radial_monotone((x * x).sum(-1), d.to(ideal.device))
    valid = ok.reshape(1, 1, height, width).to(dtype)
    return torch.nan_to_num(src, nan=-1e6, posinf=-1e6, neginf=-1e6).to(dtype).reshape(1, height, width, 2), valid


def opencv_optimal_view(
    camera_matrix, dist_coeffs, height: int, width: int, *, alpha: float
) -> tuple[float, float, float, float]:
    """:func:`optimal_view` for an OpenCV camera: the frame edges at their converged ideal positions where they invert.

    Example:
        >>> K = [[60.0, 0.0, 23.5], [0.0, 60.0, 15.5], [0.0, 0.0, 1.0]]
        >>> [round(v, 9) + 0.0  # no distortion: the frame itself
        ...  for v in opencv_optimal_view(K, [0.0] * 5, 32, 48, alpha=1.0)]
        [1.0, 1.0, 0.0, 0.0]
    """
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64).reshape(-1)

    def ideal(pts: torch.Tensor) -> torch.Tensor:
        x, ok = opencv_ideal_points(pts, k, d)
        return x[ok]

    return _view(ideal, height, width, alpha, f"the OpenCV camera (dist_coeffs {[round(float(v), 4) for v in d]})",
                 "its model")


def undistort_image(
    img: torch.Tensor, k2, k4, *, mode: str = "bilinear", view=None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Undistort images: I(p) = I_d(distort(p)) for every ideal pixel p (module docstring).

    Args:
        img: (B, C, H, W) distorted images, float or uint8 (uint8 is divided by 255).
        k2: eq. 4's k2 in the images' pixels: a number, or a (1,) or (B,) tensor (a tensor
            that requires grad gets gradients).
        k4: eq. 4's k4, as many values as k2.
        mode: ``grid_sample``'s interpolation, "bilinear" (default), "nearest" or "bicubic".
        view: the output's (sx, sy, tx, ty) (:func:`optimal_view`); None: the input's scale and centre.

    Returns:
        undistorted: (B, C, H, W) float (the input's float dtype, float32 for uint8), 0 outside
            the mask.
        valid: (B, 1, H, W) of 0 and 1: the sample came from inside the distorted image, on eq. 4's
            monotone branch (module docstring).

    Example:
        >>> from lensdist_torch.geometry.distortion import render_distorted
        >>> ideal = torch.rand(2, 3, 40, 56)
        >>> k2, k4 = torch.tensor([2e-5, 0.0]), torch.tensor([0.0, 1e-9])
        >>> out, valid = undistort_image(render_distorted(ideal, k2, k4), k2, k4)
        >>> tuple(out.shape), tuple(valid.shape)
        ((2, 3, 40, 56), (2, 1, 40, 56))
    """
    check_image(img, "img")
    x = img.float() / 255.0 if img.dtype == torch.uint8 else img
    b, _, h, w = x.shape
    if mode not in ("bilinear", "nearest", "bicubic"):
        raise ValueError(f"mode must be 'bilinear', 'nearest' or 'bicubic', got {mode!r}")
    grid, valid = undistortion_grid(k2, k4, h, w, dtype=x.dtype, device=x.device, view=view)
    if grid.shape[0] not in (1, b):
        raise ValueError(f"k2/k4 must hold 1 value or one per image ({b}), got {grid.shape[0]}")
    grid, valid = grid.expand(b, -1, -1, -1), valid.expand(b, -1, -1, -1)
    return sample_at_pixels(x, grid, mode) * valid, valid


class Undistort(nn.Module):
    """Module form of :func:`undistort_image` with fixed coefficients.

    Args:
        k2: eq. 4's k2 in pixels (a number or a (B,) tensor). An ``nn.Parameter`` is kept as a
            parameter (trainable), anything else as a float64 buffer.
        k4: eq. 4's k4, the same way.
        mode: the interpolation of :func:`undistort_image`.

    Example:
        >>> undistort = Undistort(1e-6, 0.0)
        >>> out, valid = undistort(torch.rand(1, 1, 32, 48))
        >>> tuple(out.shape)
        (1, 1, 32, 48)
    """

    def __init__(self, k2, k4, mode: str = "bilinear") -> None:
        super().__init__()
        for name, value in (("k2", k2), ("k4", k4)):
            if isinstance(value, nn.Parameter):
                self.register_parameter(name, value)
            else:
                self.register_buffer(name, torch.as_tensor(value, dtype=torch.float64).reshape(-1).clone())
        self.mode = mode

    def forward(self, img: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C, H, W) distorted -> (undistorted (B, C, H, W), valid (B, 1, H, W))."""
        return undistort_image(img, self.k2, self.k4, mode=self.mode)

    def extra_repr(self) -> str:
        """The coefficients and the mode."""
        return f"k2={self.k2.tolist()}, k4={self.k4.tolist()}, mode={self.mode!r}"
