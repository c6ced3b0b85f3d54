"""Self-calibration: the distortion (k2, k4) and the homography of a pair, estimated together.

Both images carry the same radial distortion (SPEC 6, eq. 4). Per pair we fit 10 parameters,
8 of a homography H_n and 2 distortion coefficients (a, b), by Levenberg-Marquardt on the
photometric residual, batched over pairs, coarse to fine (2 x 2 mean pyramid):

    u_d  = (p_d - p0) / R                 normalised distorted point of img1, R = half diagonal
    u    = u_d (1 + a |u_d|^2 + b |u_d|^4)   eq. 4: the ideal point
    v    = H_n u                          (projective)
    v_d  = eq. 4 inverted by Newton on the radius (differentiable)
    r    = img1(p_d) - img2(p0 + R v_d)   over the pixels whose v_d lies inside img2

In normalised radius the coefficients are O(0.1): a = k2 R^2, b = k4 R^4 (R = 264.9 px at
320 x 424, so the SPEC maxima are a = 0.18, b = 0.12); both signs are allowed (pincushion
too). The Jacobian is analytic (chain rule through eq. 4, the homography and the implicit
derivative of the Newton inverse), times the image gradient of img2; one ``grid_sample`` of
(img2, d/dx, d/dy) per iteration. The initial H comes from phase correlation on the coarsest
level (or from ``init``, e.g. :func:`estimate_homography`'s H); a = b = 0.

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
from lensdist_torch.geometry.distortion import delta_avg as _delta_avg
from lensdist_torch.core.images import check_image_pair, to_grey

__all__ = [
    "SelfCalConfig",
    "SelfCalInfo",
    "estimate_distortion",
    "selfcal_residual",
    "distort_normalized",
    "undistort_normalized",
]

class SelfCalInfo(NamedTuple):
    """Per pair, each (B,): converged (bool; False -> k2, k4, H are NaN), confident (bool),
    confidence in (0, 1], delta_avg (px, NaN if not converged), delta_avg_std (px), residual
    (RMS at full resolution), overlap, and ab (B, 2) the normalised coefficients."""

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
    rho = (u_d * u_d).sum(-1, keepdim=True)
    return u_d * (1.0 + a.view(shape) * rho + b.view(shape) * rho * rho)


def distort_normalized(v: torch.Tensor, a: torch.Tensor, b: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """Inverse of :func:`undistort_normalized` by Newton on the radius (differentiable)."""
    shape = (-1,) + (1,) * (v.dim() - 1)
    a, b = a.view(shape), b.view(shape)
    sig2 = (v * v).sum(-1, keepdim=True)
    sig = torch.sqrt(sig2 + (sig2 == 0).to(v.dtype))
    s = sig
    for _ in range(iterations):
        s2 = s * s
        s = s - (s * (1.0 + a * s2 + b * s2 * s2) - sig) / (1.0 + 3.0 * a * s2 + 5.0 * b * s2 * s2)
    return v * (s / sig)


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


def _normaliser(h: int, w: int, dtype=torch.float64) -> tuple[torch.Tensor, float]:
    """N with u = N p (pixels -> normalised), and R."""
    r = 0.5 * math.hypot(w - 1, h - 1)
    n = torch.tensor([[1 / r, 0, -(w - 1) / 2 / r], [0, 1 / r, -(h - 1) / 2 / r], [0, 0, 1]], dtype=dtype)
    return n, r


def _level_grid(h: int, w: int, r: float, dtype=torch.float32) -> torch.Tensor:
    ys = (torch.arange(h, dtype=dtype) - (h - 1) / 2) / r
    xs = (torch.arange(w, dtype=dtype) - (w - 1) / 2) / r
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], -1).reshape(-1, 2)


def selfcal_residual(img1, img2, H, k2, k4, newton: int = 5):
    """The differentiable model in pixel units: img1(p_d) - img2(distort(H undistort(p_d))).

    img1, img2: (B, 1, h, w) float; H: (B, 3, 3) pixel homography img1 -> img2 (ideal coords);
    k2, k4: (B,). Returns (residual (B, h*w), valid (B, h*w) bool). Autograd flows to H, k2, k4.
    """
    b_, _, h, w = img1.shape
    nrm, r = _normaliser(h, w, H.dtype)
    nrm = nrm.to(H.device)
    hn = nrm @ H @ torch.linalg.inv(nrm)
    ud = _level_grid(h, w, r, H.dtype).to(H.device).expand(b_, -1, -1)
    u = undistort_normalized(ud, k2 * r**2, k4 * r**4)
    wv = torch.cat([u, torch.ones_like(u[..., :1])], -1) @ hn.transpose(1, 2)
    v = wv[..., :2] / wv[..., 2:]
    vd = distort_normalized(v, k2 * r**2, k4 * r**4, newton)
    q = vd * r + vd.new_tensor([(w - 1) / 2, (h - 1) / 2])
    grid = q * q.new_tensor([2 / (w - 1), 2 / (h - 1)]) - 1
    s = F.grid_sample(img2.to(q.dtype), grid.view(b_, h, w, 2), align_corners=True, padding_mode="zeros")
    valid = (grid.abs() <= 1).all(-1)
    return (img1.to(q.dtype).flatten(1) - s.flatten(1)) * valid, valid


# ------------------------------------------------------------------ batched LM
def _grad_stack(g: torch.Tensor) -> torch.Tensor:
    """(B, 1, h, w) -> (B, 3, h, w): image, d/dx, d/dy (central differences, one-sided at edges)."""
    gx = torch.zeros_like(g)
    gy = torch.zeros_like(g)
    gx[..., 1:-1] = 0.5 * (g[..., 2:] - g[..., :-2])
    gx[..., 0], gx[..., -1] = g[..., 1] - g[..., 0], g[..., -1] - g[..., -2]
    gy[..., 1:-1, :] = 0.5 * (g[..., 2:, :] - g[..., :-2, :])
    gy[..., 0, :], gy[..., -1, :] = g[..., 1, :] - g[..., 0, :], g[..., -1, :] - g[..., -2, :]
    return torch.cat([g, gx, gy], 1)


def _evaluate(theta, i1, stack2, ux_d, uy_d, rho, r_l, newton, margin, jac=True):
    """Residual (B, N), mask (B, N) and (optionally) the Jacobian (B, 10, N) at theta (B, 10).

    Coordinates are kept as separate x / y planes (B, N): elementwise ops stay contiguous.
    """
    bsz, _, h, w = stack2.shape
    n = ux_d.shape[1]
    th = theta.float()
    col = [th[:, k : k + 1] for k in range(10)]  # (B, 1) each
    h00, h01, h02, h10, h11, h12, h20, h21 = 1 + col[0], col[1], col[2], col[3], 1 + col[4], col[5], col[6], col[7]
    a, b = col[8], col[9]
    g1 = 1.0 + rho * (a + b * rho)
    ux, uy = ux_d * g1, uy_d * g1
    w3 = 1.0 + h20 * ux + h21 * uy
    iw3 = 1.0 / w3
    vx, vy = (h00 * ux + h01 * uy + h02) * iw3, (h10 * ux + h11 * uy + h12) * iw3
    sig2 = vx * vx + vy * vy
    sig = torch.sqrt(sig2 + (sig2 == 0).float())
    s = sig
    for _ in range(newton):
        s2 = s * s
        s = s - (s * (1.0 + s2 * (a + b * s2)) - sig) / (1.0 + s2 * (3.0 * a + 5.0 * b * s2))
    ratio = s / sig
    vdx, vdy = vx * ratio, vy * ratio
    cx, cy = (w - 1) / 2, (h - 1) / 2
    gx_, gy_ = vdx * (r_l / cx), vdy * (r_l / cy)  # grid_sample coordinates
    grid = torch.stack([gx_, gy_], -1).view(bsz, 1, n, 2)
    smp = F.grid_sample(stack2, grid, align_corners=True, padding_mode="zeros").flatten(2)
    mx, my = 1 - margin / cx, 1 - margin / cy
    valid = (gx_.abs() <= mx) & (gy_.abs() <= my) & (w3 > 0)
    vf = valid.float()
    res = (i1 - smp[:, 0]) * vf
    if not jac:
        return res, valid, None
    rd = s * s
    gd = 1.0 + rd * (a + b * rd)
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
    """Per pair, the pixel of largest gradient magnitude in every block x block cell: (B, n)
    flat indices (all pixels for block 1). Sparse, spatially even, textured samples."""
    bsz, _, h, w = img.shape
    if block <= 1:
        return torch.arange(h * w).expand(bsz, -1)
    st = _grad_stack(img)
    mag = st[:, 1] ** 2 + st[:, 2] ** 2
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
    return (1 + 3 * ab[:, :1] * s2 + 5 * ab[:, 1:] * s2 * s2 > 0.05).all(-1)


def _phase_correlation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(B, h, w) -> (B, 2) translation t (x, y) with a(p) ~ b(p + t)."""
    h, w = a.shape[-2:]
    win = torch.hann_window(h, periodic=False)[:, None] * torch.hann_window(w, periodic=False)[None]
    fa = torch.fft.rfft2((a - a.mean((-2, -1), keepdim=True)) * win)
    fb = torch.fft.rfft2((b - b.mean((-2, -1), keepdim=True)) * win)
    cross = fb * fa.conj()
    corr = torch.fft.irfft2(cross / (cross.abs() + 1e-9), s=(h, w))
    idx = corr.flatten(1).argmax(1)
    iy, ix = idx // w, idx % w
    bi = torch.arange(a.shape[0])

    def sub(c0, cm, cp):
        den = cm - 2 * c0 + cp
        return torch.where(den.abs() > 1e-12, 0.5 * (cm - cp) / den, torch.zeros_like(den)).clamp(-0.5, 0.5)

    c0 = corr[bi, iy, ix]
    dx = sub(c0, corr[bi, iy, (ix - 1) % w], corr[bi, iy, (ix + 1) % w])
    dy = sub(c0, corr[bi, (iy - 1) % h, ix], corr[bi, (iy + 1) % h, ix])
    tx = torch.where(ix > w // 2, ix - w, ix).double() + dx.double()
    ty = torch.where(iy > h // 2, iy - h, iy).double() + dy.double()
    return torch.stack([tx, ty], -1)


@torch.no_grad()
def estimate_distortion(img1, img2, init=None, config: SelfCalConfig | None = None):
    """Estimate (k2, k4) and H together, per pair of a batch (see the module docstring).

    Args:
        img1, img2: (B, C, H, W) float in [0, 1] or uint8, the same distortion in both.
        init: optional (B, 3, 3) homography img1 -> img2 (pixels), e.g. from
            :func:`estimate_homography`; otherwise phase correlation on the coarsest level.
    Returns:
        k2, k4: (B,) float64 in pixel units (eq. 4), NaN where the fit diverged.
        H: (B, 3, 3) float64, img1's ideal pixel coordinates -> img2's, NaN where diverged.
        info: :class:`SelfCalInfo`.
    """
    cfg = config if config is not None else SelfCalConfig()
    if not isinstance(cfg, SelfCalConfig):
        raise TypeError(f"config must be a SelfCalConfig or None, got {type(cfg).__name__}")
    check_image_pair(img1, img2)
    bsz = img1.shape[0]
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
    bsz, _, h0, w0 = g1.shape
    nrm, r0 = _normaliser(h0, w0)
    pyr1, pyr2 = [g1], [g2]
    for _ in range(cfg.levels - 1):
        pyr1.append(F.avg_pool2d(pyr1[-1], 2))
        pyr2.append(F.avg_pool2d(pyr2[-1], 2))
    theta = torch.zeros(bsz, 10, dtype=torch.float64)
    if init is not None:
        theta[:, :8] = _theta_of(nrm @ init @ torch.linalg.inv(nrm))
    else:
        s = 2 ** (cfg.levels - 1)
        t = _phase_correlation(pyr1[-1][:, 0], pyr2[-1][:, 0]) * s / r0
        theta[:, 2], theta[:, 5] = t[:, 0], t[:, 1]
    lam = torch.full((bsz,), cfg.damping, dtype=torch.float64)
    ok = torch.ones(bsz, dtype=torch.bool)
    first_cost = None
    for lev, iters in zip(range(cfg.levels - 1, -1, -1), cfg.iterations):
        i1, i2 = pyr1[lev], pyr2[lev]
        h, w = i1.shape[-2:]
        r_l = r0 / 2**lev
        idx = _select(i1, cfg.sample_block[cfg.levels - 1 - lev], cfg.margin)
        ud = _level_grid(h, w, r_l)
        ux_d, uy_d = ud[idx, 0], ud[idx, 1]
        rho = ux_d * ux_d + uy_d * uy_d
        stack2 = _grad_stack(i2)
        i1f = torch.gather(i1.flatten(1), 1, idx)
        args = (i1f, stack2, ux_d, uy_d, rho, r_l, cfg.newton, cfg.margin)
        res, valid, J = _evaluate(theta, *args)
        cost = _cost(res, valid)
        if lev == 0:
            first_cost = cost.clone()
        for _ in range(iters):
            jtj = torch.bmm(J, J.transpose(1, 2)).double()
            jtr = torch.bmm(J, res[..., None]).double()[..., 0]
            diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp_min(1e-9)
            A = jtj + torch.diag_embed(lam[:, None] * diag + 1e-9 * diag.amax(1, keepdim=True))
            step = -torch.linalg.solve(A, jtr)
            cand = theta + torch.nan_to_num(step, nan=0.0)
            res_c, valid_c, J_c = _evaluate(cand, *args)
            cost_c = _cost(res_c, valid_c)
            acc = (cost_c < cost) & torch.isfinite(cost_c) & _invertible(cand[:, 8:]) & (valid_c.float().mean(1) > 0.05)
            theta = torch.where(acc[:, None], cand, theta)
            m = acc[:, None]
            res = torch.where(m, res_c, res)
            valid = torch.where(m, valid_c, valid)
            J = torch.where(m[..., None], J_c, J)
            cost = torch.where(acc, cost_c, cost)
            lam = torch.where(acc, lam / 3, lam * 4).clamp(1e-7, 1e7)
        lam = lam.clamp_min(cfg.damping)  # a fresh start of the damping at the next level
    # covariance of the final, full-resolution fit
    n = valid.sum(1).double()
    jtj = torch.bmm(J, J.transpose(1, 2)).double()
    # residual variance, floored at the quantisation noise of 8-bit images, so that a
    # textureless or identical pair cannot claim certainty
    s2 = ((res.double() ** 2).sum(1) / (n - 10).clamp_min(1)).clamp_min(cfg.noise_floor**2)
    eye = torch.eye(10, dtype=torch.float64)
    cov = s2[:, None, None] * torch.linalg.inv(jtj + cfg.ridge * eye)
    ab = theta[:, 8:].clone()
    k2, k4 = ab[:, 0] / r0**2, ab[:, 1] / r0**4
    # Delta_avg and its gradient in (a, b): r0 * mean |a u^3 + b u^5|
    u2 = (_level_grid(h0, w0, r0, torch.float64) ** 2).sum(-1)
    m3, m5 = u2**1.5, u2**2.5
    sgn = torch.sign(ab[:, :1] * m3 + ab[:, 1:] * m5)
    sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)  # the kink of |.| at 0: one side
    grad = r0 * torch.stack([(sgn * m3).mean(1), (sgn * m5).mean(1)], -1)
    var = torch.einsum("bi,bij,bj->b", grad, cov[:, 8:, 8:], grad)
    std = torch.sqrt(var.clamp_min(0))
    std = torch.where(torch.isfinite(std), std, torch.full_like(std, float("inf")))
    overlap = valid.float().mean(1)
    fin = torch.isfinite(theta).all(1)
    ok = (fin & (ab.abs() <= cfg.max_coefficient).all(1) & _invertible(torch.nan_to_num(ab)) & (overlap >= cfg.min_overlap)
          & (cost <= first_cost * (1 + 1e-6)))
    hn = _h_matrix(theta)
    H = torch.linalg.inv(nrm) @ hn @ nrm
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


def _cost(res: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    return ((res.double() ** 2).sum(1) / valid.sum(1).clamp_min(1)).double()
