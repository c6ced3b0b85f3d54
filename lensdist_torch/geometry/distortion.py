"""Radial lens distortion (paper eq. 4, docs/method.md, section 6): the model, Delta metrics, classes.

    p = p0 + (1 + k2 r^2 + k4 r^4) (p_d - p0),   r = ||p_d - p0||,   p0 = ((W-1)/2, (H-1)/2)

p is the ideal point, p_d the point in the distorted image. A distorted image is rendered by a
backward warp, I_d(p_d) = I(p(p_d)): one ``grid_sample`` per image. All coordinates are pixels
with centres at integer positions (``align_corners=True``).

The model's two primitives, used by every module that applies eq. 4 (in pixels or in the
normalised frame, where a = k2 R^2 and b = k4 R^4 take the place of k2, k4):
:func:`radial_factor`, the factor 1 + k2 r^2 + k4 r^4, and :func:`radial_inverse`, the
distorted radius r of an ideal radius rho = r (1 + k2 r^2 + k4 r^4) by Newton.

The classes: :func:`distortion_class` and :func:`estimated_class` return an index into
``CLASS_LABELS``, the last one (``REJECT``) the class R, "no visible distortion".

Example:
    >>> CLASS_LABELS, CLASS_LABELS[REJECT]
    (('1', '2', '3', '4', 'R'), 'R')
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.frame import half_diagonal, pixel_grid, to_normalized

__all__ = [
    "CLASS_LABELS",
    "REJECT",
    "METRICS",
    "distortion_center",
    "from_normalized",
    "radial_factor",
    "radial_derivative",
    "radial_inverse",
    "pixel_grid",
    "undistort_points",
    "distort_points",
    "distortion_grid",
    "pixel_offsets",
    "delta_max",
    "delta_avg",
    "delta_metric",
    "paper_frame_delta_avg",
    "delta_top",
    "distortion_class",
    "estimated_class",
    "class_bounds",
    "distortion_type",
    "to_normalized",
    "sample_at_pixels",
    "render_distorted",
    "fit_eq4",
]

#: Class labels; index 4 is the reject class R (no visible distortion).
CLASS_LABELS = ("1", "2", "3", "4", "R")
REJECT = 4
N_CLASSES = 4  # the distortion classes 1-4: equal-width bins of ]0, Delta_top]; R besides
METRICS = ("delta_avg", "delta_max")


def distortion_center(height: int, width: int) -> tuple[float, float]:
    """p0 = ((W - 1) / 2, (H - 1) / 2): the image centre in pixel coordinates."""
    return (width - 1) / 2.0, (height - 1) / 2.0


def _coefficients(k2, k4, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    k2 = torch.as_tensor(k2, dtype=like.dtype, device=like.device).reshape(-1)
    k4 = torch.as_tensor(k4, dtype=like.dtype, device=like.device).reshape(-1)
    if k2.shape != k4.shape:
        raise ValueError(f"k2 and k4 must have the same number of elements, got {k2.numel()} and {k4.numel()}")
    if not (torch.isfinite(k2).all() and torch.isfinite(k4).all()):
        raise ValueError("k2 and k4 must be finite")
    return k2, k4


def radial_factor(r2: torch.Tensor, k2, k4) -> torch.Tensor:
    """Eq. 4's factor 1 + k2 r^2 + k4 r^4 at squared radii ``r2``.

    k2, k4 broadcast against r2. The ideal offset from p0 is the distorted offset times this
    factor.

    Example:
        >>> radial_factor(torch.tensor([0.0, 100.0], dtype=torch.float64), 1e-3, 1e-6).tolist()  # 1 + 0.1 + 0.01
        [1.0, 1.11]
    """
    return 1.0 + k2 * r2 + k4 * r2 * r2


def radial_derivative(r2: torch.Tensor, k2, k4) -> torch.Tensor:
    """d/dr of r (1 + k2 r^2 + k4 r^4) = 1 + 3 k2 r^2 + 5 k4 r^4 at squared radii ``r2``.

    Eq. 4 is invertible along a ray while it stays positive.
    """
    return 1.0 + 3.0 * k2 * r2 + 5.0 * k4 * r2 * r2


def radial_inverse(rho2: torch.Tensor, k2, k4, iterations: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4 inverted on the radius: (r, rho) with rho = r (1 + k2 r^2 + k4 r^4), rho = sqrt(rho2).

    Newton from r = rho, ``iterations`` steps, differentiable. Where rho2 = 0 (the centre, whose
    offset is 0) rho is taken as 1 so that r / rho, the factor from an ideal offset to its
    distorted one, stays finite. Where the model is not invertible (strongly negative
    coefficients) r is the Newton iterate.

    Example:
        >>> r, rho = radial_inverse(torch.tensor([101.0**2], dtype=torch.float64), 1e-6, 0.0)
        >>> round(float(r), 9), float(rho)  # 100 (1 + 1e-6 100^2) = 101
        (100.0, 101.0)
    """
    rho = torch.sqrt(rho2 + (rho2 == 0).to(rho2.dtype))
    r = rho
    for _ in range(iterations):
        r2 = r * r
        r = r - (r * radial_factor(r2, k2, k4) - rho) / radial_derivative(r2, k2, k4)
    return r, rho


