"""Self-calibration's model: eq. 4, the photometric model, the residual and its Jacobian.

Also the samples and the M-estimator (docs/method.md, section 10). Used by
:mod:`lensdist_torch.selfcal.fit`, which holds the fit; see its docstring. Per pair, theta holds 8 homography
entries (H_n - I, H_n[2, 2] = 1), the normalised
coefficients (a, b) and, with the ``gain_bias`` photometric model, a gain g and a bias c:

    r = img1(p_d) - (g img2(p0 + R v_d) + c)                       ("gain_bias")
    r = (img1 - m1) - (s1 / s2) (img2(...) - m2)                    ("normalized")
    r = img1(p_d) - img2(p0 + R v_d)                                ("none")

m, s the mean and standard deviation of a pair's valid samples (in img1's units: the
normalised residual is the zero-mean, unit-variance difference times s1). Every tensor is made
on the device of the images; the work is float32.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from lensdist_torch.geometry.distortion import radial_derivative, radial_factor, radial_inverse
from lensdist_torch.geometry.frame import half_diagonal, level_to_grid, normalized_grid, normalizer
from lensdist_torch.geometry.pyramid import central_differences

__all__ = [
    "GAIN_RANGE",
    "HUBER_K",
    "INTERPOLATION",
    "MARGIN",
    "NEWTON",
    "NOISE_FLOOR",
    "PARALLAX_WIDTH",
    "PHOTOMETRIC",
    "ROBUST",
    "TUKEY_C",
    "Level",
    "SelfCalInfo",
    "undistort_normalized",
    "distort_normalized",
    "h_matrix",
    "homography_parameters",
    "planar_parameters",
    "selfcal_residual",
    "with_gradients",
    "evaluate",
    "select_samples",
    "relief_basis",
    "relief_direction",
    "invertible",
    "plausible",
    "robust_constant",
    "robust_scale",
    "robust_weights",
    "robust_cost",
]

PHOTOMETRIC = ("none", "gain_bias", "normalized")
INTERPOLATION = ("bilinear", "bicubic", "blend")
ROBUST = ("none", "huber", "tukey")
MAD_TO_STD = 1.4826  # sigma = 1.4826 MAD for Gaussian residuals
ROBUST_LOSS = "tukey"  # the photometric residual's M-estimator, one of ROBUST: Tukey's biweight (IRLS)
PHOTOMETRIC_MODEL = "gain_bias"  # one of PHOTOMETRIC: img2 times a gain plus a bias, fitted per pair
#: Newton steps of the inverse of eq. 4 on the radius (docs/method.md, section 10).
NEWTON = 5
#: Level px by which a sample's point must map inside img2 to count (docs/method.md, section 10).
MARGIN = 2.0
#: Intensity std floor of the residual's scale and of the covariance (8-bit quantisation, half a grey level in
#: [0, 1] units): a textureless or identical pair cannot claim certainty (docs/method.md, section 10).
NOISE_FLOOR = 0.5 / 255
#: Huber's constant, in sigmas: 95 % efficiency for Gaussian noise (``ROBUST_LOSS`` "huber"; section 10).
HUBER_K = 1.345
#: Tukey's biweight constant, in sigmas: 95 % efficiency for Gaussian noise (``ROBUST_LOSS`` "tukey"; section 10).
TUKEY_C = 4.685
#: (low, high) plausible gain of the ``gain_bias`` photometric model: its start is clamped to it, a fit that leaves
#: it diverged (docs/method.md, section 10).
GAIN_RANGE = (0.25, 4.0)
#: The plane + parallax model's Gaussian bumps' sigma, in half-diagonals (docs/method.md, section 10).
PARALLAX_WIDTH = 0.3


# ------------------------------------------------------------------ eq. 4, normalised units
def undistort_normalized(u_d: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Eq. 4 in normalised units: u = u_d (1 + a |u_d|^2 + b |u_d|^4); a, b of shape (B,)."""
    shape = (-1,) + (1,) * (u_d.dim() - 1)
    return u_d * radial_factor((u_d * u_d).sum(-1, keepdim=True), a.view(shape), b.view(shape))


