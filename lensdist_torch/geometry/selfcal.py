"""Self-calibration: the distortion (k2, k4) and the homography of a pair, estimated together.

Both images carry the same radial distortion (docs/method.md, section 6, eq. 4). Per pair we
fit 10 parameters, 8 of a homography H_n and 2 distortion coefficients (a, b), by
Levenberg-Marquardt on the photometric residual, batched over pairs, coarse to fine (2 x 2 mean
pyramid), in the normalised frame of :mod:`~lensdist_torch.geometry.frame`:

    u_d  = (p_d - p0) / R                 normalised distorted point of img1, R = half diagonal
    u    = u_d (1 + a |u_d|^2 + b |u_d|^4)   eq. 4: the ideal point
    v    = H_n u                          (projective)
    v_d  = eq. 4 inverted by Newton on the radius (differentiable)
    r    = img1(p_d) - img2(p0 + R v_d)   over the pixels whose v_d lies inside img2

In normalised radius the coefficients are O(0.1): a = k2 R^2, b = k4 R^4 (R = 264.9 px at
320 x 424, so the largest coefficients of section 6 are a = 0.18, b = 0.12); both signs are
allowed (pincushion too). The Jacobian is analytic (chain rule through eq. 4, the homography
and the implicit derivative of the Newton inverse), times the image gradient of img2; one
``grid_sample`` of (img2, d/dx, d/dy) per iteration. The initial H comes from the phase
correlation of the coarsest level (or from ``init``, e.g. :func:`estimate_homography`'s H);
a = b = 0.

Confidence. The Gauss-Newton covariance of the parameters, s^2 (J^T J)^-1 (s^2 the residual
variance), is propagated to Delta_avg through its gradient in (a, b): ``delta_avg_std`` (px).
With little motion the distortion of the two views cancels, J's (a, b) columns vanish and the
std explodes. ``confidence = s0 / (s0 + delta_avg_std)`` with ``s0 = config.cannot_tell_std_px``;
below ``config.confidence_threshold`` (0.5: std above s0) the answer is
"cannot tell from this pair" (``info.confident`` False; the numbers are still returned).

Divergence. A pair whose fit goes non-finite, leaves the plausible range (|a|, |b| <=
``max_coefficient``), makes eq. 4 non-invertible on the image (dr/dr_d <= 0), loses its
overlap or ends with a larger residual than it started with gets ``converged`` False and
k2 = k4 = NaN, H = NaN: flagged, never returned as a number.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F

from lensdist_torch.config import SelfCalConfig
from lensdist_torch.core.images import check_image_pair, to_grey
from lensdist_torch.geometry.distortion import delta_avg as _delta_avg
from lensdist_torch.geometry.distortion import radial_derivative, radial_factor, radial_inverse
from lensdist_torch.geometry.frame import half_diagonal, level_to_grid, normalized_grid, normalizer
from lensdist_torch.geometry.phase import phase_correlation
from lensdist_torch.geometry.pyramid import central_differences, mean_pyramid

__all__ = [
    "SelfCalConfig",
    "SelfCalInfo",
    "estimate_distortion",
    "selfcal_residual",
    "distort_normalized",
    "undistort_normalized",
]


class SelfCalInfo(NamedTuple):
    """Per-pair diagnostics of :func:`estimate_distortion`, each (B,).

    converged (bool; False -> k2, k4, H are NaN), confident (bool), confidence in (0, 1],
    delta_avg (px, NaN if not converged), delta_avg_std (px), residual (RMS at full
    resolution), overlap, and ab (B, 2) the normalised coefficients.
    """

    converged: torch.Tensor
    confident: torch.Tensor
    confidence: torch.Tensor
    delta_avg: torch.Tensor
    delta_avg_std: torch.Tensor
    residual: torch.Tensor
    overlap: torch.Tensor
    ab: torch.Tensor


# ------------------------------------------------------------------ the model, normalised units
def undistort_normalized(u_d: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Eq. 4 in normalised units: u = u_d (1 + a |u_d|^2 + b |u_d|^4); a, b of shape (B,)."""
    shape = (-1,) + (1,) * (u_d.dim() - 1)
    return u_d * radial_factor((u_d * u_d).sum(-1, keepdim=True), a.view(shape), b.view(shape))


