"""A radial lens about a distortion centre: the homography model's lens, and eq. 4 as its special case.

The lens maps a distorted pixel p to its ideal point

    u(p) = c + (p - c) (1 + a_1 r^2 + a_2 r^4 + ... + a_n r^(2n)),   r = |p - c| / R,

c the distortion centre (the frame centre unless given), R the frame's half diagonal
(:func:`~lensdist_torch.geometry.frame.half_diagonal`). With n = 2 and c the frame centre this is
eq. 4 with a_1 = k2 R^2, a_2 = k4 R^4 (docs/method.md, sections 6 and 12). The coefficients are
those of the normalised radius, so they hold for the same camera at any frame size (the centre
scales with the frame).

The map inverts where r (1 + a_1 r^2 + ...) still grows (:func:`monotone_radius`);
:func:`lens_distorted_points` inverts it there by Newton's method on the radius.
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.geometry.distortion import distortion_center
from lensdist_torch.geometry.frame import half_diagonal

__all__ = ["lens_factor", "lens_factor_derivative", "lens_ideal_points", "lens_distorted_points", "lens_inverts",
           "monotone_radius"]

#: The normalised radius :func:`monotone_radius` searches up to (the frame's corners lie at 1 about its centre).
MAX_RADIUS = 1.5


def lens_factor(r2: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """1 + a_1 r^2 + ... + a_n r^(2n) by Horner's rule."""
    out = torch.zeros_like(r2)
    for k in range(a.shape[-1] - 1, -1, -1):
        out = (out + a[k]) * r2
    return 1 + out


def lens_factor_derivative(r2: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """d/d(r^2) of :func:`lens_factor`: a_1 + 2 a_2 r^2 + ... + n a_n r^(2n - 2), by Horner's rule."""
    out = torch.zeros_like(r2)
    for k in range(a.shape[-1] - 1, 0, -1):
        out = (out + (k + 1) * a[k]) * r2
    return out + a[0]


def _centre(points: torch.Tensor, height: int, width: int, centre) -> torch.Tensor:
    return points.new_tensor(distortion_center(height, width) if centre is None else [float(v) for v in centre])


def lens_ideal_points(points: torch.Tensor, coefficients, height: int, width: int, *, centre=None) -> torch.Tensor:
    """Ideal pixels of (..., 2) distorted pixels under the lens a_1 .. a_n about ``centre`` (module docstring).

    ``centre``: the distortion centre (x, y) in pixels; the frame centre when None.

    Example:
        >>> p = torch.tensor([[0.0, 0.0], [4.5, 3.5]], dtype=torch.float64)  # a corner and the centre of 8 x 10
        >>> lens_ideal_points(p, [0.1], 8, 10).round(decimals=4).tolist()  # r = 1 at the corner: 10 % further out
        [[-0.45, -0.35], [4.5, 3.5]]
        >>> lens_ideal_points(p, [0.1], 8, 10, centre=(0.0, 0.0))[0].tolist()  # the centre stays put
        [0.0, 0.0]
    """
    c = _centre(points, height, width, centre)
    big_r = half_diagonal(height, width)
    v = (points - c) / big_r
    return c + big_r * v * lens_factor((v * v).sum(-1, keepdim=True), torch.as_tensor(coefficients, dtype=points.dtype))


def monotone_radius(a: torch.Tensor) -> float:
    """The normalised radius up to which r (1 + a_1 r^2 + ...) grows (the map inverts there), at most ``MAX_RADIUS``.

    Example:
        >>> monotone_radius(torch.tensor([0.3], dtype=torch.float64))  # barrel in this sense never folds
        inf
        >>> round(monotone_radius(torch.tensor([-0.5], dtype=torch.float64)), 3)  # 1 - 1.5 r^2 = 0 at r = 0.816
        0.817
    """
    r = torch.linspace(0, MAX_RADIUS, 3001, dtype=torch.float64)[:, None]
    g = (r * lens_factor(r * r, torch.as_tensor(a, dtype=torch.float64)))[:, 0]
    falls = (g[1:] <= g[:-1]).nonzero()
    return float(r[int(falls[0, 0]), 0]) if len(falls) else math.inf


def lens_inverts(points: torch.Tensor, coefficients, height: int, width: int, *, centre=None) -> torch.Tensor:
    """(...,) bool: where the lens's map inverts, the pixels (..., 2) closer to its centre than :func:`monotone_radius`.

    Example:
        >>> p = torch.tensor([[4.5, 3.5], [0.0, 0.0]], dtype=torch.float64)  # the centre and a corner of 8 x 10 (r = 1)
        >>> lens_inverts(p, [-0.5], 8, 10).tolist()  # it folds at r = 0.816
        [True, False]
    """
    a = torch.as_tensor(coefficients, dtype=torch.float64)
    c = _centre(points, height, width, centre)
    return (points - c).norm(dim=-1) / half_diagonal(height, width) < monotone_radius(a)


def lens_distorted_points(ideal: torch.Tensor, coefficients, height: int, width: int, *, centre=None,
                          iterations: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    """The distorted pixels of (..., 2) ideal pixels: :func:`lens_ideal_points` inverted on its monotone branch.

    Newton's method on the normalised radius r of r f(r^2) = rho (rho the ideal point's), from r =
    rho, ``iterations`` steps, each kept within [0, the monotone radius].

    Returns:
        (points, ok): the distorted pixels (..., 2) and where they are exact ((...,) bool: a round
        trip through the lens within 0.01 px, on the monotone branch).

    Example:
        >>> p = torch.tensor([[1.0, 2.0], [7.0, 5.0]], dtype=torch.float64)
        >>> q = lens_ideal_points(p, [0.1, 0.02], 8, 10, centre=(5.0, 3.0))
        >>> back, ok = lens_distorted_points(q, [0.1, 0.02], 8, 10, centre=(5.0, 3.0))
        >>> bool((back - p).abs().max() < 1e-9), ok.tolist()
        (True, [True, True])
    """
    a = torch.as_tensor(coefficients, dtype=ideal.dtype, device=ideal.device)
    c = _centre(ideal, height, width, centre)
    big_r = half_diagonal(height, width)
    d = (ideal - c) / big_r
    rho = d.norm(dim=-1)
    top = min(monotone_radius(a.detach().cpu().double()), MAX_RADIUS)
    r = rho.clamp(max=top)
    for _ in range(iterations):
        s = r * r
        g = r * lens_factor(s, a) - rho
        dg = lens_factor(s, a) + 2 * s * lens_factor_derivative(s, a)
        r = (r - g / torch.where(dg.abs() > 1e-12, dg, torch.ones_like(dg))).clamp(0.0, top)
    scale = torch.where(rho > 0, r / torch.where(rho > 0, rho, torch.ones_like(rho)), torch.ones_like(rho))
    out = c + big_r * d * scale[..., None]
    ok = ((lens_ideal_points(out, a, height, width, centre=c.tolist()) - ideal).abs().amax(-1) <= 1e-2) & (r < top)
    return out, ok
