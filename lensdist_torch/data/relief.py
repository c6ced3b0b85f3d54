"""A scene with relief seen by a pinhole camera looking straight down (docs/method.md, section 7).

The scene is the embedded texture laid on the ground, raised by a smooth height field. A height
is given as a **relief fraction** rho = height / the camera's height above the ground, so the
same field serves every altitude. A camera whose optical axis is vertical sees a point raised by
rho at the place where the flat ground would be seen at

    X_plane = X_c + (X - X_c) / (1 - rho(X)),

X_c being the ground point straight below the camera (the nadir: where the principal point
looks). So the ground point that a pixel sees solves the fixed point

    X = X_c + (1 - rho(X)) (X_plane - X_c),

X_plane being where the pixel would see a flat scene. :func:`relief_samples` solves it by
iteration (the map contracts by about rho times the field's relative slope over the view, a few
percent, so four steps reach 1e-5 of a pixel). Everything follows from that, as a camera draws
it: a rotation about the optical axis keeps X_c and moves no point against the others (no
parallax), a translation moves X_c and gives each point a parallax in proportion to the
baseline and its height, a change of altitude scales X_plane - X_c and gives a radial parallax.
The coordinates may be scaled per axis (scene pixels, or grid_sample units): the equation is
affine per axis.

Two uses, one model. A **sequence** (``synthetic_sequence``) lays the texture on the ground and
samples it where each frame sees the ground (:func:`relief_samples`). A **pair** of the
realistic protocol keeps I1 as rendered and moves I2's samples: :func:`second_view_points` takes
the points where camera 2 would see a flat scene, expressed in I1's frame (the ground
homography applied), and returns where camera 1 sees the scene points that camera 2 sees there.
For a camera 2 whose nadir is at c2 (camera 1's at the origin) the parallax is
rho / (1 - rho) c2 to first order: zero for a pure rotation about the optical axis, in proportion
to the baseline otherwise.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

__all__ = ["HeightField", "draw_height_field", "relief_fraction", "relief_samples", "scaled_field", "second_view_points",
           "homography_view_points"]

N_BUMPS = 4  # Gaussian bumps of a height field
SIGMA_RANGE = (0.15, 0.4)  # bump widths, as a share of the region's half diagonal
ITERATIONS = 4  # fixed-point steps of relief_samples


class HeightField(NamedTuple):
    """A height field: a sum of Gaussian bumps, in relief fractions (height / camera height).

    centres: (K, 2) bump centres (x, y) in the scene's coordinates; sigmas: (K,) their widths;
    weights: (K,) signed peak fractions (a negative one is a hollow), scaled so that the largest
    |rho| over the region drawn is ``relief``.
    """

    centres: torch.Tensor
    sigmas: torch.Tensor
    weights: torch.Tensor


def relief_fraction(field: HeightField, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """rho(x, y): the field at points of any shape (float64 recommended).

    Example:
        >>> f = HeightField(torch.tensor([[0.0, 0.0]]), torch.tensor([1.0]), torch.tensor([0.02]))
        >>> round(float(relief_fraction(f, torch.tensor(0.0), torch.tensor(0.0))), 6)
        0.02
    """
    c = field.centres.to(x.dtype)
    s = field.sigmas.to(x.dtype)
    w = field.weights.to(x.dtype)
    d2 = (x[..., None] - c[:, 0]) ** 2 + (y[..., None] - c[:, 1]) ** 2
    return (w * torch.exp(-d2 / (2 * s * s))).sum(-1)


def draw_height_field(
    generator: torch.Generator, region: tuple[float, float, float, float], relief: float, n_bumps: int = N_BUMPS
) -> HeightField:
    """A random height field over ``region`` (x_lo, x_hi, y_lo, y_hi) whose largest |rho| is ``relief``.

    Bump centres are uniform over the region, widths ~ U[SIGMA_RANGE] x its half diagonal,
    weights ~ U[-1, 1] (hills and hollows); the peak |rho| is measured on a 64 x 64 grid of the
    region and scaled to ``relief`` (0 gives a flat scene).

    Example:
        >>> f = draw_height_field(torch.Generator().manual_seed(0), (0.0, 100.0, 0.0, 80.0), 0.03)
        >>> xs, ys = torch.meshgrid(torch.linspace(0, 100, 64, dtype=torch.float64),
        ...                         torch.linspace(0, 80, 64, dtype=torch.float64), indexing="xy")
        >>> round(float(relief_fraction(f, xs, ys).abs().max()), 6)
        0.03
    """
    if not 0.0 <= relief < 0.5:
        raise ValueError(f"relief must be a fraction of the camera's height in [0, 0.5), got {relief}")
    x_lo, x_hi, y_lo, y_hi = region
    u = torch.rand(n_bumps, 4, generator=generator, dtype=torch.float64)
    centres = torch.stack([x_lo + (x_hi - x_lo) * u[:, 0], y_lo + (y_hi - y_lo) * u[:, 1]], 1)
    half_diag = 0.5 * math.hypot(x_hi - x_lo, y_hi - y_lo)
    sigmas = (SIGMA_RANGE[0] + (SIGMA_RANGE[1] - SIGMA_RANGE[0]) * u[:, 2]) * half_diag
    return scaled_field(HeightField(centres=centres, sigmas=sigmas, weights=2 * u[:, 3] - 1), region, relief)


def scaled_field(field: HeightField, region: tuple[float, float, float, float], relief: float) -> HeightField:
    """``field`` with its weights scaled so that its largest |rho| over ``region`` is ``relief``.

    The peak is measured on a 64 x 64 grid of the region (x_lo, x_hi, y_lo, y_hi); a field that
    is zero there, or ``relief`` 0, gives a flat scene (weights 0).

    Example:
        >>> f = HeightField(torch.tensor([[0.0, 0.0]]), torch.tensor([10.0]), torch.tensor([-5.0]))
        >>> [round(v, 6) for v in scaled_field(f, (-1.0, 1.0, -1.0, 1.0), 0.02).weights.tolist()]
        [-0.02]
    """
    x_lo, x_hi, y_lo, y_hi = region
    xs, ys = torch.meshgrid(
        torch.linspace(x_lo, x_hi, 64, dtype=torch.float64), torch.linspace(y_lo, y_hi, 64, dtype=torch.float64), indexing="xy"
    )
    peak = float(relief_fraction(field, xs, ys).abs().max())
    return field._replace(weights=field.weights.double() * (relief / peak if peak > 0 else 0.0))


def relief_samples(
    x: torch.Tensor, y: torch.Tensor, nadir: tuple[float, float] | torch.Tensor, field: HeightField | None,
    *,
    altitude: float = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ground points seen where a flat scene would be seen at (x, y) (module docstring).

    Args:
        x: the flat scene's sample abscissae (any shape, float64 recommended).
        y: their ordinates, of x's shape.
        nadir: (x_c, y_c), the ground point below the camera, in the same coordinates.
        field: the height field, or None (a flat scene: x, y unchanged).
        altitude: the camera's height over the one the field's fractions refer to: a camera
            twice as high sees every relief fraction halved (rho / altitude).

    Returns:
        The ground points (x', y'), each of x's shape.

    Example:
        >>> f = HeightField(torch.tensor([[0.0, 0.0]]), torch.tensor([1e6]), torch.tensor([0.1]))
        >>> xs, ys = relief_samples(torch.tensor([10.0]), torch.tensor([0.0]), (0.0, 0.0), f)
        >>> round(float(xs), 4)  # a flat rise of 10 %: points seen 10 % nearer the nadir
        9.0
    """
    if field is None:
        return x, y
    field = field._replace(weights=field.weights / altitude)
    xc, yc = float(nadir[0]), float(nadir[1])
    px, py = x - xc, y - yc
    gx, gy = x, y
    for _ in range(ITERATIONS):
        keep = 1.0 - relief_fraction(field, gx, gy)
        gx, gy = xc + keep * px, yc + keep * py
    return gx, gy