def undistort_points(points: torch.Tensor, k2, k4, center: tuple[float, float]) -> torch.Tensor:
    """Eq. 4: distorted points p_d (B, ..., 2) -> ideal points p, per-pair (k2, k4) of shape (B,).

    Example:
        >>> c = distortion_center(320, 424)  # (211.5, 159.5)
        >>> p_d = torch.tensor([[[c[0] + 100, c[1]]]], dtype=torch.float64)  # 100 px right of p0
        >>> [round(v, 6) for v in undistort_points(p_d, [1e-6], [0.0], c)[0, 0].tolist()]  # 100 (1 + 1e-6 100^2) = 101
        [312.5, 159.5]
    """
    k2, k4 = _coefficients(k2, k4, points)
    shape = (-1,) + (1,) * (points.dim() - 1)
    c = points.new_tensor(center)
    d = points - c
    r2 = (d * d).sum(-1, keepdim=True)
    return c + radial_factor(r2, k2.view(shape), k4.view(shape)) * d


def distort_points(points: torch.Tensor, k2, k4, center: tuple[float, float], *, iterations: int = 8) -> torch.Tensor:
    """Inverse of eq. 4 by Newton on the radius: ideal points p (B, ..., 2) -> distorted p_d.

    :func:`radial_inverse` on the radius; differentiable. Accurate to well below 1e-6 px over
    the coefficient ranges of docs/method.md, section 6 (the tests check it); where the model
    is not invertible (strongly negative coefficients) the result is the Newton iterate.

    Example:
        >>> c, p = distortion_center(320, 424), torch.tensor([[[10.0, 20.0], [300.0, 200.0]]], dtype=torch.float64)
        >>> p_d = distort_points(p, [1e-6], [1e-11], c)  # barrel: drawn towards p0
        >>> back = undistort_points(p_d, [1e-6], [1e-11], c)  # eq. 4 returns the ideal points
        >>> p_d[0, 0].round(decimals=2).tolist(), bool(torch.allclose(back, p, atol=1e-4))
        ([24.64, 30.13], True)
    """
    k2, k4 = _coefficients(k2, k4, points)
    shape = (-1,) + (1,) * (points.dim() - 1)
    c = points.new_tensor(center)
    d = points - c
    r, rho = radial_inverse((d * d).sum(-1, keepdim=True), k2.view(shape), k4.view(shape), iterations)
    return c + d * (r / rho)


def distortion_grid(k2, k4, height: int, width: int, *, dtype=torch.float32, device=None) -> torch.Tensor:
    """Ideal coordinates of every distorted pixel: (B, H, W, 2) in pixels (x, y).

    Example:
        >>> g = distortion_grid([0.0, 1e-6], [0.0, 0.0], 320, 424)  # without distortion each pixel is its own place
        >>> tuple(g.shape), g[0, 0, 0].tolist(), [round(v, 2) for v in g[1, 0, 0].tolist()]  # barrel: outside
        ((2, 320, 424, 2), [0.0, 0.0], [-14.84, -11.19])
    """
    grid = pixel_grid(height, width, dtype, device)
    k2, k4 = _coefficients(k2, k4, grid)
    pts = grid.expand(k2.numel(), height, width, 2)
    return undistort_points(pts, k2, k4, distortion_center(height, width))


