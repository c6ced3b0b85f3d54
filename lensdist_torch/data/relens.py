"""Real frames seen through a known lens: undistorted by their camera's calibration, re-distorted by eq. 4.

A real camera's calibration (OpenCV's K and radial coefficients, e.g. from a chessboard) says where
each ideal ray lands in its frames. Sampling a frame there gives the picture an ideal pinhole
camera with the same focal length and its principal point at the frame's centre would have taken;
sampling that picture through eq. 4 gives the same real scene, light, noise and motion as seen
through the lens (k2, k4). The composition is one backward map per output pixel q:

    p = eq. 4 (q; k2, k4)            the ideal pixel (about the frame centre)
    x = (p - c) / f                  its ray (f = (fx + fy) / 2, c the frame centre)
    s = K opencv_distort(x)          where the real camera recorded that ray

and one bilinear sample per frame at the source's resolution, then the area resampling of
:func:`~lensdist_torch.core.images.resize_to` down to ``size`` (so the output is not aliased). The
lens of the output is (k2, k4) exactly, up to the calibration's own error (a chessboard calibration
of 0.5 px RMS). A wide-angle source seen through a milder lens fills every output pixel: no empty
borders, no guessed content.

Real footage with a published calibration of a lens far outside the classes' range thus becomes real footage of any lens within it: the benchmark that checks ``lensdist
calibrate`` against a known truth on real images (``benchmarks/bench_real_relensed.py``).

Example:
    >>> import torch
    >>> K = torch.tensor([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]], dtype=torch.float64)
    >>> frames = torch.rand(2, 1, 96, 128, generator=torch.Generator().manual_seed(0))
    >>> same = relens_frames(frames, K, torch.zeros(5), k2=0.0, k4=0.0)  # no lens on either side
    >>> bool(torch.allclose(same.frames, frames, atol=1e-5)), same.valid_fraction
    (True, 1.0)
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from lensdist_torch.core.images import check_image, resize_to
from lensdist_torch.geometry.distortion import distortion_center, distortion_grid, sample_at_pixels
from lensdist_torch.geometry.opencv_model import opencv_distort_normalized, radial_monotone

__all__ = ["RelensedFrames", "relens_frames", "relens_map"]


class RelensedFrames(NamedTuple):
    """What :func:`relens_frames` returns.

    Attributes:
        frames: (N, C, h, w) float images in [0, 1] at ``size``, seen through (k2, k4).
        k2: eq. 4's k2 at ``size`` (the user's pixels of the output), as given.
        k4: eq. 4's k4 at ``size``.
        valid_fraction: the share of output pixels whose ray the source frame recorded (1.0 when
            the source's field of view covers the output's).

    Example:
        >>> K = torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]], dtype=torch.float64)
        >>> out = relens_frames(torch.full((1, 1, 48, 64), 0.5), K, torch.zeros(5), k2=1e-4, k4=0.0)
        >>> out.valid_fraction < 1.0, out.k2  # a barrel lens sees past a pinhole source's corners
        (True, 0.0001)
    """

    frames: torch.Tensor
    k2: float
    k4: float
    valid_fraction: float


def _calibration(camera_matrix, dist_coeffs) -> tuple[torch.Tensor, torch.Tensor]:
    k = torch.as_tensor(camera_matrix, dtype=torch.float64)
    d = torch.as_tensor(dist_coeffs, dtype=torch.float64).reshape(-1)
    if k.shape != (3, 3) or not bool(torch.isfinite(k).all()) or float(k[0, 0]) <= 0 or float(k[1, 1]) <= 0:
        raise ValueError("camera_matrix must be a finite 3 x 3 matrix with positive fx, fy")
    if d.numel() not in (4, 5, 8) or not bool(torch.isfinite(d).all()):
        raise ValueError(f"dist_coeffs must hold 4, 5 or 8 finite values (OpenCV's order), got {d.numel()}")
    radial = torch.zeros(8 if d.numel() == 8 else 5, dtype=torch.float64)
    radial[: d.numel()] = d
    radial[2:4] = 0  # tangential terms are not modelled: a chessboard calibration's are ~1e-5 (< 0.02 px)
    return k, radial


def relens_map(
    height: int, width: int, camera_matrix, dist_coeffs, *, k2: float, k4: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the real camera recorded each pixel of the relensed frame, at the source's size.

    Args:
        height: the source frames' height (the calibration's image size).
        width: their width.
        camera_matrix: the source camera's K (3 x 3, pixels).
        dist_coeffs: its OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]); p1, p2 are ignored.
        k2: eq. 4's k2 of the new lens at the source's size.
        k4: its k4.

    Returns:
        (H, W, 2) float64 source pixels (x, y), and an (H, W) bool mask: inside the source frame
        and on the calibration's monotone branch (where its model does not fold back).

    Example:
        >>> K = torch.tensor([[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]], dtype=torch.float64)
        >>> from lensdist_torch.geometry.frame import pixel_grid
        >>> src, ok = relens_map(96, 128, K, torch.zeros(5), k2=0.0, k4=0.0)
        >>> bool(torch.allclose(src, pixel_grid(96, 128, torch.float64))), bool(ok.all())
        (True, True)
    """
    k, d = _calibration(camera_matrix, dist_coeffs)
    p = distortion_grid([k2], [k4], height, width, dtype=torch.float64)[0]  # eq. 4: each pixel's ideal point
    x = (p - p.new_tensor(distortion_center(height, width))) / ((k[0, 0] + k[1, 1]) / 2)
    src = opencv_distort_normalized(x, d) * torch.stack([k[0, 0], k[1, 1]]) + k[:2, 2]
    inside = (src[..., 0] >= 0) & (src[..., 0] <= width - 1) & (src[..., 1] >= 0) & (src[..., 1] <= height - 1)
    return src, inside & radial_monotone((x * x).sum(-1), d)  # the calibration's model only where it does not fold