def second_view_points(
    x: torch.Tensor, y: torch.Tensor, nadir: tuple[float, float] | torch.Tensor, *, altitude: float, field: HeightField | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where camera 1 sees the scene points that camera 2 sees where it would see a flat scene at (x, y).

    Coordinates are camera 1's (ideal, centred: its nadir at the origin), the field's heights
    fractions of camera 1's height. Camera 2's nadir is ``nadir`` and its height ``altitude``
    times camera 1's (the ground homography's scale), so its relief fractions are rho / altitude.
    The ground point X solves camera 2's fixed point (:func:`relief_samples`); camera 1 sees it
    at X / (1 - rho(X)). A camera 2 with camera 1's nadir and altitude (a pure rotation) gives
    (x, y) back: no parallax.

    Args:
        x: abscissae of the flat scene's points seen by camera 2, in camera 1's frame (any shape).
        y: their ordinates, of x's shape.
        nadir: camera 2's nadir (x_c, y_c) in camera 1's frame.
        altitude: camera 2's height over camera 1's, > 0.
        field: the height field, or None (a flat scene: x, y unchanged).

    Returns:
        Camera 1's points (x1, y1), each of x's shape.

    Example:
        >>> f = HeightField(torch.tensor([[0.0, 0.0]]), torch.tensor([1e6]), torch.tensor([0.02]))
        >>> x, y = torch.tensor([30.0], dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
        >>> x1, _ = second_view_points(x, y, (10.0, 0.0), altitude=1.0, field=f)
        >>> round(float(x1 - 30.0), 4)  # rho / (1 - rho) times the nadir's 10 px
        0.2041
        >>> x1, _ = second_view_points(x, y, (0.0, 0.0), altitude=1.0, field=f)
        >>> round(float(x1 - 30.0), 6)  # the same nadir: a rotation, no parallax
        0.0
    """
    if field is None:
        return x, y
    if not (math.isfinite(altitude) and altitude > 0):
        raise ValueError(f"altitude must be a positive finite ratio of heights, got {altitude}")
    gx, gy = relief_samples(x, y, nadir, field, altitude=altitude)
    keep = 1.0 - relief_fraction(field, gx, gy)
    return gx / keep, gy / keep


def homography_view_points(
    a: torch.Tensor, x: torch.Tensor, y: torch.Tensor, field: HeightField | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`second_view_points` for a pair whose ground homography is ``a``.

    ``a`` (3, 3) maps camera 2's ideal points to camera 1's, both centred on camera 1's nadir
    (the protocol's centred motion). Camera 2's nadir is a (0, 0) and its height over camera 1's
    sqrt |det a| (the ground scale), so a rotation about the optical axis moves nothing.

    Args:
        a: (3, 3) float64 centred homography, camera 2 -> camera 1.
        x: camera 2's ideal abscissae, centred (any shape; float64 recommended).
        y: their ordinates, of x's shape.
        field: the height field in camera 1's centred frame, or None (a plane).

    Returns:
        Camera 1's points (x1, y1), each of x's shape.

    Example:
        >>> f = HeightField(torch.tensor([[0.0, 0.0]]), torch.tensor([1e6]), torch.tensor([0.02]))
        >>> shift = torch.tensor([[1.0, 0.0, 10.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> x1, _ = homography_view_points(shift, torch.tensor([20.0], dtype=torch.float64), torch.zeros(1, dtype=torch.float64), f)
        >>> round(float(x1 - 30.0), 4)  # A moves the point to 30; rho / (1 - rho) times the nadir's 10 px
        0.2041
    """
    den = a[2, 0] * x + a[2, 1] * y + a[2, 2]
    nadir = (float(a[0, 2] / a[2, 2]), float(a[1, 2] / a[2, 2]))
    altitude = abs(float(torch.linalg.det(a[:2, :2] / a[2, 2]))) ** 0.5
    return second_view_points((a[0, 0] * x + a[0, 1] * y + a[0, 2]) / den, (a[1, 0] * x + a[1, 1] * y + a[1, 2]) / den,
                              nadir, altitude=altitude, field=field)