def from_normalized(ab: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 4's (k2, k4) from the normalised coefficients (a, b) = (k2 R^2, k4 R^4), R the half diagonal.

    The self-calibration fits (a, b) (``SelfCalInfo.ab``, ``planar_ab``, ``relief_ab``): both are
    then the offsets, as shares of R, that eq. 4's two terms give at the corners.

    Example:
        >>> k2, k4 = from_normalized(torch.tensor([[0.25, 0.0]], dtype=torch.float64), 320, 424)
        >>> round(float(k2[0]) * half_diagonal(320, 424) ** 2, 6), float(k4[0])  # R = 264.9 px
        (0.25, 0.0)
    """
    r = half_diagonal(height, width)
    return ab[..., 0] / r**2, ab[..., 1] / r**4


def pixel_offsets(k2, k4, height: int, width: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """delta(p_d) = ||p - p_d|| = |k2 r^3 + k4 r^5| at every pixel centre: (B, H, W).

    Example:
        >>> off = pixel_offsets([1e-6], [0.0], 320, 424)  # 1e-6 r^3: 0 at p0, largest at the corners
        >>> tuple(off.shape), round(float(off[0, 0, 0]), 2), round(float(off.max()), 2)
        ((1, 320, 424), 18.59, 18.59)
    """
    grid = pixel_grid(height, width, dtype, device)
    k2, k4 = _coefficients(k2, k4, grid)
    x0, y0 = distortion_center(height, width)
    r2 = (grid[..., 0] - x0) ** 2 + (grid[..., 1] - y0) ** 2
    r = torch.sqrt(r2)
    return (k2.view(-1, 1, 1) * r2 * r + k4.view(-1, 1, 1) * r2 * r2 * r).abs()


def delta_max(k2, k4, height: int, width: int) -> torch.Tensor:
    """Delta_max: the largest pixel offset over all pixel centres, (B,) float64.

    Example:
        >>> [round(float(d), 1) for d in delta_max([0.0, 2.5e-6], [0.0, 2.5e-11], 320, 424)]  # none; the top
        [0.0, 79.1]
    """
    return pixel_offsets(k2, k4, height, width).flatten(1).amax(1)


def delta_avg(k2, k4, height: int, width: int) -> torch.Tensor:
    """Delta_avg: the mean pixel offset over all pixel centres, (B,) float64.

    Example:
        >>> [round(float(d), 2) for d in delta_avg([0.0, 1e-6, 2.5e-6], [0.0, 0.0, 2.5e-11], 320, 424)]
        [0.0, 4.19, 14.37]
    """
    return pixel_offsets(k2, k4, height, width).flatten(1).mean(1)


def delta_metric(k2, k4, height: int, width: int, *, metric: str) -> torch.Tensor:
    """``delta_avg`` or ``delta_max`` (``metric``, by name) of the lenses ``k2``, ``k4`` at ``height`` x ``width``."""
    if metric == "delta_avg":
        return delta_avg(k2, k4, height, width)
    if metric == "delta_max":
        return delta_max(k2, k4, height, width)
    raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")


def delta_top(metric: str, config: LensdistConfig) -> float:
    """The metric at the largest coefficients of ``config`` at its analysis size.

    The top of the class range: 79.1 px for Delta_max, 14.4 px for Delta_avg at 320 x 424.

    Example:
        >>> [round(delta_top(m, LensdistConfig()), 1) for m in ("delta_max", "delta_avg")]
        [79.1, 14.4]
    """
    d = config.distortion
    return _delta_top(metric, float(d.k2_max), float(d.k4_max), *map(int, config.image.size))


@functools.lru_cache(maxsize=64)
def _delta_top(metric: str, k2: float, k4: float, h: int, w: int) -> float:
    """:func:`delta_top`'s value, once per lens and size: a whole frame's offsets each time it is asked."""
    return float(delta_metric([k2], [k4], h, w, metric=metric)[0])


def distortion_class(delta: torch.Tensor, top: float, n_classes: int = N_CLASSES) -> torch.Tensor:
    """Class index of a true Delta: 0..n-1 for the equal-width bins of ]0, top], ``REJECT`` for 0.

    Values above ``top`` fall into the last class.

    Example:
        >>> idx = distortion_class(torch.tensor([0.0, 1.0, 5.0, 14.4, 20.0]), top=14.4)  # bins of 3.6
        >>> idx.tolist(), [CLASS_LABELS[i] for i in idx]
        ([4, 0, 1, 3, 3], ['R', '1', '2', '4', '4'])
    """
    delta = torch.as_tensor(delta, dtype=torch.float64)
    if not math.isfinite(top) or top <= 0:
        raise ValueError(f"top must be a positive number, got {top!r}")
    if bool((delta < 0).any()) or not bool(torch.isfinite(delta).all()):
        raise ValueError("delta must be finite and non-negative")
    idx = torch.ceil(delta / (top / n_classes)).long() - 1
    idx = idx.clamp(0, n_classes - 1)
    return torch.where(delta == 0, torch.full_like(idx, REJECT), idx)


def estimated_class(
    delta: torch.Tensor, delta_avg_estimate: torch.Tensor, *, metric: str, config: LensdistConfig,
    threshold: float | None = None,
) -> torch.Tensor:
    """The class of an *estimated* Delta.

    The bin of ``delta`` (of ``metric``), and ``REJECT`` ("no visible distortion") where the
    estimated Delta_avg is below ``threshold`` or not finite. The one labelling rule of every
    estimator (self-calibration, regression, the sequence paths) and of ``analyze``.

    Args:
        delta: (B,) estimates of ``metric`` (px at the analysis size).
        delta_avg_estimate: (B,) the same pairs' estimated Delta_avg, which decides R.
        metric: ``"delta_avg"`` or ``"delta_max"`` (the bins' range).
        config: the classes' range (Delta_top) and the default threshold.
        threshold: the R threshold (px at 320 x 424); default one pair's,
            ``config.analysis.no_distortion_px`` (a sequence's is ``config.calibration``'s).

    Example:
        >>> d = torch.tensor([0.1, 5.0, 5.0])  # Delta_avg estimates (px at 320 x 424), the last one not finite:
        >>> estimated_class(d, torch.tensor([0.1, 5.0, float("nan")]), metric="delta_avg",
        ...                 config=LensdistConfig()).tolist()
        [4, 1, 4]
    """
    t = config.analysis.no_distortion_px if threshold is None else threshold
    delta = torch.as_tensor(delta, dtype=torch.float64)
    d_avg = torch.as_tensor(delta_avg_estimate, dtype=torch.float64)
    none = ~torch.isfinite(d_avg) | ~torch.isfinite(delta) | (d_avg < t)
    top = delta_top(metric, config)
    label = distortion_class(torch.where(none, top, delta).clamp_min(1e-12), top, N_CLASSES)
    return torch.where(none, torch.full_like(label, REJECT), label)


def paper_frame_delta_avg(k2: float, k4: float, size: tuple[int, int], config: LensdistConfig) -> float:
    """Delta_avg at the paper's frame (``config.image.size``) of the lens (k2, k4) of a ``size`` frame.

    The same normalised lens (a = k2 R^2, b = k4 R^4, R the half diagonal): the Delta whose class
    ``lensdist calibrate`` and ``analyze`` report for coefficients in a user's pixels.
    """
    hc, wc = config.image.size
    ratio = half_diagonal(hc, wc) / half_diagonal(*size)
    return float(delta_avg([k2 / ratio**2], [k4 / ratio**4], hc, wc)[0])


def class_bounds(
    label: str, metric: str, config: LensdistConfig, threshold: float | None = None
) -> tuple[float, float]:
    """The Delta (of ``metric``) interval ]lo, hi] that :func:`estimated_class` labels ``label``.

    R is [0, ``threshold``[ (of Delta_avg; default ``analysis.no_distortion_px``); class i of n
    is ](i - 1) w, i w] with w = top / n, class 1 starting at the R threshold and the last class
    open above (a Delta beyond the range is the last class).

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> [round(x, 2) for x in class_bounds("2", "delta_avg", LensdistConfig())]
        [3.59, 7.18]
    """
    t = config.analysis.no_distortion_px if threshold is None else threshold
    if label == CLASS_LABELS[REJECT]:
        return 0.0, t
    n, w = N_CLASSES, delta_top(metric, config) / N_CLASSES
    i = CLASS_LABELS.index(label) + 1
    lo = max((i - 1) * w, t) if i == 1 else (i - 1) * w
    return lo, (math.inf if i == n else i * w)


def sample_at_pixels(img: torch.Tensor, points: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """Sample (B, C, h, w) images at pixel coordinates (B, H, W, 2); zeros outside."""
    h, w = img.shape[-2:]
    grid = to_normalized(points.to(img.dtype), h, w)
    return F.grid_sample(img, grid, mode=mode, padding_mode="zeros", align_corners=True)


def render_distorted(img: torch.Tensor, k2, k4) -> torch.Tensor:
    """A distorted image: I_d(p_d) = I(p(p_d)) for (B, C, H, W) images and (B,) coefficients.

    Example:
        >>> img = torch.rand(2, 1, 32, 48, generator=torch.Generator().manual_seed(0))
        >>> out = render_distorted(img, [0.0, 1e-3], [0.0, 0.0])  # the first one undistorted
        >>> bool(torch.allclose(out[0], img[0], atol=1e-5)), float(out[1, 0, 0, 0])  # a corner sees outside: 0
        (True, 0.0)
    """
    b, _, h, w = img.shape
    grid = distortion_grid(k2, k4, h, w, dtype=img.dtype, device=img.device)
    if grid.shape[0] != b:
        raise ValueError(f"k2/k4 must have one value per image: {grid.shape[0]} for a batch of {b}")
    return sample_at_pixels(img, grid)


def distortion_type(a: float, b: float) -> str | None:
    """"barrel", "pincushion" or "mustache" of eq. 4 with normalised coefficients (a, b) = (k2 R^2, k4 R^4).

    The ideal point lies at u_d (1 + a |u_d|^2 + b |u_d|^4): its radial offset, divided by
    |u_d|^3, is a + b |u_d|^2, linear in |u_d|^2, so its sign over the frame (|u_d| in ]0, 1],
    R the half diagonal) is that of a and of a + b. Outward (>= 0 everywhere) is **barrel**: the
    lens drew every point nearer the centre than its ideal place; inward is **pincushion**; a
    sign change inside the frame is **mustache**. None for a = b = 0 or non-finite input.

    Example:
        >>> distortion_type(0.1, 0.0), distortion_type(-0.05, 0.01), distortion_type(0.1, -0.3)
        ('barrel', 'pincushion', 'mustache')
    """
    if not (math.isfinite(a) and math.isfinite(b)) or (a == 0 and b == 0):
        return None
    ends = (a, a + b)
    if min(ends) >= 0:
        return "barrel"
    if max(ends) <= 0:
        return "pincushion"
    return "mustache"


def fit_eq4(points: torch.Tensor, ideal: torch.Tensor, height: int, width: int) -> tuple[float, float, float]:
    """Eq. 4's (k2, k4) about the frame centre fitted to a lens map by least squares, and its RMS error (px).

    Args:
        points: (N, 2) float64 distorted pixels.
        ideal: (N, 2) their ideal pixels under the lens to follow.
        height: the frame's height (its centre is eq. 4's p0).
        width: the frame's width.

    Example:
        >>> p = pixel_grid(8, 10, dtype=torch.float64).reshape(-1, 2)
        >>> k2, k4, err = fit_eq4(p, undistort_points(p[None], 1e-3, 0.0, distortion_center(8, 10))[0], 8, 10)
        >>> round(k2, 6), err < 1e-9
        (0.001, True)
    """
    if points.numel() == 0:
        return math.nan, math.nan, math.nan
    q = points - points.new_tensor([(width - 1) / 2, (height - 1) / 2])
    r2 = (q * q).sum(-1, keepdim=True)
    design = torch.stack([q * r2, q * r2 * r2], -1).reshape(-1, 2)
    target = (ideal - points).reshape(-1, 1)
    cols = design.norm(dim=0).clamp_min(1e-300)
    sol = torch.linalg.lstsq(design / cols, target).solution[:, 0] / cols
    err = ((design @ sol[:, None] - target) ** 2).reshape(-1, 2).sum(-1).mean().sqrt()
    return float(sol[0]), float(sol[1]), float(err)
