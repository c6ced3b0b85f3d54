"""The homography model's lens, residual, Jacobian and Levenberg-Marquardt (docs/method.md, section 12).

The lens (:mod:`~lensdist_torch.geometry.radial_lens`) maps a pixel p to its ideal point
c + (p - c) (1 + a_1 r^2 + ... + a_n r^(2n)), r = |p - c| / R (c the distortion centre, the frame
centre unless the fit frees it; R the frame's half diagonal); n = 2 with c the frame centre is eq. 4. A
match between two views of a plane is explained by the lens and its pair's homography H (img1's ideal
points to img2's, normalised frame, H[2, 2] = 1): the residual is the symmetric transfer error, each
side divided by the lens's factor at the point, so it reads about in the image's pixels (times R).

Its measures: Delta over the frame where the map is monotone, and how well the map's bending is
known (a jackknife's half-width of what no homography takes away).

Each pair's homography between ideal points by COLMAP's LO-RANSAC (:func:`pair_homographies`): the
start's scan and the guided matching's chain of views both take it.

The fitted parameter vector ``theta`` is (a_1 .. a_n) with the centre fixed at the frame's, or
(a_1 .. a_n, d_x, d_y) with the centre free, d its offset from the frame centre over R (``terms``
= n tells them apart; a translation of the ideal points is the homographies' to absorb).
:mod:`~lensdist_torch.calibration.planar_features` fits it.
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.calibration.multiview import pycolmap_or_error
from lensdist_torch.calibration.pooling import t_quantile
from lensdist_torch.geometry.distortion import distortion_center
from lensdist_torch.geometry.frame import grid_near, grid_points, half_diagonal
from lensdist_torch.geometry.radial_lens import lens_factor, lens_factor_derivative, lens_ideal_points, lens_inverts

__all__ = ["split_lens", "transfer_residuals", "transfer_jacobians", "fit_lens_and_homographies",
           "transfer_errors", "lens_covariance", "lens_of", "lens_deltas", "bending_halfwidth", "pair_homographies"]


# ------------------------------------------------------------------ the lens and the residual
def _adjugate(m: torch.Tensor) -> torch.Tensor:
    """The adjugates of (..., 3, 3) matrices (inverse times determinant) in closed form, differentiable and batched.

    (``torch.linalg.solve`` under ``vmap(jacfwd)`` gave wrong derivatives here.)
    """
    def cross(x, y):  # written out: linalg.cross has no fast batching rule under forward-mode AD
        return torch.stack(
            [
                x[..., 1] * y[..., 2] - x[..., 2] * y[..., 1],
                x[..., 2] * y[..., 0] - x[..., 0] * y[..., 2],
                x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0],
            ],
            -1,
        )

    c0, c1, c2 = m[..., :, 0], m[..., :, 1], m[..., :, 2]
    return torch.stack([cross(c1, c2), cross(c2, c0), cross(c0, c1)], -2)


def split_lens(theta: torch.Tensor, terms: int | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``theta``'s lens coefficients (n,) and its centre offset (2,) over R, or None where the centre is fixed."""
    n = theta.shape[-1] if terms is None else terms
    return theta[..., :n], (theta[..., n:n + 2] if theta.shape[-1] > n else None)