def distort_normalized(v: torch.Tensor, a: torch.Tensor, b: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """Inverse of :func:`undistort_normalized` by Newton on the radius (differentiable)."""
    shape = (-1,) + (1,) * (v.dim() - 1)
    r, rho = radial_inverse((v * v).sum(-1, keepdim=True), a.view(shape), b.view(shape), iterations)
    return v * (r / rho)


def _h_matrix(theta: torch.Tensor) -> torch.Tensor:
    one = torch.ones_like(theta[:, 0])
    h = torch.stack([1 + theta[:, 0], theta[:, 1], theta[:, 2], theta[:, 3], 1 + theta[:, 4], theta[:, 5],
                     theta[:, 6], theta[:, 7], one], -1)
    return h.view(-1, 3, 3)


def _theta_of(hn: torch.Tensor) -> torch.Tensor:
    hn = hn / hn[:, 2:, 2:]
    f = hn.reshape(-1, 9)[:, :8].clone()
    f[:, 0] -= 1
    f[:, 4] -= 1
    return f


def selfcal_residual(img1, img2, H, k2, k4, newton: int = 5):
    """The differentiable model in pixel units: img1(p_d) - img2(distort(H undistort(p_d))).

    img1, img2: (B, 1, h, w) float; H: (B, 3, 3) pixel homography img1 -> img2 (ideal coords);
    k2, k4: (B,). Returns (residual (B, h*w), valid (B, h*w) bool). Autograd flows to H, k2, k4.
    """
    b_, _, h, w = img1.shape
    r, nrm = half_diagonal(h, w), normalizer(h, w, H.dtype, H.device)
    hn = nrm @ H @ torch.linalg.inv(nrm)
    ud = normalized_grid(0, h, w, h, w, H.dtype, H.device).view(1, -1, 2).expand(b_, -1, -1)
    u = undistort_normalized(ud, k2 * r**2, k4 * r**4)
    wv = torch.cat([u, torch.ones_like(u[..., :1])], -1) @ hn.transpose(1, 2)
    v = wv[..., :2] / wv[..., 2:]
    vd = distort_normalized(v, k2 * r**2, k4 * r**4, newton)
    sx, ox, sy, oy = level_to_grid(0, h, w, h, w)
    grid = vd * vd.new_tensor([sx, sy]) + vd.new_tensor([ox, oy])
    s = F.grid_sample(img2.to(grid.dtype), grid.view(b_, h, w, 2), align_corners=True, padding_mode="zeros")
    valid = (grid.abs() <= 1).all(-1)
    return (img1.to(grid.dtype).flatten(1) - s.flatten(1)) * valid, valid


# ------------------------------------------------------------------ batched LM
def _with_gradients(g: torch.Tensor) -> torch.Tensor:
    """(B, 1, h, w) -> (B, 3, h, w): image, d/dx, d/dy (central differences)."""
    return torch.cat([g, central_differences(g[:, 0]).transpose(1, 2)], 1)


class _Level(NamedTuple):
    """The fixed data of one level.

    img1 at the sampled pixels (B, N), img2 with its gradients (B, 3, h, w), the sampled pixels'
    u_d (x, y planes, (B, N)) and |u_d|^2, level px per unit, the map u -> grid_sample
    coordinates (sx, ox, sy, oy), Newton steps and the margin (level px).
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


def _evaluate(theta: torch.Tensor, lv: _Level, jac: bool = True):
    """Residual (B, N), mask (B, N) and (optionally) the Jacobian (B, 10, N) at theta (B, 10).

    Coordinates are kept as separate x / y planes (B, N): elementwise ops stay contiguous.
    """
    bsz, _, h, w = lv.stack2.shape
    ux_d, uy_d, rho, r_l, (sx, ox, sy, oy) = lv.ux_d, lv.uy_d, lv.rho, lv.px, lv.to_grid
    th = theta.float()
    col = [th[:, k : k + 1] for k in range(10)]  # (B, 1) each
    h00, h01, h02, h10, h11, h12, h20, h21 = 1 + col[0], col[1], col[2], col[3], 1 + col[4], col[5], col[6], col[7]
    a, b = col[8], col[9]
    g1 = radial_factor(rho, a, b)
    ux, uy = ux_d * g1, uy_d * g1
    w3 = 1.0 + h20 * ux + h21 * uy
    iw3 = 1.0 / w3
    vx, vy = (h00 * ux + h01 * uy + h02) * iw3, (h10 * ux + h11 * uy + h12) * iw3
    s, sig = radial_inverse(vx * vx + vy * vy, a, b, lv.newton)
    ratio = s / sig
    vdx, vdy = vx * ratio, vy * ratio
    gx_, gy_ = vdx * sx + ox, vdy * sy + oy  # grid_sample coordinates
    grid = torch.stack([gx_, gy_], -1).view(bsz, 1, -1, 2)
    smp = F.grid_sample(lv.stack2, grid, align_corners=True, padding_mode="zeros").flatten(2)
    mx, my = 1 - 2 * lv.margin / (w - 1), 1 - 2 * lv.margin / (h - 1)
    valid = (gx_.abs() <= mx) & (gy_.abs() <= my) & (w3 > 0)
    vf = valid.float()
    res = (lv.i1 - smp[:, 0]) * vf
    if not jac:
        return res, valid, None
    rd = s * s
    gd = radial_factor(rd, a, b)
    c = 2.0 * (a + 2.0 * b * rd)
    dx, dy = smp[:, 1] * vf, smp[:, 2] * vf
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
    J = torch.stack([Ex * ux, Ex * uy, Ex, Ey * ux, Ey * uy, Ey, -ev * ux, -ev * uy, ja, jb], 1)
    return res, valid, J


def _select(img: torch.Tensor, block: int, margin: float) -> torch.Tensor:
    """Per pair, the pixel of largest gradient magnitude in every block x block cell.

    (B, n) flat indices (all pixels for block 1): sparse, spatially even, textured samples.
    """
    bsz, _, h, w = img.shape
    if block <= 1:
        return torch.arange(h * w).expand(bsz, -1)
    d = central_differences(img[:, 0])
    mag = d[:, :, 0] ** 2 + d[:, :, 1] ** 2
    m = int(math.ceil(margin))
    mag[:, :m], mag[:, h - m :], mag[:, :, :m], mag[:, :, w - m :] = -1, -1, -1, -1
    hb, wb = h // block, w // block
    cells = mag[:, : hb * block, : wb * block].reshape(bsz, hb, block, wb, block).permute(0, 1, 3, 2, 4)
    arg = cells.reshape(bsz, hb, wb, block * block).argmax(-1)
    yy = torch.arange(hb)[:, None] * block + arg // block
    xx = torch.arange(wb)[None, :] * block + arg % block
    return (yy * w + xx).reshape(bsz, -1)


def _invertible(ab: torch.Tensor, s_max: float = 1.05) -> torch.Tensor:
    """d(r (1 + a r^2 + b r^4))/dr > 0 on [0, s_max] (the image plus a margin)."""
    s2 = torch.linspace(0, s_max, 22, dtype=ab.dtype) ** 2
    return (radial_derivative(s2, ab[:, :1], ab[:, 1:]) > 0.05).all(-1)


@torch.no_grad()
def estimate_distortion(img1, img2, init=None, config: SelfCalConfig | None = None):
    """Estimate (k2, k4) and H together, per pair of a batch (see the module docstring).

    Args:
        img1: (B, C, H, W) float in [0, 1] or uint8; H and W at least 16 (and 2^levels).
        img2: the same shape and dtype, with the same distortion as img1.
        init: optional (B, 3, 3) homography img1 -> img2 (pixels), e.g. from
            :func:`estimate_homography`; otherwise phase correlation on the coarsest level.
        config: :class:`SelfCalConfig`; defaults when None.

    Returns:
        k2, k4: (B,) float64 in pixel units (eq. 4), NaN where the fit diverged.
        H: (B, 3, 3) float64, img1's ideal pixel coordinates -> img2's, NaN where diverged.
        info: :class:`SelfCalInfo`.
    """
    cfg = config if config is not None else SelfCalConfig()
    if not isinstance(cfg, SelfCalConfig):
        raise TypeError(f"config must be a SelfCalConfig or None, got {type(cfg).__name__}")
    check_image_pair(img1, img2)
    (bsz, _, h, w), least = img1.shape, max(16, 2**cfg.levels)
    if h < least or w < least:
        raise ValueError(f"img1 and img2 must be at least {least} x {least} pixels, got {h} x {w}")
    if init is not None:
        init = torch.as_tensor(init, dtype=torch.float64)
        if init.shape != (bsz, 3, 3):
            raise ValueError(f"init must be ({bsz}, 3, 3), got {tuple(init.shape)}")
    parts = []
    for i in range(0, bsz, cfg.chunk_size):
        sl = slice(i, i + cfg.chunk_size)
        parts.append(_fit(to_grey(img1[sl]).float().cpu(), to_grey(img2[sl]).float().cpu(),
                          None if init is None else init[sl], cfg))
    k2, k4, H = (torch.cat([p[j] for p in parts]) for j in range(3))
    info = SelfCalInfo(*(torch.cat(f) for f in zip(*[p[3] for p in parts])))
    return k2, k4, H, info


def _fit(g1, g2, init, cfg: SelfCalConfig):
    """One chunk: g1, g2 (b, 1, h, w) float32 grey on the CPU -> k2, k4, H, info."""
    bsz, _, h0, w0 = g1.shape
    pyr1, pyr2 = mean_pyramid(g1, cfg.levels), mean_pyramid(g2, cfg.levels)
    theta = torch.zeros(bsz, 10, dtype=torch.float64)
    if init is not None:
        nrm = normalizer(h0, w0)
        theta[:, :8] = _theta_of(nrm @ init @ torch.linalg.inv(nrm))
    else:  # the translation in level px -> u
        t = phase_correlation(pyr1[-1][:, 0], pyr2[-1][:, 0]).double() * 2 ** (cfg.levels - 1) / half_diagonal(h0, w0)
        theta[:, 2], theta[:, 5] = t[:, 0], t[:, 1]
    lam = torch.full((bsz,), cfg.damping, dtype=torch.float64)
    for lev, iters in zip(range(cfg.levels - 1, -1, -1), cfg.iterations):
        i1, h, w = pyr1[lev], *pyr1[lev].shape[-2:]
        idx = _select(i1, cfg.sample_block[cfg.levels - 1 - lev], cfg.margin)
        ud = normalized_grid(lev, h, w, h0, w0).view(-1, 2)
        ux_d, uy_d = ud[idx, 0], ud[idx, 1]
        lv = _Level(torch.gather(i1.flatten(1), 1, idx), _with_gradients(pyr2[lev]), ux_d, uy_d,
                    ux_d * ux_d + uy_d * uy_d, half_diagonal(h0, w0) / 2**lev, level_to_grid(lev, h, w, h0, w0),
                    cfg.newton, cfg.margin)
        theta, lam, state, start_cost = _levenberg_marquardt(theta, lam, lv, iters)
        lam = lam.clamp_min(cfg.damping)  # a fresh start of the damping at the next level
    return _result(theta, state, start_cost, h0, w0, cfg)


def _cost(res: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return ((res.double() ** 2).sum(1) / valid.sum(1).clamp_min(1)).double()


def _levenberg_marquardt(theta, lam, lv: _Level, iterations: int):
    """``iterations`` Levenberg-Marquardt steps on one level.

    A pair's step is accepted where the cost falls, the model stays invertible and some overlap
    remains. Returns theta, lambda, (res, valid, J, cost) at theta, and the cost at the start.
    """
    res, valid, J = _evaluate(theta, lv)
    cost = _cost(res, valid)
    start_cost = cost.clone()
    for _ in range(iterations):
        jtj = torch.bmm(J, J.transpose(1, 2)).double()
        jtr = torch.bmm(J, res[..., None]).double()[..., 0]
        diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp_min(1e-9)
        A = jtj + torch.diag_embed(lam[:, None] * diag + 1e-9 * diag.amax(1, keepdim=True))
        step = -torch.linalg.solve(A, jtr)
        cand = theta + torch.nan_to_num(step, nan=0.0)
        res_c, valid_c, J_c = _evaluate(cand, lv)
        cost_c = _cost(res_c, valid_c)
        acc = (cost_c < cost) & torch.isfinite(cost_c) & _invertible(cand[:, 8:]) & (valid_c.float().mean(1) > 0.05)
        theta = torch.where(acc[:, None], cand, theta)
        m = acc[:, None]
        res = torch.where(m, res_c, res)
        valid = torch.where(m, valid_c, valid)
        J = torch.where(m[..., None], J_c, J)
        cost = torch.where(acc, cost_c, cost)
        lam = torch.where(acc, lam / 3, lam * 4).clamp(1e-7, 1e7)
    return theta, lam, (res, valid, J, cost), start_cost


def _delta_avg_std(ab, res, valid, J, h0: int, w0: int, cfg: SelfCalConfig) -> torch.Tensor:
    """Std (px) of Delta_avg from the Gauss-Newton covariance of the final full-resolution fit.

    inf where it is not finite.
    """
    n = valid.sum(1).double()
    jtj = torch.bmm(J, J.transpose(1, 2)).double()
    # residual variance, floored at the quantisation noise of 8-bit images, so that a
    # textureless or identical pair cannot claim certainty
    s2 = ((res.double() ** 2).sum(1) / (n - 10).clamp_min(1)).clamp_min(cfg.noise_floor**2)
    eye = torch.eye(10, dtype=torch.float64)
    cov = s2[:, None, None] * torch.linalg.inv(jtj + cfg.ridge * eye)
    # Delta_avg and its gradient in (a, b): R * mean |a u^3 + b u^5|
    u2 = (normalized_grid(0, h0, w0, h0, w0, torch.float64).view(1, -1, 2) ** 2).sum(-1)
    m3, m5 = u2**1.5, u2**2.5
    sgn = torch.sign(ab[:, :1] * m3 + ab[:, 1:] * m5)
    sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)  # the kink of |.| at 0: one side
    grad = half_diagonal(h0, w0) * torch.stack([(sgn * m3).mean(1), (sgn * m5).mean(1)], -1)
    std = torch.einsum("bi,bij,bj->b", grad, cov[:, 8:, 8:], grad).clamp_min(0).sqrt()
    return torch.where(torch.isfinite(std), std, torch.full_like(std, float("inf")))


def _result(theta, state, start_cost, h0: int, w0: int, cfg: SelfCalConfig):
    """k2, k4, H and :class:`SelfCalInfo` of a chunk from its final fit; NaN where it diverged."""
    res, valid, J, cost = state
    r0, ab = half_diagonal(h0, w0), theta[:, 8:].clone()
    std = _delta_avg_std(ab, res, valid, J, h0, w0, cfg)
    k2, k4 = ab[:, 0] / r0**2, ab[:, 1] / r0**4
    overlap = valid.float().mean(1)
    ok = (torch.isfinite(theta).all(1) & (ab.abs() <= cfg.max_coefficient).all(1)
          & _invertible(torch.nan_to_num(ab)) & (overlap >= cfg.min_overlap) & (cost <= start_cost * (1 + 1e-6)))
    nrm = normalizer(h0, w0)
    H = torch.linalg.inv(nrm) @ _h_matrix(theta) @ nrm
    H = H / H[:, 2:, 2:]
    nan = torch.tensor(float("nan"), dtype=torch.float64)
    k2, k4 = torch.where(ok, k2, nan), torch.where(ok, k4, nan)
    H = torch.where(ok[:, None, None], H, nan)
    d_avg = torch.full_like(k2, float("nan"))
    if bool(ok.any()):
        d_avg[ok] = _delta_avg(k2[ok], k4[ok], h0, w0)
    std = torch.where(ok, std, torch.full_like(std, float("inf")))
    conf = cfg.cannot_tell_std_px / (cfg.cannot_tell_std_px + std)
    info = SelfCalInfo(ok, ok & (conf >= cfg.confidence_threshold), conf, d_avg, std,
                       torch.sqrt(cost.clamp_min(0)).float(), overlap, ab)
    return k2, k4, H, info