def distort_normalized(v: torch.Tensor, a: torch.Tensor, b: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """Inverse of :func:`undistort_normalized` by Newton on the radius (differentiable)."""
    shape = (-1,) + (1,) * (v.dim() - 1)
    r, rho = radial_inverse((v * v).sum(-1, keepdim=True), a.view(shape), b.view(shape), iterations)
    return v * (r / rho)


def planar_parameters(photometric: str) -> int:
    """Parameters of the planar model: 8 of H, (a, b), and (g, c) with ``gain_bias``; the relief's follow."""
    return 12 if photometric == "gain_bias" else 10


def h_matrix(theta: torch.Tensor) -> torch.Tensor:
    """(B, >= 8) parameters -> (B, 3, 3) normalised homographies (identity at 0)."""
    one = torch.ones_like(theta[:, 0])
    h = torch.stack([1 + theta[:, 0], theta[:, 1], theta[:, 2], theta[:, 3], 1 + theta[:, 4], theta[:, 5],
                     theta[:, 6], theta[:, 7], one], -1)
    return h.view(-1, 3, 3)


def homography_parameters(hn: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) normalised homographies -> their 8 parameters (inverse of :func:`h_matrix`)."""
    hn = hn / hn[:, 2:, 2:]
    f = hn.reshape(-1, 9)[:, :8].clone()
    f[:, 0] -= 1
    f[:, 4] -= 1
    return f


def sample_image(img: torch.Tensor, grid: torch.Tensor, interpolation: str = "blend") -> torch.Tensor:
    """``grid_sample`` (align_corners, zeros outside) of img at grid, by the named kernel.

    ``blend`` is the mean of the bilinear and the bicubic (Keys, a = -0.75) samples. A small
    motion's local displacements are biased by the kernel by an amount that follows their
    sub-pixel part, and the self-calibration reads that pattern as distortion: bilinear and
    bicubic err with opposite signs, their mean 3-6 times less than either on rendered pans of
    2-5 px (docs/method.md, section 10).

    Example:
        >>> img = torch.arange(16.0).view(1, 1, 4, 4)
        >>> grid = torch.tensor([[[[-1 / 3, -1 / 3]]]])  # pixel (1, 1)
        >>> [round(float(sample_image(img, grid, k)), 4) for k in INTERPOLATION]
        [5.0, 5.0, 5.0]
    """
    lin = F.grid_sample(img, grid, align_corners=True, padding_mode="zeros")
    if interpolation == "bilinear":
        return lin
    cub = F.grid_sample(img, grid, align_corners=True, padding_mode="zeros", mode="bicubic")
    return cub if interpolation == "bicubic" else (lin + cub).mul_(0.5)


def selfcal_residual(img1, img2, H, *, k2, k4, newton: int = 5, gain=None, bias=None, interpolation: str = "blend"):
    """The differentiable model in pixel units: img1(p_d) - (g img2(distort(H undistort(p_d))) + c).

    Args:
        img1: (B, 1, h, w) float.
        img2: (B, 1, h, w) float.
        H: (B, 3, 3) pixel homography img1 -> img2 (ideal coordinates).
        k2: (B,) coefficient of r^2 in pixel units (eq. 4).
        k4: (B,) coefficient of r^4 in pixel units.
        newton: Newton steps of the inverse of eq. 4.
        gain: optional (B,) photometric gain g (1 when None).
        bias: optional (B,) photometric bias c (0 when None).
        interpolation: how img2 is sampled (:func:`sample_image`).

    Returns:
        (residual (B, h*w), valid (B, h*w) bool); autograd flows to H, k2, k4, gain, bias.
    """
    b_, _, h, w = img1.shape
    r, nrm = half_diagonal(h, w), normalizer(h, w, H.dtype, H.device)
    hn = nrm @ H @ torch.linalg.inv(nrm)
    ud = (
        normalized_grid(0, h, w, full_height=h, full_width=w, dtype=H.dtype, device=H.device)
        .view(1, -1, 2)
        .expand(b_, -1, -1)
    )
    u = undistort_normalized(ud, k2 * r**2, k4 * r**4)
    wv = torch.cat([u, torch.ones_like(u[..., :1])], -1) @ hn.transpose(1, 2)
    v = wv[..., :2] / wv[..., 2:]
    vd = distort_normalized(v, k2 * r**2, k4 * r**4, newton)
    sx, ox, sy, oy = level_to_grid(0, h, w, full_height=h, full_width=w)
    grid = vd * vd.new_tensor([sx, sy]) + vd.new_tensor([ox, oy])
    s = sample_image(img2.to(grid.dtype), grid.view(b_, h, w, 2), interpolation).flatten(1)
    if gain is not None:
        s = s * gain.view(-1, 1)
    if bias is not None:
        s = s + bias.view(-1, 1)
    valid = (grid.abs() <= 1).all(-1)
    return (img1.to(grid.dtype).flatten(1) - s) * valid, valid


# ------------------------------------------------------------------ one level's data and the Jacobian
def with_gradients(g: torch.Tensor) -> torch.Tensor:
    """(B, 1, h, w) -> (B, 3, h, w): image, d/dx, d/dy (central differences)."""
    return torch.cat([g, central_differences(g[:, 0]).transpose(1, 2)], 1)


class SelfCalInfo(NamedTuple):
    """Per-pair diagnostics of :func:`estimate_distortion`, each (B,) on the images' device.

    converged (bool; False -> k2, k4, H are NaN), confident (bool), confidence in (0, 1],
    delta_avg (px, NaN if not converged), delta_avg_std (px), residual (RMS of the
    photometrically corrected residual at full resolution), overlap, ab (B, 2) the normalised
    coefficients, gain_bias (B, 2) the photometric gain and bias (1, 0 without that model),
    scale (the robust sigma, 1.4826 MAD, of the final residual), from_init (bool: the start
    from ``init`` won), relief (bool: the plane + parallax model's answer was kept), motion
    (the fitted H's mean displacement, px; NaN if not converged), planar_ab and relief_ab (B, 2) the
    planar and plane + parallax models' coefficients whichever was kept (relief_ab NaN without that
    model or where it did not converge), relief_z Hausman's statistic of their Delta_avg difference
    (what ``parallax_test`` thresholds; NaN without that model), planar_std and relief_std the two
    models' Delta_avg stds whichever was kept (relief_std NaN without that model, inf where it did
    not converge), aligned_residual the RMS of the same residual over the frame's ``clusters`` x
    ``clusters`` rectangles but the worst ``occluded_share`` of them (what ``analyze`` tests: an
    occluder spoils a few rectangles, a model that cannot follow the lens most of the border),
    relief_score Rao's score statistic of the relief at the planar answer (chi-square with
    ``parallax**2`` degrees of freedom on a flat scene; what ``fit.PARALLAX_SCORE_LEVEL`` tests;
    NaN without that model). Where the score test finds no relief, the plane + parallax figures are
    those of its one Gauss-Newton step from the planar answer (``prior.relief_step``), not of the
    fitted stage.
    """

    converged: torch.Tensor
    confident: torch.Tensor
    confidence: torch.Tensor
    delta_avg: torch.Tensor
    delta_avg_std: torch.Tensor
    residual: torch.Tensor
    overlap: torch.Tensor
    ab: torch.Tensor
    gain_bias: torch.Tensor
    scale: torch.Tensor
    from_init: torch.Tensor
    relief: torch.Tensor
    motion: torch.Tensor
    planar_ab: torch.Tensor
    relief_ab: torch.Tensor
    relief_z: torch.Tensor
    planar_std: torch.Tensor
    relief_std: torch.Tensor
    aligned_residual: torch.Tensor
    relief_score: torch.Tensor


class Level(NamedTuple):
    """The fixed data of one level.

    img1 at the sampled pixels (B, N), img2 with its gradients (B, 3, h, w), the sampled pixels'
    u_d (x, y planes, (B, N)) and |u_d|^2, level px per unit, the map u -> grid_sample
    coordinates (sx, ox, sy, oy), Newton steps, the margin (level px), the photometric model
    and the std floor of the normalised model; with the plane + parallax model, the relief's
    basis at the sampled pixels (B, K, N) and, per row, the unit direction (B, 2) the relief moves
    img2's points along; the kernel img2 and its gradients are sampled with (:func:`sample_image`).
    """

    i1: torch.Tensor
    stack2: torch.Tensor
    ux_d: torch.Tensor
    uy_d: torch.Tensor
    rho: torch.Tensor
    px: float
    to_grid: tuple[float, float, float, float]
    newton: int
    margin: float
    photometric: str
    floor: float
    basis: torch.Tensor | None = None
    direction: torch.Tensor | None = None
    interpolation: str = "bilinear"


def _valid_mean(x: torch.Tensor, vf: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    return (x * vf).sum(-1, keepdim=True) / n


def evaluate(theta: torch.Tensor, lv: Level, jac: bool = True):
    """Residual (B, N), mask (B, N) and (optionally) the Jacobian (B, P, N) at theta (B, P).

    P = 12 with the ``gain_bias`` model (its rows 10, 11 d r / d g = -img2(...), d r / d c
    = -1), 10 otherwise, plus K relief coefficients with the plane + parallax model. Coordinates are kept as
    separate x / y planes (B, N): elementwise ops stay contiguous.
    """
    bsz, _, h, w = lv.stack2.shape
    ux_d, uy_d, rho, r_l, (sx, ox, sy, oy) = lv.ux_d, lv.uy_d, lv.rho, lv.px, lv.to_grid
    th = theta.float()
    col = [th[:, k : k + 1] for k in range(th.shape[1])]  # (B, 1) each
    h00, h01, h02, h10, h11, h12, h20, h21 = 1 + col[0], col[1], col[2], col[3], 1 + col[4], col[5], col[6], col[7]
    a, b = col[8], col[9]
    g1 = radial_factor(rho, a, b)
    ux, uy = ux_d * g1, uy_d * g1
    w3 = 1.0 + h20 * ux + h21 * uy
    iw3 = 1.0 / w3
    vx, vy = (h00 * ux + h01 * uy + h02) * iw3, (h10 * ux + h11 * uy + h12) * iw3
    if lv.basis is not None:  # the relief along the motion: v += (c . phi(u_d)) d
        relief = torch.bmm(th[:, None, planar_parameters(lv.photometric):], lv.basis)[:, 0]
        vx, vy = vx + relief * lv.direction[:, :1], vy + relief * lv.direction[:, 1:]
    s, sig = radial_inverse(vx * vx + vy * vy, a, b, lv.newton)
    ratio = s / sig
    vdx, vdy = vx * ratio, vy * ratio
    gx_, gy_ = vdx * sx + ox, vdy * sy + oy  # grid_sample coordinates
    grid = torch.stack([gx_, gy_], -1).view(bsz, 1, -1, 2)
    smp = sample_image(lv.stack2, grid, lv.interpolation).flatten(2)
    mx, my = 1 - 2 * lv.margin / (w - 1), 1 - 2 * lv.margin / (h - 1)
    valid = (gx_.abs() <= mx) & (gy_.abs() <= my) & (w3 > 0)
    vf = valid.float()
    i2, gain = smp[:, 0], None
    if lv.photometric == "gain_bias":
        gain = col[10]
        res = (lv.i1 - gain * i2 - col[11]) * vf
    elif lv.photometric == "normalized":
        n = vf.sum(1, keepdim=True).clamp_min(1)
        d1, d2 = lv.i1 - _valid_mean(lv.i1, vf, n), i2 - _valid_mean(i2, vf, n)
        s2 = _valid_mean(d2 * d2, vf, n).sqrt().clamp_min(lv.floor)
        gain, z = _valid_mean(d1 * d1, vf, n).sqrt().clamp_min(lv.floor) / s2, d2 / s2
        res = (d1 - gain * d2) * vf
    else:
        res = (lv.i1 - i2) * vf
    if not jac:
        return res, valid, None
    rd = s * s
    gd = radial_factor(rd, a, b)
    c = 2.0 * (a + 2.0 * b * rd)
    dx, dy = smp[:, 1] * vf, smp[:, 2] * vf
    if gain is not None:  # d r / d img2(...) = -gain
        dx, dy = dx * gain, dy * gain
    # e = -R grad^T DF^-1, DF = g I + c vd vd^T (Sherman-Morrison)
    t = c * (dx * vdx + dy * vdy) / (gd + c * rd)
    sc = -r_l / gd
    ex, ey = sc * (dx - t * vdx), sc * (dy - t * vdy)
    Ex, Ey = ex * iw3, ey * iw3
    ev = Ex * vx + Ey * vy
    fx = Ex * h00 + Ey * h10 - ev * h20  # e . dv/du
    fy = Ex * h01 + Ey * h11 - ev * h21
    fu = fx * ux_d + fy * uy_d
    evd = ex * vdx + ey * vdy
    ja = fu * rho - evd * rd
    jb = fu * rho * rho - evd * rd * rd
    rows = [Ex * ux, Ex * uy, Ex, Ey * ux, Ey * uy, Ey, -ev * ux, -ev * uy, ja, jb]
    if lv.photometric == "gain_bias":
        rows += [-i2 * vf, -vf]
    J = torch.stack(rows, 1)
    if lv.basis is not None:
        ed = ex * lv.direction[:, :1] + ey * lv.direction[:, 1:]
        J = torch.cat([J, ed[:, None] * lv.basis], 1)
    if lv.photometric == "normalized":  # the moments move with the samples: project them out
        J = (
            J
            - _valid_mean(J, vf[:, None], n[:, None])
            - z[:, None] * _valid_mean(z[:, None] * J, vf[:, None], n[:, None])
        )
        J = J * vf[:, None]
    return res, valid, J


def relief_basis(ux_d: torch.Tensor, uy_d: torch.Tensor, *, n: int, width: float, h0: int, w0: int) -> torch.Tensor:
    """Gaussian bumps of sigma ``width`` (half-diagonals) on an n x n grid spanning the frame.

    ``ux_d``, ``uy_d`` (B, N): normalised points -> (B, n^2, N). The relief of the plane + parallax model is
    their weighted sum.
    """
    r = half_diagonal(h0, w0)
    cx = torch.linspace(-(w0 - 1) / (2 * r), (w0 - 1) / (2 * r), n, device=ux_d.device)
    cy = torch.linspace(-(h0 - 1) / (2 * r), (h0 - 1) / (2 * r), n, device=ux_d.device)
    d2 = (ux_d[:, None] - cx.repeat_interleave(n)[:, None]) ** 2 + (uy_d[:, None] - cy.repeat(n)[:, None]) ** 2
    return torch.exp(-d2 / (2 * width * width))


def relief_direction(theta: torch.Tensor) -> torch.Tensor:
    """(B, 2) the unit direction the relief moves img2's points along: the homography's translation.

    (h02, h12) of ``theta`` (B, P), downwards where it is 0: a camera translating parallel to the
    scene moves every point of a relief along it.
    """
    t = theta[:, [2, 5]].float()
    n = t.norm(dim=1, keepdim=True)
    down = torch.tensor([0.0, 1.0], device=t.device).expand_as(t)
    return torch.where(n > 0, t / n.clamp_min(1e-12), down)


def select_samples(img: torch.Tensor, block: int, margin: float) -> torch.Tensor:
    """Per pair, the pixel of largest gradient magnitude in every block x block cell.

    (B, n) flat indices on img's device (all pixels for block 1): sparse, spatially even,
    textured samples.
    """
    bsz, _, h, w = img.shape
    if block <= 1:
        return torch.arange(h * w, device=img.device).expand(bsz, -1)
    d = central_differences(img[:, 0])
    mag = d[:, :, 0] ** 2 + d[:, :, 1] ** 2
    m = int(math.ceil(margin))
    mag[:, :m], mag[:, h - m :], mag[:, :, :m], mag[:, :, w - m :] = -1, -1, -1, -1
    hb, wb = h // block, w // block
    cells = mag[:, : hb * block, : wb * block].reshape(bsz, hb, block, wb, block).permute(0, 1, 3, 2, 4)
    arg = cells.reshape(bsz, hb, wb, block * block).argmax(-1)
    yy = torch.arange(hb, device=img.device)[:, None] * block + arg // block
    xx = torch.arange(wb, device=img.device)[None, :] * block + arg % block
    return (yy * w + xx).reshape(bsz, -1)


def invertible(ab: torch.Tensor, s_max: float = 1.05) -> torch.Tensor:
    """d(r (1 + a r^2 + b r^4))/dr > 0 on [0, s_max] (the image plus a margin); ab (B, 2)."""
    s2 = torch.linspace(0, s_max, 22, dtype=ab.dtype, device=ab.device) ** 2
    return (radial_derivative(s2, ab[:, :1], ab[:, 1:]) > 0.05).all(-1)


def plausible(theta: torch.Tensor, photometric: str) -> torch.Tensor:
    """(B,) bool: eq. 4 invertible on the image and, with ``gain_bias``, the gain within :data:`GAIN_RANGE`."""
    ok = invertible(torch.nan_to_num(theta[:, 8:10]))
    if photometric == "gain_bias":
        ok &= (theta[:, 10] >= GAIN_RANGE[0]) & (theta[:, 10] <= GAIN_RANGE[1])
    return ok


# ------------------------------------------------------------------ the M-estimator
def robust_constant(loss: str) -> float:
    """The M-estimator's constant, in sigmas: :data:`TUKEY_C` for "tukey", else :data:`HUBER_K`."""
    return TUKEY_C if loss == "tukey" else HUBER_K