def relens_frames(
    frames: torch.Tensor,
    camera_matrix,
    dist_coeffs,
    *,
    k2: float,
    k4: float,
    size: tuple[int, int] | None = None,
) -> RelensedFrames:
    """Real frames undistorted by their calibration and re-distorted by eq. 4 (module docstring).

    Args:
        frames: (N, C, H, W) float frames in [0, 1] at the calibration's image size.
        camera_matrix: the source camera's K (3 x 3).
        dist_coeffs: its OpenCV coefficients.
        k2: eq. 4's k2 of the new lens, in the pixels of ``size``.
        k4: its k4, in the pixels of ``size``.
        size: (h, w) of the output (``resize_to``: a centre crop to its aspect, then area
            resampling); the source's size when None.

    Returns:
        :class:`RelensedFrames`. Pixels whose ray the source did not record are 0.

    Raises:
        ValueError: bad frames, calibration, coefficients or size (one line, naming the argument).
        TypeError: frames that are not float.

    Example:
        >>> K = torch.tensor([[70.0, 0, 79.5], [0, 70.0, 59.5], [0, 0, 1]], dtype=torch.float64)
        >>> frames = torch.rand(3, 1, 120, 160, generator=torch.Generator().manual_seed(0))
        >>> out = relens_frames(frames, K, [-0.23, 0.06, 0, 0, -0.0075], k2=1e-5, k4=0.0, size=(60, 80))
        >>> tuple(out.frames.shape), out.k2, out.valid_fraction  # a wide source fills the milder lens' view
        ((3, 1, 60, 80), 1e-05, 1.0)
    """
    frames = check_image(frames, "frames")
    if not frames.is_floating_point():
        raise TypeError(f"frames must be float images in [0, 1], got {frames.dtype}")
    h_src, w_src = frames.shape[-2:]
    h, w = (h_src, w_src) if size is None else (int(size[0]), int(size[1]))
    if h < 2 or w < 2:
        raise ValueError(f"size must be two integers >= 2, got {size}")
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (k2, k4)):
        raise ValueError(f"k2 and k4 must be finite numbers, got {k2!r}, {k4!r}")
    # the output's pixels are the source's scaled by s (after resize_to's centre crop to the aspect)
    s = max(h / h_src, w / w_src)
    src, ok = relens_map(h_src, w_src, camera_matrix, dist_coeffs, k2=k2 * s**2, k4=k4 * s**4)
    out = sample_at_pixels(frames.double(), src[None].expand(frames.shape[0], -1, -1, -1)) * ok
    valid = resize_to(ok.double()[None, None], h, w)
    return RelensedFrames(
        frames=resize_to(out, h, w).clamp(0, 1).to(frames.dtype), k2=float(k2), k4=float(k4),
        valid_fraction=float((valid > 0.999).double().mean()))
