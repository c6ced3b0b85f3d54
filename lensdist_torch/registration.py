"""Batched homography registration (SPEC section 7) and the class-R perturbation.

Convention: ``H`` maps img1's pixel coordinates to img2's, ``img1(p) = img2(H p)``, pixel centres
at integer positions (``align_corners=True``), ``H[:, 2, 2] = 1``. With SPEC 7's motion ``M``
(I2 -> I1), the true ``H`` is ``M^-1``.

Method of :func:`estimate_homography`, batched over pairs, no Python loop over pairs:

1. Grey images, a pyramid of 2 x 2 means (default 3 levels: 1/4, 1/2, 1/1).
2. Initial translation by phase correlation (Hann window, sub-pixel parabola) on the coarsest
   level, unless ``init`` is given.
3. Inverse-compositional Gauss-Newton (Baker-Matthews) for the 8 homography parameters, coarse
   to fine, in centred coordinates scaled by the half-diagonal (same at every level). Per level
   the steepest-descent images and the Hessian of img1 are precomputed once; the Hessian is
   accumulated through image moments (sum of ``m g_a g_b u^i v^j``, one small matmul), so the
   (B, 8, N) steepest-descent images are never stored. Each iteration is one ``grid_sample``
   of img2, a (B, 2, N) x (N, 6) matmul and a float64 8 x 8 solve (damped).
4. Masks: the Hessian uses the pixels that map at least ``margin`` level pixels inside img2
   under the estimate at the start of the level; each iteration further drops the pixels whose
   current warped position lies outside img2.
5. Per pair, a level ends when the update moves no image corner by more than
   ``step_tol * 2**level`` px (full-resolution pixels); pairs that are done, diverged or
   textureless drop out of the batch, so pair i's result does not depend on the others.

Failure reporting (``converged=False``, never a silent answer): a Gauss-Newton Hessian whose
smallest eigenvalue (per pixel, pixel units) is below ``min_texture`` at full resolution
(constant or one-dimensional textures), a non-finite or exploding update, an overlap below
``min_overlap``, a full-resolution residual that grew, or no small step within the iterations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F
from kornia.geometry import warp_perspective

from .images import check_image, check_image_pair, to_grey

__all__ = [
    "RegistrationConfig",
    "RegistrationInfo",
    "estimate_homography",
    "warp_to_reference",
    "perturb_homography",
    "corner_error",
]


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`estimate_homography`.

    Attributes:
        levels: pyramid levels (2 x 2 means); fewer are used when the coarsest would be
            smaller than 16 px.
        iterations: maximum IC iterations per level, coarsest first (length ``levels``; the
            last entry is used for missing ones).
        step_tol: a pair is done at full resolution when an update moves no image corner by
            more than this (px); at level l the tolerance is ``step_tol * 2**l``.
        damping: Hessian damping, a fraction of its mean diagonal.
        min_texture: smallest eigenvalue of the per-pixel Gauss-Newton Hessian (pixel units,
            centred coordinates / half-diagonal) below which a level is textureless.
        min_overlap: fraction of img1 that must map inside img2.
        margin: level pixels by which the Hessian's pixels must map inside img2.
        max_step: an update moving a corner by more than this fraction of the image
            diagonal is divergence.
    """

    levels: int = 3
    iterations: tuple[int, ...] = (20, 6, 3)
    step_tol: float = 0.01
    damping: float = 1e-6
    min_texture: float = 1e-8
    min_overlap: float = 0.3
    margin: float = 2.0
    max_step: float = 0.25

    def __post_init__(self) -> None:
        if isinstance(self.levels, bool) or not isinstance(self.levels, int) or self.levels < 1:
            raise ValueError(f"levels must be a positive int, got {self.levels!r}")
        its = tuple(self.iterations)
        if not its or any(isinstance(i, bool) or not isinstance(i, int) or i < 1 for i in its):
            raise ValueError(f"iterations must be positive ints, got {self.iterations!r}")
        for name in ("step_tol", "min_texture", "max_step"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if not (0 <= self.damping and 0 <= self.margin and 0 <= self.min_overlap <= 1):
            raise ValueError("damping and margin must be >= 0, min_overlap in [0, 1]")


class RegistrationInfo(NamedTuple):
    """Per-pair diagnostics of :func:`estimate_homography`, each (B,).

    converged: the estimate can be trusted (see the module docstring for the checks).
    residual: RMS of img2(H p) - img1(p) over the overlap at full resolution, at the last
        evaluated estimate (before the final update of at most ``step_tol`` px).
    iterations: IC iterations summed over levels.
    overlap: fraction of img1's pixels whose mapped position lies inside img2.
    textured: the full-resolution Hessian passed the ``min_texture`` test.
    """

    converged: torch.Tensor
    residual: torch.Tensor
    iterations: torch.Tensor
    overlap: torch.Tensor
    textured: torch.Tensor


# ------------------------------------------------------------------ IC Jacobian as moments
# Parameters p1..p8: H(p) = [[1 + p1, p3, p5], [p2, 1 + p4, p6], [p7, p8, 1]] (Baker-Matthews).
# dW/dp at p = 0 in the monomials [1, u, v, u^2, uv, v^2]:
#   dWx/dp = [u, 0, v, 0, 1, 0, -u^2, -uv],  dWy/dp = [0, u, 0, v, 0, 1, -uv, -v^2].
_E2 = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
_E4 = [(i - j, j) for i in range(5) for j in range(i + 1)]
_PX = torch.zeros(8, 6, dtype=torch.float64)
_PY = torch.zeros(8, 6, dtype=torch.float64)
for _k, _m, _v in [(0, 1, 1), (2, 2, 1), (4, 0, 1), (6, 3, -1), (7, 4, -1)]:
    _PX[_k, _m] = _v
for _k, _m, _v in [(1, 1, 1), (3, 2, 1), (5, 0, 1), (6, 4, -1), (7, 5, -1)]:
    _PY[_k, _m] = _v
# H_kl = sum g_x^2 Px_k Px_l + g_x g_y (Px_k Py_l + Py_k Px_l) + g_y^2 Py_k Py_l, in degree-4 moments.
_C = torch.zeros(3, len(_E4), 8, 8, dtype=torch.float64)
for _a, (_i, _j) in enumerate(_E2):
    for _b, (_r, _s) in enumerate(_E2):
        _q = _E4.index((_i + _r, _j + _s))
        _C[0, _q] += torch.outer(_PX[:, _a], _PX[:, _b])
        _C[1, _q] += torch.outer(_PX[:, _a], _PY[:, _b]) + torch.outer(_PY[:, _a], _PX[:, _b])
        _C[2, _q] += torch.outer(_PY[:, _a], _PY[:, _b])


def _monomials(u: torch.Tensor, v: torch.Tensor, exps) -> torch.Tensor:
    """(N,) u, v -> (N, len(exps)) float32 monomials u^i v^j."""
    return torch.stack([u**i * v**j for i, j in exps], dim=1).float().contiguous()


class _Frame:
    """Coordinates of one pyramid level: level pixels <-> centred, half-diagonal units."""

    def __init__(self, level: int, h: int, w: int, h0: int, w0: int, device):
        f, self.level, self.h, self.w = 2.0**level, level, h, w
        self.scale = 0.5 * math.hypot(w0 - 1, h0 - 1)  # s: full-res px per unit
        cx, cy, off = (w0 - 1) / 2, (h0 - 1) / 2, (f - 1) / 2
        d = dict(dtype=torch.float64, device=device)
        self.u = (f * torch.arange(w, **d) + off - cx) / self.scale  # (w,)
        self.v = (f * torch.arange(h, **d) + off - cy) / self.scale  # (h,)
        # u -> grid_sample coordinates of this level: x0 = s u + c, x_l = (x0 - off) / f.
        ax, ay = 2 / (f * max(w - 1, 1)), 2 / (f * max(h - 1, 1))
        self.out = torch.tensor(
            [[ax * self.scale, 0, ax * (cx - off) - 1], [0, ay * self.scale, ay * (cy - off) - 1], [0, 0, 1]], **d
        )
        self.px = self.scale / f  # level pixels per unit

    def grid(self, hn: torch.Tensor) -> torch.Tensor:
        """(B, 3, 3) u -> u' homographies -> (B, h, w, 2) float32 grid_sample grid on img2."""
        g = (self.out @ hn).float()
        u, v = self.u.float(), self.v.float()
        row = g[:, None, None, :, 0] * u[None, None, :, None]  # (B, 1, w, 3)
        col = g[:, None, None, :, 1] * v[None, :, None, None] + g[:, None, None, :, 2]  # (B, h, 1, 3)
        p = row + col  # (B, h, w, 3)
        return p[..., :2] / p[..., 2:]


def _pyramid(x: torch.Tensor, levels: int) -> list[torch.Tensor]:
    pyr = [x]
    for _ in range(levels - 1):
        pyr.append(F.avg_pool2d(pyr[-1], 2))
    return pyr


def _gradients(t: torch.Tensor) -> torch.Tensor:
    """Central differences (level pixels, replicate border): (B, 1, h, w) -> (B, 2, h*w)."""
    p = F.pad(t, (1, 1, 1, 1), mode="replicate")
    gx = 0.5 * (p[:, :, 1:-1, 2:] - p[:, :, 1:-1, :-2])
    gy = 0.5 * (p[:, :, 2:, 1:-1] - p[:, :, :-2, 1:-1])
    return torch.cat([gx, gy], dim=1).flatten(2)


def _phase_correlation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Translation t (B, 2) = (tx, ty) with a(p) ~ b(p + t), level pixels, sub-pixel."""
    bsz, _, h, w = a.shape
    win = torch.outer(torch.hann_window(h, periodic=False, dtype=a.dtype, device=a.device),
                      torch.hann_window(w, periodic=False, dtype=a.dtype, device=a.device))
    a = (a - a.mean(dim=(2, 3), keepdim=True)) * win
    b = (b - b.mean(dim=(2, 3), keepdim=True)) * win
    x = torch.fft.rfft2(b[:, 0]) * torch.fft.rfft2(a[:, 0]).conj()
    mag = x.abs()
    x = x / (mag + 1e-6 * mag.amax(dim=(1, 2), keepdim=True) + 1e-30)
    r = torch.fft.irfft2(x, s=(h, w))  # peak at +t
    idx = r.flatten(1).argmax(dim=1)
    iy, ix = idx // w, idx % w
    ar = torch.arange(bsz, device=a.device)

    def sub(c, n, along_y):  # parabola through the peak and its (cyclic) neighbours
        lo, hi = (c - 1) % n, (c + 1) % n
        r0 = r[ar, iy, ix]
        rl = r[ar, lo, ix] if along_y else r[ar, iy, lo]
        rh = r[ar, hi, ix] if along_y else r[ar, iy, hi]
        den = rl - 2 * r0 + rh
        d = torch.where(den < 0, 0.5 * (rl - rh) / torch.where(den < 0, den, torch.ones_like(den)), 0.0)
        c = c.to(a.dtype) + d.clamp(-0.5, 0.5)
        return torch.where(c > n / 2, c - n, c)

    return torch.stack([sub(ix, w, False), sub(iy, h, True)], dim=1)


def _dp_matrix(dp: torch.Tensor) -> torch.Tensor:
    """(B, 8) -> (B, 3, 3) I + D(dp)."""
    z = torch.zeros_like(dp[:, 0])
    m = torch.stack([1 + dp[:, 0], dp[:, 2], dp[:, 4], dp[:, 1], 1 + dp[:, 3], dp[:, 5], dp[:, 6], dp[:, 7], 1 + z], 1)
    return m.view(-1, 3, 3)


def _apply(hn: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) x (K, 2) -> (B, K, 2)."""
    q = hn[:, None, :, :2] @ pts[None, :, :, None] + hn[:, None, :, 2:]
    return q[..., :2, 0] / q[..., 2:, 0]


def _check_h(h: object, name: str, batch: int | None = None) -> torch.Tensor:
    if not isinstance(h, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(h).__name__}")
    if h.dim() != 3 or h.shape[1:] != (3, 3) or (batch is not None and h.shape[0] != batch):
        want = f"({batch}, 3, 3)" if batch is not None else "(B, 3, 3)"
        raise ValueError(f"{name} must have shape {want}, got {tuple(h.shape)}")
    if not h.is_floating_point() or not bool(torch.isfinite(h).all()):
        raise ValueError(f"{name} must be a finite float tensor")
    return h


def _pixel_to_unit(h0: int, w0: int, device) -> torch.Tensor:
    s = 0.5 * math.hypot(w0 - 1, h0 - 1)
    return torch.tensor([[1 / s, 0, -(w0 - 1) / 2 / s], [0, 1 / s, -(h0 - 1) / 2 / s], [0, 0, 1]],
                        dtype=torch.float64, device=device)


@torch.no_grad()
def estimate_homography(
    img1: torch.Tensor,
    img2: torch.Tensor,
    init: torch.Tensor | None = None,
    config: RegistrationConfig | None = None,
) -> tuple[torch.Tensor, RegistrationInfo]:
    """Estimate the homography H with img1(p) = img2(H p), per pair of a batch.

    Args:
        img1, img2: (B, C, H, W) float in [0, 1] or uint8, C in {1, 3} (grey by ITU-R 601).
        init: optional (B, 3, 3) initial guess (pixel coordinates); replaces the phase
            correlation.
        config: :class:`RegistrationConfig`; defaults when None.

    Returns:
        H: (B, 3, 3) float64, H[:, 2, 2] = 1, pixel coordinates of img1 -> img2.
        info: :class:`RegistrationInfo` of (B,) tensors.

    Example:
        >>> x = torch.rand(1, 1, 64, 96)
        >>> H, info = estimate_homography(x, x)
        >>> bool(torch.allclose(H, torch.eye(3, dtype=H.dtype), atol=1e-4)), bool(info.converged)
        (True, True)
    """
    cfg = config if config is not None else RegistrationConfig()
    if not isinstance(cfg, RegistrationConfig):
        raise TypeError(f"config must be a RegistrationConfig or None, got {type(cfg).__name__}")
    check_image_pair(img1, img2)
    bsz, _, h0, w0 = img1.shape
    dev = img1.device
    if init is not None:
        init = _check_h(init, "init", bsz).to(device=dev, dtype=torch.float64)
    g1, g2 = to_grey(img1).float(), to_grey(img2).float()
    levels = max(1, min(cfg.levels, int(math.log2(max(min(h0, w0), 1) / 16)) + 1))
    its = [cfg.iterations[min(i, len(cfg.iterations) - 1)] for i in range(cfg.levels)][cfg.levels - levels:]
    pyr1, pyr2 = _pyramid(g1, levels), _pyramid(g2, levels)
    frames = [_Frame(l, *pyr1[l].shape[-2:], h0, w0, dev) for l in range(levels)]
    scale = frames[0].scale

    to_u = _pixel_to_unit(h0, w0, dev)
    if init is not None:
        hn = to_u @ init @ torch.linalg.inv(to_u)
    else:
        top = levels - 1
        t = _phase_correlation(pyr1[top], pyr2[top]).double() * 2.0**top / scale
        hn = torch.eye(3, dtype=torch.float64, device=dev).repeat(bsz, 1, 1)
        hn[:, :2, 2] = t
    hn = hn / hn[:, 2:, 2:]

    corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]], dtype=torch.float64, device=dev)
    corners = corners * torch.tensor([(w0 - 1) / 2, (h0 - 1) / 2], dtype=torch.float64, device=dev) / scale
    f64 = dict(dtype=torch.float64, device=dev)
    iterations = torch.zeros(bsz, dtype=torch.int64, device=dev)
    residual = torch.full((bsz,), float("nan"), **f64)
    overlap = torch.zeros(bsz, **f64)
    first_res = torch.full((bsz,), float("nan"), **f64)
    last_step = torch.full((bsz,), float("inf"), **f64)
    diverged = torch.zeros(bsz, dtype=torch.bool, device=dev)
    textured = torch.zeros(bsz, dtype=torch.bool, device=dev)
    eye = torch.eye(8, **f64)
    c4 = _C.to(dev)
    px_m, py_m = _PX.to(dev), _PY.to(dev)

    for lv in reversed(range(levels)):
        fr, t1, t2 = frames[lv], pyr1[lv], pyr2[lv]
        finest = lv == 0
        uu = fr.u[None, :].expand(fr.h, fr.w).reshape(-1)
        vv = fr.v[:, None].expand(fr.h, fr.w).reshape(-1)
        mono2, mono4 = _monomials(uu, vv, _E2), _monomials(uu, vv, _E4)
        grad = _gradients(t1)  # (B, 2, N)
        # Hessian pixels: those mapping `margin` level px inside img2 under the current estimate.
        lim = 1 - 2 * cfg.margin / torch.tensor([max(fr.w - 1, 1), max(fr.h - 1, 1)], device=dev)
        mask = (fr.grid(hn).abs() <= lim).all(-1).flatten(1).float()  # (B, N)
        g2p = torch.cat([grad[:, :1] ** 2, grad[:, :1] * grad[:, 1:], grad[:, 1:] ** 2], 1) * mask[:, None]
        hess = torch.einsum("bcm,cmkl->bkl", (g2p @ mono4).double(), c4)  # pixel units
        n = mask.sum(1).double().clamp_min(1)
        eig_min = torch.linalg.eigvalsh(hess / n[:, None, None])[:, 0]
        ok = eig_min > cfg.min_texture
        if finest:
            textured = ok
        damp = cfg.damping * hess.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-30)
        hinv = torch.linalg.solve(hess + damp[:, None, None] * eye, eye.expand(bsz, 8, 8))
        tol = cfg.step_tol * 2.0**lv
        frozen = diverged | ~ok  # evaluated once at full resolution (residual, overlap), never moved
        active = torch.arange(bsz, device=dev) if finest else torch.nonzero(~frozen).flatten()
        t1f, g2f = t1.flatten(1), pyr2[lv]
        sub = None
        for it in range(its[lv]):
            if active.numel() == 0:
                break
            if sub is None or sub[0].numel() != active.numel():
                sub = (active, t1f[active], grad[active], g2f[active], mask[active], hinv[active], ~frozen[active])
            idx, ta, ga, ia, ma, hi, oka = sub
            ha = hn[idx]
            grid = fr.grid(ha)
            warped = F.grid_sample(ia, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
            inside = (grid.abs() <= 1).all(-1).flatten(1)
            e = (warped.flatten(1) - ta) * inside
            ew = e * ma
            mom = (ga * ew[:, None]) @ mono2  # (b, 2, 6)
            bvec = mom[:, 0].double() @ px_m.T + mom[:, 1].double() @ py_m.T
            dp = (hi @ bvec[:, :, None])[:, :, 0] / fr.px
            dp = torch.where(oka[:, None], dp, torch.zeros_like(dp))
            h_new = ha @ torch.linalg.inv(_dp_matrix(dp))
            h_new = h_new / h_new[:, 2:, 2:]
            step = (_apply(h_new, corners) - _apply(ha, corners)).norm(dim=-1).amax(1) * scale
            n_in = inside.sum(1).double()
            ov = n_in / inside.shape[1]
            bad = ~torch.isfinite(step) | (step > cfg.max_step * 2 * scale) | (ov < cfg.min_overlap)
            hn[idx] = torch.where(bad[:, None, None], ha, h_new)
            iterations[idx] += 1
            if finest:
                res = ((e.double() ** 2).sum(1) / n_in.clamp_min(1)).sqrt()
                residual[idx], overlap[idx], last_step[idx] = res, ov, step
                first_res[idx] = torch.where(first_res[idx].isnan(), res, first_res[idx])
            diverged[idx] |= bad
            done = bad | (step < tol) | ~oka
            if bool(done.any()):
                active = idx[~done]
    grew = residual > first_res * 1.01 + 1e-4
    converged = textured & ~diverged & (last_step < cfg.step_tol) & ~grew & (overlap >= cfg.min_overlap)
    converged &= torch.isfinite(hn).all(dim=(1, 2))
    h = torch.linalg.inv(to_u) @ hn @ to_u
    h = h / h[:, 2:, 2:]
    return h, RegistrationInfo(converged, residual.float(), iterations, overlap.float(), textured)


def warp_to_reference(
    img2: torch.Tensor, H: torch.Tensor, dsize: tuple[int, int] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp img2 into img1's frame: warped(p) = img2(H p), and the validity of each pixel.

    The image goes through ``kornia.geometry.warp_perspective`` (bilinear, zero padding,
    ``align_corners=True``) with ``H^-1`` (kornia takes the src -> dst map). The mask is
    computed from the mapped coordinates directly, in float64: valid = 1 where H p lies in
    [0, W-1] x [0, H-1] of img2, with 1e-3 px of slack for rounding (such a sample is within
    0.1 % of the border pixel). It is not eroded (the quality metric erodes it).

    Args:
        img2: (B, C, H, W) float or uint8 (uint8 is divided by 255).
        H: (B, 3, 3) float homographies, img1 pixel coordinates -> img2's.
        dsize: (height, width) of the output; img2's size when None.

    Returns:
        warped: (B, C, h, w) in img2's float dtype (float32 for uint8). valid: (B, 1, h, w), 0 or 1.
    """
    check_image(img2, "img2")
    H = _check_h(H, "H", img2.shape[0])
    if dsize is None:
        dsize = (int(img2.shape[-2]), int(img2.shape[-1]))
    if not (isinstance(dsize, (tuple, list)) and len(dsize) == 2 and all(isinstance(d, int) and d > 0 for d in dsize)):
        raise ValueError(f"dsize must be (height, width) positive ints or None, got {dsize!r}")
    img = img2.float() / 255.0 if img2.dtype == torch.uint8 else img2
    h64 = H.to(device=img.device, dtype=torch.float64)
    if not bool((torch.linalg.det(h64).abs() > 1e-12).all()):
        raise ValueError("H must be invertible")
    warped = warp_perspective(img, torch.linalg.inv(h64).to(img.dtype), dsize, mode="bilinear",
                              padding_mode="zeros", align_corners=True)
    hh, ww = dsize
    d = dict(dtype=torch.float64, device=img.device)
    x, y = torch.arange(ww, **d)[None, None, :], torch.arange(hh, **d)[None, :, None]
    q = [h64[:, i, 0, None, None] * x + h64[:, i, 1, None, None] * y + h64[:, i, 2, None, None] for i in range(3)]
    xs, ys = q[0] / q[2], q[1] / q[2]
    tol = 1e-3
    w_in, h_in = img2.shape[-1] - 1 + tol, img2.shape[-2] - 1 + tol
    valid = (q[2] > 0) & (xs >= -tol) & (xs <= w_in) & (ys >= -tol) & (ys <= h_in)
    return warped, valid[:, None].to(warped.dtype)


def perturb_homography(
    H: torch.Tensor,
    generator: torch.Generator | Sequence[torch.Generator],
    amount: float = 0.01,
    *,
    size: tuple[int, int],
) -> torch.Tensor:
    """SPEC 7's class-R perturbation, in centred coordinates.

    H_c = T(-p0) H T(p0), h33 = 1; each of its 8 free parameters (row-major h11..h32) is
    multiplied by (1 + e), e ~ U[-amount, amount] drawn as ``torch.rand(8, float64)`` from the
    pair's generator (in that order); the result is T(p0) H_c T(-p0), h33 = 1. p0 = ((W-1)/2,
    (H-1)/2).

    Args:
        H: (3, 3) with one generator, or (B, 3, 3) with a sequence of B generators (one per
            pair, SPEC 7; a single generator is accepted for B = 1 only).
        generator: torch.Generator or sequence of them (CPU or H's device).
        amount: half-width of the relative perturbation.
        size: (height, width) of the images H applies to.

    Returns:
        The perturbed homographies, H's shape and dtype.
    """
    if not isinstance(H, torch.Tensor) or H.dim() not in (2, 3) or H.shape[-2:] != (3, 3):
        raise ValueError(f"H must be a (3, 3) or (B, 3, 3) tensor, got {getattr(H, 'shape', type(H).__name__)}")
    if not H.is_floating_point():
        raise TypeError(f"H must be a float tensor, got {H.dtype}")
    gens = [generator] if isinstance(generator, torch.Generator) else list(generator)
    hb = H if H.dim() == 3 else H[None]
    if len(gens) != hb.shape[0] or not all(isinstance(g, torch.Generator) for g in gens):
        raise ValueError(f"generator must be one torch.Generator per pair ({hb.shape[0]}), got {generator!r}")
    if not (isinstance(amount, (int, float)) and 0 <= amount < 1):
        raise ValueError(f"amount must be a number in [0, 1), got {amount!r}")
    if not (isinstance(size, (tuple, list)) and len(size) == 2 and all(s > 0 for s in size)):
        raise ValueError(f"size must be (height, width), got {size!r}")
    e = torch.stack([torch.rand(8, generator=g, dtype=torch.float64, device=g.device) for g in gens])
    e = (2 * e - 1).to(H.device) * amount
    p0x, p0y = (size[1] - 1) / 2, (size[0] - 1) / 2
    t_plus = torch.tensor([[1, 0, p0x], [0, 1, p0y], [0, 0, 1]], dtype=torch.float64, device=H.device)
    t_minus = torch.tensor([[1, 0, -p0x], [0, 1, -p0y], [0, 0, 1]], dtype=torch.float64, device=H.device)
    hc = t_minus @ hb.double() @ t_plus
    hc = (hc / hc[:, 2:, 2:]).flatten(1)
    hc = torch.cat([hc[:, :8] * (1 + e), hc[:, 8:]], 1).view(-1, 3, 3)
    out = t_plus @ hc @ t_minus
    out = (out / out[:, 2:, 2:]).to(H.dtype)
    return out if H.dim() == 3 else out[0]


def corner_error(H_est: torch.Tensor, H_true: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Mean distance (px) between the 4 image corners mapped by H_est and by H_true.

    Args:
        H_est, H_true: (B, 3, 3) or (3, 3). height, width: the image size.

    Returns:
        (B,) float64 (B = 1 for (3, 3) inputs).
    """
    a, b = (x if isinstance(x, torch.Tensor) and x.dim() == 3 else x[None] for x in (H_est, H_true))
    _check_h(a, "H_est")
    _check_h(b, "H_true", a.shape[0])
    pts = torch.tensor([[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]],
                       dtype=torch.float64, device=a.device)
    return (_apply(a.double(), pts) - _apply(b.double().to(a.device), pts)).norm(dim=-1).mean(1)