def robust_scale(res: torch.Tensor, valid: torch.Tensor, floor: float, samples: int = 1024) -> torch.Tensor:
    """Per pair, sigma = 1.4826 MAD of the valid residuals (B, N) -> (B,), at least ``floor``.

    The medians are taken over an even subset of at most about ``samples`` residuals per pair
    (the scale needs no more; it is the costly step of the M-estimator).
    """
    step = max(1, res.shape[1] // samples)
    x = torch.where(valid[:, ::step], res[:, ::step], torch.full_like(res[:, ::step], float("nan")))
    med = x.nanmedian(1, keepdim=True).values
    mad = (x - med).abs().nanmedian(1).values
    return torch.nan_to_num(MAD_TO_STD * mad, nan=floor).clamp_min(floor)


def robust_weights(res: torch.Tensor, sigma: torch.Tensor, loss: str, k: float) -> torch.Tensor | None:
    """IRLS weights psi(z) / z at z = r / sigma (B, N); None for least squares (all ones)."""
    if loss == "none":
        return None
    z = res.abs() / sigma[:, None].to(res.dtype)
    if loss == "huber":
        return (k / z.clamp_min(1e-12)).clamp_max(1.0)
    return (1 - (z / k) ** 2).clamp_min(0) ** 2  # tukey


def robust_cost(res: torch.Tensor, valid: torch.Tensor, sigma: torch.Tensor, *, loss: str, k: float) -> torch.Tensor:
    """(B,) float64: 2 sigma^2 mean rho(r / sigma) over the valid samples (mean r^2 for "none").

    ``res`` is zero where not valid; the terms are float32, their sums float64.
    """
    n = valid.sum(1).clamp_min(1).double()
    if loss == "none":
        return (res * res).sum(1, dtype=torch.float64) / n
    z = res.abs() / sigma[:, None].to(res.dtype)
    if loss == "huber":
        rho = torch.where(z <= k, 0.5 * z * z, k * z - 0.5 * k * k)
    else:  # tukey
        rho = (k * k / 6) * (1 - (1 - (z / k).clamp_max(1) ** 2) ** 3)
    return 2 * sigma.double() ** 2 * (rho * valid).sum(1, dtype=torch.float64) / n