def transfer_residuals(theta: torch.Tensor, h: torch.Tensor, v1: torch.Tensor, v2: torch.Tensor,
                       *,
                       terms: int | None = None, pair: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 4) symmetric transfer errors of N matches (normalised frame, ``v = (p - c) / R``) over the lens's scale.

    ``theta``: the lens (module docstring; ``terms`` its number of coefficients, all when None).
    ``h`` (N, 8): each match's pair's homography (the ninth entry 1) in the normalised frame; or
    (P, 8), the pairs' homographies, with ``pair`` (N,) each match's pair (the inverses are then
    formed once per pair, not per match).
    """
    a, d = split_lens(theta, terms)
    if d is not None:  # about the free centre: the offset of the ideal points is the homographies'
        v1, v2 = v1 - d, v2 - d
    f1, f2 = lens_factor((v1 * v1).sum(-1, keepdim=True), a), lens_factor((v2 * v2).sum(-1, keepdim=True), a)
    u1, u2 = v1 * f1, v2 * f2
    m = torch.cat([h, h.new_ones(len(h), 1)], 1).reshape(-1, 3, 3)
    adj = _adjugate(m)
    if pair is not None:
        m, adj = m[pair], adj[pair]
    q = m[:, :, 0] * u1[:, :1] + m[:, :, 1] * u1[:, 1:] + m[:, :, 2]  # elementwise: 3 x 3 bmm is slow under AD
    back = adj[:, :, 0] * u2[:, :1] + adj[:, :, 1] * u2[:, 1:] + adj[:, :, 2]  # H^-1 up to scale
    return torch.cat([(q[:, :2] / q[:, 2:] - u2) / f2, (back[:, :2] / back[:, 2:] - u1) / f1], 1)


def transfer_jacobians(a: torch.Tensor, h: torch.Tensor, v1: torch.Tensor, v2: torch.Tensor,
                       *,
                       terms: int | None = None, pair: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 4, n) and (N, 4, 8): the residuals' derivatives by the lens ``a`` (``theta``) and by each match's homography.

    ``h`` and ``pair`` as :func:`transfer_residuals`. In closed form (tests check it against finite
    differences and forward-mode AD): with u = v f(|v|^2) an ideal point, F = proj(H [u1; 1]) and
    B = proj(H^-1 [u2; 1]), the forward residual is (F - u2) / f2 and the backward (B - u1) / f1;
    proj's derivative at y is [I | -proj(y)] / y_3, and H^-1's by an entry E of H is -H^-1 E H^-1.
    """
    coef, d = split_lens(a, terms)
    eye2 = torch.eye(2, dtype=a.dtype)
    if d is not None:
        v1, v2 = v1 - d, v2 - d

    def lens(v):  # u, f, du/dtheta (N, 2, n_theta), df/dtheta (N, n_theta)
        s = (v * v).sum(-1, keepdim=True)
        f, g = lens_factor(s, coef), lens_factor_derivative(s, coef)
        powers = s ** torch.arange(1, coef.shape[-1] + 1, dtype=a.dtype)  # df/da_k = s^k
        du, df = v[:, :, None] * powers[:, None, :], powers
        if d is not None:  # v = p - c - d: du/dd = -(f I + 2 g v v^T), df/dd = -2 g v
            du = torch.cat([du, -(f[..., None] * eye2 + 2 * g[..., None] * v[:, :, None] * v[:, None, :])], 2)
            df = torch.cat([df, -2 * g * v], 1)
        return v * f, f, du, df

    u1, f1, du1, df1 = lens(v1)
    u2, f2, du2, df2 = lens(v2)
    m = torch.cat([h, h.new_ones(len(h), 1)], 1).reshape(-1, 3, 3)
    adj = _adjugate(m)
    inv = adj / (adj[:, 0, :] * m[:, :, 0]).sum(-1)[:, None, None]  # adj(M) M = det(M) I
    if pair is not None:
        m, inv = m[pair], inv[pair]
    w1, w2 = torch.cat([u1, torch.ones_like(f1)], 1), torch.cat([u2, torch.ones_like(f2)], 1)

    def projection(y):  # proj(y) and its derivative [I | -proj(y)] / y_3, (N, 2, 3)
        p = y[:, :2] / y[:, 2:]
        return p, torch.cat([eye2.expand(len(y), 2, 2), -p[:, :, None]], 2) / y[:, 2:, None]

    y1 = (m @ w1[..., None])[..., 0]
    fwd, gf = projection(y1)
    y2 = (inv @ w2[..., None])[..., 0]
    bwd, gb = projection(y2)
    gbi = gb @ inv
    rf, rb = (fwd - u2) / f2, (bwd - u1) / f1
    ja = torch.cat([((gf @ m)[:, :, :2] @ du1 - du2 - rf[:, :, None] * df2[:, None, :]) / f2[..., None],
                    (gbi[:, :, :2] @ du2 - du1 - rb[:, :, None] * df1[:, None, :]) / f1[..., None]], 1)
    jh = torch.cat([(gf[:, :, :, None] * w1[:, None, None, :]).reshape(-1, 2, 9)[..., :8] / f2[..., None],
                    -(gbi[:, :, :, None] * y2[:, None, None, :]).reshape(-1, 2, 9)[..., :8] / f1[..., None]], 1)
    return ja, jh


def _normal_equations(a, hs, v1, v2, *, pair, w, terms):
    """The weighted Gauss-Newton blocks at (``a``, ``hs``), the pairs' to be eliminated (Schur complement).

    Per pair U (P, 8, 8) and W (P, 8, n), the lens's V (n, n), the gradients' negatives g_h (P, 8) and g_a (n,),
    and the weighted sum of squared residuals.
    """
    n_pairs = hs.shape[0]
    r = transfer_residuals(a, hs, v1, v2, terms=terms, pair=pair)
    ja, jh = transfer_jacobians(a, hs, v1, v2, terms=terms, pair=pair)
    wr = w[:, None, None]
    uhh = torch.zeros(n_pairs, 8, 8, dtype=a.dtype).index_add_(0, pair, (jh.transpose(1, 2) @ (wr * jh)))
    whd = torch.zeros(n_pairs, 8, a.numel(), dtype=a.dtype).index_add_(0, pair, (jh.transpose(1, 2) @ (wr * ja)))
    vdd = (ja.transpose(1, 2) @ (wr * ja)).sum(0)
    gh = -torch.zeros(n_pairs, 8, dtype=a.dtype).index_add_(
        0, pair, (jh.transpose(1, 2) @ (w[:, None] * r)[..., None])[..., 0]
    )
    gd = -(ja.transpose(1, 2) @ (w[:, None] * r)[..., None])[..., 0].sum(0)
    return uhh, whd, vdd, gh, gd, float((w[:, None] * r * r).sum())


def fit_lens_and_homographies(a: torch.Tensor, hs: torch.Tensor, v1, v2, *, pair, w, iterations: int,
                              terms: int | None = None, lens_held: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Levenberg-Marquardt on the lens ``a`` (``theta``, ``terms``) and the pairs' homographies ``hs`` (P, 8) (step 3).

    ``w`` (N,) weights the matches (0: left out; a pair without weight keeps its homography). The
    pairs' blocks are eliminated (Schur complement). ``lens_held``: the homographies alone move
    (a held-out pair posed again under a lens fitted without it).
    """
    lam = 1e-3

    def cost(a_, hs_):
        r = transfer_residuals(a_, hs_, v1, v2, terms=terms, pair=pair)
        return float((w[:, None] * r * r).sum())

    c0 = cost(a, hs)
    eye8 = torch.eye(8, dtype=a.dtype)
    for _ in range(iterations):
        uhh, whd, vdd, gh, gd, _ = _normal_equations(a, hs, v1, v2, pair=pair, w=w, terms=terms)
        while True:
            ud = uhh + lam * (torch.diagonal(uhh, dim1=1, dim2=2)[..., None] * eye8 + 1e-12 * eye8)
            ui = torch.linalg.pinv(ud)
            if lens_held:
                da = torch.zeros_like(a)
            else:
                s = vdd + lam * torch.diag(torch.diagonal(vdd) + 1e-12) - torch.einsum("pji,pjk,pkl->il", whd, ui, whd)
                rhs = gd - torch.einsum("pji,pjk,pk->i", whd, ui, gh)
                da = torch.linalg.lstsq(s, rhs[:, None]).solution[:, 0]
            dh = torch.einsum("pij,pj->pi", ui, gh - whd @ da)
            c1 = cost(a + da, hs + dh)
            if math.isfinite(c1) and c1 < c0:
                a, hs, lam = a + da, hs + dh, max(lam / 3, 1e-9)
                break
            lam *= 5
            if lam > 1e8:
                return a, hs
        done = (c0 - c1) <= 1e-10 * c0
        c0 = c1
        if done:
            break
    return a, hs


def lens_covariance(a: torch.Tensor, hs: torch.Tensor, v1, v2, *, pair, w, terms: int | None = None):
    """The covariance (n, n) of the fitted lens ``a`` (``theta``), every pair's homography marginalised, or None.

    The inverse of the lens's Schur complement V - sum_p W_p^T U_p^-1 W_p at the fit, times
    RSS / (2 N - 8 P - n) over the N weighted matches and P pairs that hold them: a match's
    forward and backward transfer errors measure one 2-D misfit twice, so the normal matrix and the
    RSS both count it twice and the degrees of freedom once. None where they are not positive or
    the complement is singular (the matches do not determine the lens).
    """
    uhh, whd, vdd, _, _, rss = _normal_equations(a, hs, v1, v2, pair=pair, w=w, terms=terms)
    held = torch.zeros(hs.shape[0], dtype=torch.bool)
    held[pair[w > 0]] = True
    s = vdd - torch.einsum("pji,pjk,pkl->il", whd[held], torch.linalg.pinv(uhh[held]), whd[held])
    dof = 2 * int((w > 0).sum()) - 8 * int(held.sum()) - a.numel()
    if dof <= 0 or torch.linalg.matrix_rank(s) < a.numel():
        return None
    return rss / dof * torch.linalg.inv(s)


def transfer_errors(a, hs, v1, v2, *, pair, big_r: float, terms: int | None = None) -> torch.Tensor:
    """(N,) each match's larger transfer error in pixels."""
    return transfer_residuals(a, hs, v1, v2, terms=terms, pair=pair).reshape(-1, 2, 2).norm(dim=-1).amax(-1) * big_r


def pair_homographies(u1: torch.Tensor, u2: torch.Tensor, pair: torch.Tensor, *, which, max_error, seed: int):
    """Each listed pair's homography between its matches' ideal points, by COLMAP's LO-RANSAC.

    Args:
        u1: (N, 2) float64 ideal points (pixels) of the matches in their pairs' first views.
        u2: (N, 2) their partners in the second views.
        pair: (N,) each match's pair.
        which: the pairs' indices to fit.
        max_error: RANSAC's threshold (px), or a function of a pair's match indices giving it.
        seed: RANSAC's random seed.

    Yields:
        (p, idx, H, inliers): the pair, its matches' indices (into ``u1``), H (3, 3) float64 from
        u1 to u2 with H[2, 2] = 1 (None where RANSAC found none) and its inlier mask over ``idx``.

    Example:
        >>> u = torch.rand(30, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 100
        >>> [(p, round(float(h[0, 2]), 3), int(m.sum())) for p, _, h, m in  # a shift by 2 px
        ...  pair_homographies(u, u + 2.0, torch.zeros(30, dtype=torch.long), which=[0], max_error=1.0, seed=0)]
        [(0, 2.0, 30)]
    """
    pc = pycolmap_or_error()
    options = pc.RANSACOptions()
    options.random_seed = seed
    for p in which:
        idx = (pair == p).nonzero()[:, 0]
        options.max_error = max_error(idx) if callable(max_error) else max_error
        est = pc.estimate_homography_matrix(u1[idx].numpy(), u2[idx].numpy(), options)
        if est is None:
            yield p, idx, None, None
            continue
        hm = torch.as_tensor(est["H"], dtype=torch.float64)
        yield p, idx, hm / hm[2, 2], torch.as_tensor(est["inlier_mask"], dtype=torch.bool).reshape(-1)


# ------------------------------------------------------------------ the lens map's measures
def lens_of(theta: torch.Tensor, terms: int, size: tuple[int, int]) -> tuple[list[float], list[float]]:
    """The lens ``theta`` as :func:`lens_ideal_points` takes it: its coefficients and its centre (x, y) in pixels."""
    h, w = size
    a, d = split_lens(theta, terms)
    off = [0.0, 0.0] if d is None else (d * half_diagonal(h, w)).tolist()
    return a.tolist(), [c + o for c, o in zip(distortion_center(h, w), off)]


def lens_deltas(theta: torch.Tensor, terms: int, size: tuple[int, int], step: int) -> dict:
    """Delta (px) of the lens ``theta`` over a ``step``-spaced grid where its map is monotone.

    Returns ``delta_avg_px``, ``delta_max_px``, ``invertible_fraction``, the grid ``points``, the mask ``ok`` and
    the grid's ``step``.
    """
    h, w = size
    a, centre = lens_of(theta, terms, size)
    p = grid_points(h, w, step)
    ok = lens_inverts(p, a, h, w, centre=centre)
    off = (lens_ideal_points(p, a, h, w, centre=centre) - p).norm(dim=-1)[ok]
    if off.numel() == 0:
        return {"delta_avg_px": math.nan, "delta_max_px": math.nan, "invertible_fraction": 0.0, "points": p, "ok": ok,
                "step": step}
    return {"delta_avg_px": float(off.mean()), "delta_max_px": float(off.max()),
            "invertible_fraction": float(ok.double().mean()), "points": p, "ok": ok, "step": step}


def bending_halfwidth(theta, replicates: list, *, n: int, size: tuple[int, int], dl: dict, confidence: float,
                       seen: torch.Tensor) -> tuple[float, float]:
    """The jackknife's half-width (px, RMS) of the lens map's bending where matches reach, and that share of the frame.

    Each replicate's ideal points are mapped onto the answer's by the best affine map (a change of
    the lens's scale or centre is about one); what remains is its bending. Half-width: t on
    replicates - 1 degrees of freedom times sqrt((B - 1) / B sum of the mean squared remainders),
    over the pixels within 5 % of the half diagonal of a match ``seen`` (M, 2) (beyond, the
    polynomial extrapolates).
    """
    h, w = size
    big_r = half_diagonal(h, w)
    p = dl["points"][dl["ok"]]
    if len(seen):
        p = p[grid_near(seen, h, w, step=dl["step"], radius=0.05 * big_r)[dl["ok"]]]
    share = len(p) / max(len(dl["points"]), 1)
    if len(replicates) < 2 or len(p) < 3 or not len(seen):
        return math.nan, share
    a, centre = lens_of(theta, n, size)
    x = lens_ideal_points(p, a, h, w, centre=centre)
    design = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], 1)
    msq = []
    for tj in replicates:
        a, centre = lens_of(tj, n, size)
        y = lens_ideal_points(p, a, h, w, centre=centre)
        fit = design @ torch.linalg.lstsq(design, y).solution
        msq.append(float(((y - fit) ** 2).sum(-1).mean()))
    b = len(replicates)
    return t_quantile(0.5 + confidence / 2, b - 1) * math.sqrt((b - 1) / b * sum(msq)), share
