"""Self-calibration: the distortion (k2, k4) and the homography of a pair, estimated together.

Both images carry the same radial distortion (docs/method.md, section 6, eq. 4). Per pair we
fit 8 parameters of a homography H_n, 2 distortion coefficients (a, b) and, by default, a
photometric gain and bias, by robust (IRLS) Levenberg-Marquardt on the photometric residual,
batched over pairs, coarse to fine (2 x 2 mean pyramid), in the normalised frame of
:mod:`~lensdist_torch.geometry.frame` (docs/method.md, section 10):

    u_d  = (p_d - p0) / R                 normalised distorted point of img1, R = half diagonal
    u    = u_d (1 + a |u_d|^2 + b |u_d|^4)   eq. 4: the ideal point
    v    = H_n u                          (projective)
    v_d  = eq. 4 inverted by Newton on the radius (differentiable)
    r    = img1(p_d) - (g img2(p0 + R v_d) + c)   over the pixels whose v_d lies inside img2

In normalised radius the coefficients are O(0.1): a = k2 R^2, b = k4 R^4 (docs/method.md, section 10);
both signs are allowed (pincushion too). (a, b) are held at 0 on the levels coarser than :data:`DISTORTION_LEVELS`:
there they trade off with H on few samples and can lead the fit into a far minimum. The Jacobian is analytic
(chain rule through eq. 4, the homography and the implicit derivative of the Newton inverse), times the image
gradient of img2; one sampling of (img2, d/dx, d/dy) per iteration (:mod:`.selfcal_model`).

Interpolation (:data:`SAMPLING`): img2 and its gradients are sampled by the mean of the bilinear and
the bicubic kernel (``blend``, default; :func:`.selfcal_model.sample_image`); the plane + parallax stage below
samples bilinearly.

Photometric model (``model.PHOTOMETRIC_MODEL``): ``gain_bias`` (default) fits g and c with the rest under the robust
weights, started at the ratio of the robust standard deviations (1.4826 MAD) and the difference of the medians
of the coarsest level; ``normalized`` compares zero-mean, unit-variance samples instead (moments that outliers
move, and that jump as samples enter or leave the overlap); ``none`` compares raw intensities.

Robust loss (``model.ROBUST_LOSS``): each LM iteration solves the weighted normal equations
(J W J^T + lambda diag) d = -J W r with Tukey (default) or Huber weights of z = r / sigma, sigma = 1.4826 MAD of
the pair's residuals, re-estimated every iteration; a step is accepted where the robust cost 2 sigma^2 mean
rho(z), at the same sigma, falls. Tukey's weights drop an occluder entirely; Huber's keep a bounded pull that can
drag the gain down.

Starts. Without ``init``, H starts at the phase correlation of the coarsest level. With ``init`` (e.g.
:func:`estimate_homography`'s H, which absorbs part of the distortion and can hold the fit in a wrong minimum)
and :data:`BOTH_STARTS`, both starts are fitted in the same batch and, per pair, the one with the lower final
robust cost (at the smaller of the two sigmas; a flagged start loses) is kept; a = b = 0 in both.

Confidence. The weighted Gauss-Newton covariance s_w^2 (J W J^T)^-1, s_w^2 = sum w r^2 / (sum w - P)
(W the final IRLS weights), is propagated to Delta_avg through its gradient in (a, b): ``delta_avg_std`` (px).
With little motion the distortion of the two views cancels, J's (a, b) columns vanish and the std explodes.
``confidence = s0 / (s0 + delta_avg_std)`` with s0 = :data:`CANNOT_TELL_STD_PX`; below
:data:`CONFIDENCE_THRESHOLD` the answer is "cannot tell from this pair" (``info.confident`` False; the
numbers are still returned).

Divergence. A pair whose fit goes non-finite, leaves the plausible range (|a|, |b| <= :data:`MAX_COEFFICIENT`,
the gain within ``selfcal_model.GAIN_RANGE``), makes eq. 4 non-invertible on the image (dr/dr_d <= 0), keeps
less than :data:`MIN_OVERLAP` of its samples inside img2 or ends with a larger robust cost than it started with
gets ``converged`` False and k2 = k4 = NaN, H = NaN: flagged, never returned as a number.

Device: the images' (CUDA included); the model in float32, the normal equations in float64.

References:
    B. Möller, S. Posch, "Automatic Analysis of Lens Distortions in Image Registration", Institute
    of Computer Science, Martin Luther University Halle-Wittenberg (venue and year not in the text
    the project worked from; docs/method.md): eq. 4, the distortion model fitted here.
    S. Baker, I. Matthews, "Lucas-Kanade 20 years on: a unifying framework", IJCV 56(3), 2004
    (image alignment by Gauss-Newton on the photometric residual).
    P. J. Huber, "Robust Statistics", Wiley, 1981 (the M-estimator weights).
"""

from __future__ import annotations

import torch

from lensdist_torch.config import SelfCalConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.chunks import chunk_slices
from lensdist_torch.core.images import check_image_pair, to_grey
from lensdist_torch.geometry.distortion import from_normalized, pixel_offsets
from lensdist_torch.geometry.frame import half_diagonal, level_to_grid, normalized_grid, normalizer
from lensdist_torch.geometry.homography import mean_displacement
from lensdist_torch.geometry.phase import phase_correlation
from lensdist_torch.geometry.pyramid import mean_pyramid
from lensdist_torch.selfcal import model as _model  # ROBUST_LOSS, PHOTOMETRIC_MODEL read at call time
from lensdist_torch.selfcal import solver
from lensdist_torch.selfcal.model import (
    GAIN_RANGE,
    MARGIN,
    NEWTON,
    NOISE_FLOOR,
    PARALLAX_WIDTH,
    Level,
    SelfCalInfo,
    distort_normalized,
    evaluate,
    h_matrix,
    homography_parameters,
    planar_parameters,
    plausible,
    relief_basis,
    relief_direction,
    robust_constant,
    robust_cost,
    robust_scale,
    robust_weights,
    select_samples,
    selfcal_residual,
    undistort_normalized,
    with_gradients,
)
from lensdist_torch.selfcal.prior import (
    posterior_inverse,
    relief_p_value,
    relief_score,
    relief_step,
)
from lensdist_torch.selfcal.regions import aligned_residual, cluster_robust_covariance, region_ids

__all__ = [
    "BOTH_STARTS", "CANNOT_TELL_STD_PX", "CLUSTERS", "CONFIDENCE_THRESHOLD", "DAMPING", "DISTORTION_LEVELS",
    "ITERATIONS", "LEVELS", "MAX_COEFFICIENT", "MIN_OVERLAP", "OCCLUDED_SHARE", "PARALLAX_BLOCK", "PARALLAX_ITERATIONS",
    "PARALLAX_SCORE_LEVEL", "PARALLAX_TEST", "SAMPLE_BLOCK", "SAMPLING", "SMALL_MOTION_ERROR", "SelfCalConfig",
    "SelfCalInfo", "estimate_distortion", "selfcal_residual", "distort_normalized", "undistort_normalized",
]


_RELIEF_INTERPOLATION = "bilinear"  # the relief stage's kernel: blended, its relief stayed on 4 of 24 flat pairs

_HAUSMAN_FLOOR_PX = 0.05  # floor (px) of the std of the difference in Hausman's test (the relief's can be below)
DAMPING = 1e-3  # initial Levenberg-Marquardt lambda, relative to diag(J^T J), at each level's start
DISTORTION_LEVELS = 2  # (a, b) are fitted on the finest this many levels; the coarser fit H and the photometry only
MAX_COEFFICIENT = 2.0  # a fit whose |a| or |b| (normalised units) exceeds this diverged
MIN_OVERLAP = 0.3  # a fit keeping a smaller share of img1's samples inside img2 diverged
CANNOT_TELL_STD_PX = 0.5  # the std of Delta_avg (px) at which a pair's confidence s0 / (s0 + std) is 0.5
CONFIDENCE_THRESHOLD = 0.5  # a confidence below this: "cannot tell from this pair" (``info.confident`` False)
LEVELS = 3  # pyramid levels (2 x 2 means), coarsest first in ITERATIONS and SAMPLE_BLOCK
ITERATIONS = (8, 4, 6)  # Levenberg-Marquardt iterations per level, coarsest first (6 at full size: unseen textures)
SAMPLE_BLOCK = (2, 4, 4)  # per level: the residual's samples, the strongest-gradient pixel of each block x block cell
PARALLAX_ITERATIONS = 6  # LM iterations of the plane + parallax model at full size, from the planar fit
PARALLAX_BLOCK = 2  # that model's samples: the strongest-gradient pixel of every block x block cell
SAMPLING = "blend"  # img2's sampling kernel: the mean of bilinear and bicubic (their sub-pixel biases cancel)
BOTH_STARTS = True  # with an init H, the phase-correlation start is fitted too; the lower robust cost is kept
CLUSTERS = 6  # the frame's clusters x clusters rectangles of the cluster-robust covariance (0: Gauss-Newton's)
OCCLUDED_SHARE = 0.15  # the share of those rectangles the aligned residual leaves out (an occluder's)
SMALL_MOTION_ERROR = 1.5e-5  # a floor e R^2 / m px on Delta_avg's std, m the pair's motion (px), R the half diagonal
PARALLAX_TEST = 2.0  # the relief's answer is kept where Delta_avg moves by this many stds of the difference (Hausman)
PARALLAX_SCORE_LEVEL = 0.01  # the relief stage is fitted where the score test rejects a plane at this level (p-value)


@torch.no_grad()
def estimate_distortion(img1, img2, *, init=None, config: SelfCalConfig | None = None, validate: bool = True):
    """Estimate (k2, k4) and H together, per pair of a batch (see the module docstring).

    Args:
        img1: (B, C, H, W) float in [0, 1] or uint8; H and W at least 16 (and 2^LEVELS).
        img2: the same shape and dtype, with the same distortion as img1.
        init: optional (B, 3, 3) homography img1 -> img2 (pixels), e.g. from :func:`estimate_homography`;
            beside the phase-correlation start (:data:`BOTH_STARTS`; the better kept).
        config: :class:`SelfCalConfig`; defaults when None.
        validate: check the images' values (one host sync); False for images already checked.

    Returns:
        k2, k4: (B,) float64 in pixel units (eq. 4), NaN where the fit diverged.
        H: (B, 3, 3) float64, img1's ideal pixel coordinates -> img2's, NaN where diverged.
        info: :class:`SelfCalInfo`. Everything on img1's device.

    Example:
        >>> from lensdist_torch.geometry.distortion import delta_avg
        >>> from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
        >>> frames, _ = synthetic_sequence(2, 4e-6, 0.0, size=(160, 212), seed=1)  # truth: Delta_avg 2.10 px
        >>> k2, k4, H, info = estimate_distortion(frames[:1], frames[1:])
        >>> abs(float(delta_avg(k2, k4, 160, 212)[0]) - 2.10) < 0.1
        True
    """
    cfg = or_defaults(config, SelfCalConfig)
    check_image_pair(img1, img2, finite=validate)
    (bsz, _, h, w), least = img1.shape, max(16, 2**LEVELS)
    if h < least or w < least:
        raise ValueError(f"img1 and img2 must be at least {least} x {least} pixels, got {h} x {w}")
    if init is not None:
        init = torch.as_tensor(init, dtype=torch.float64, device=img1.device)
        if init.shape != (bsz, 3, 3):
            raise ValueError(f"init must be ({bsz}, 3, 3), got {tuple(init.shape)}")
    parts = [_fit(to_grey(img1[sl]).float(), to_grey(img2[sl]).float(), None if init is None else init[sl], cfg)
             for sl in chunk_slices(bsz, cfg.chunk_size, img1.device, h * w)]
    k2, k4, H = (torch.cat([p[j] for p in parts]) for j in range(3))
    info = SelfCalInfo(*(torch.cat(f) for f in zip(*[p[3] for p in parts])))
    return k2, k4, H, info


def _starts(pyr1, pyr2, init, cfg: SelfCalConfig, h0: int, w0: int) -> torch.Tensor:
    """(S B, P) float64 starting parameters: [init start,] [phase-correlation start]."""
    bsz, dev = pyr1[0].shape[0], pyr1[0].device
    theta = torch.zeros(bsz, planar_parameters(_model.PHOTOMETRIC_MODEL), dtype=torch.float64, device=dev)
    c1, c2 = pyr1[-1].flatten(1), pyr2[-1].flatten(1)
    if _model.PHOTOMETRIC_MODEL == "gain_bias":  # robust std ratio and median difference of the coarsest level
        every = torch.ones_like(c1, dtype=torch.bool)
        g = (robust_scale(c1, every, NOISE_FLOOR) / robust_scale(c2, every, NOISE_FLOOR)).clamp(*GAIN_RANGE)
        theta[:, 10], theta[:, 11] = g, c1.median(1).values - g * c2.median(1).values
    out = []
    if init is not None:
        nrm = normalizer(h0, w0, device=dev)
        out.append(theta.clone())
        out[0][:, :8] = homography_parameters(nrm @ init @ torch.linalg.inv(nrm))
    if init is None or BOTH_STARTS:  # the translation in level px -> u
        t = phase_correlation(pyr1[-1][:, 0], pyr2[-1][:, 0]).double()
        theta[:, 2:6:3] = t * 2 ** (LEVELS - 1) / half_diagonal(h0, w0)
        out.append(theta)
    return torch.cat(out)


def _fit(g1, g2, init, cfg: SelfCalConfig):
    """One chunk: g1, g2 (b, 1, h, w) float32 grey on any device -> k2, k4, H, info."""
    bsz, _, h0, w0 = g1.shape
    pyr1, pyr2 = mean_pyramid(g1, LEVELS), mean_pyramid(g2, LEVELS)
    theta = _starts(pyr1, pyr2, init, cfg, h0, w0)
    n_starts = theta.shape[0] // bsz
    lam = torch.full((theta.shape[0],), DAMPING, dtype=torch.float64, device=g1.device)
    for lev, iters in zip(range(LEVELS - 1, -1, -1), ITERATIONS):
        lv = _level(pyr1, pyr2, lev, theta, n_starts, cfg, relief=False)
        theta, lam, state = solver.levenberg_marquardt(theta, lam, lv, iterations=iters, cfg=cfg,
                                                          free_ab=lev < DISTORTION_LEVELS)
        lam = lam.clamp_min(DAMPING)  # a fresh start of the damping at the next level
    theta, *planar = _result(theta, state, n_starts, init is not None, h0, w0, cfg, SAMPLE_BLOCK[-1])
    if cfg.parallax == 0:
        return planar
    # the plane + parallax model from the planar fit: one step on every pair (:func:`_relief_start`), the
    # fitted stage where the score test rejects a flat scene
    theta = torch.cat([theta, theta.new_zeros(bsz, cfg.parallax**2)], 1)
    first = {f: getattr(lv, f)[:bsz] for f in ("i1", "stack2", "ux_d", "uy_d", "rho")}  # the starts share samples
    score, relief = _relief_start(lv._replace(**first), theta, cfg, h0, w0)
    ask = planar[3].converged & (relief_p_value(score, cfg) <= PARALLAX_SCORE_LEVEL)
    rows = (ask | (not cfg.parallax_evidence)).nonzero()[:, 0]  # a fixed prior: every pair
    if len(rows):
        lam = torch.full((len(rows),), DAMPING, dtype=torch.float64, device=g1.device)
        lv = _level([p[rows] for p in pyr1], [p[rows] for p in pyr2], 0, theta[rows], 1, cfg, relief=True)
        theta, _, state = solver.levenberg_marquardt(theta[rows], lam, lv, iterations=PARALLAX_ITERATIONS, cfg=cfg)
        fitted = _result(theta, state, 1, False, h0, w0, cfg, PARALLAX_BLOCK)[1:]
        relief = (*(_on_rows(a, b, rows) for a, b in zip(fitted[:3], relief[:3])),
                  SelfCalInfo(*(_on_rows(a, b, rows) for a, b in zip(fitted[3], relief[3]))))
    return _kept(planar, relief, score, planar[3].converged | (not cfg.parallax_evidence))


def _on_rows(a, b, rows):
    """``b`` with ``a`` (one per index of ``rows``) on those rows."""
    out = b.clone()
    out[rows] = a
    return out


def _kept(planar, relief, score, answered):
    """Per pair the planar answer or the plane + parallax one (Hausman's test), with both in the info.

    ``planar``, ``relief``: (k2, k4, H, info) of the two models; ``answered`` (B,) bool: the pairs
    whose relief figures the info carries (NaN elsewhere).
    """
    p, r = planar[3], relief[3]
    # Hausman: under a planar scene the planar answer is the efficient one, var(d1 - d0) = s1^2 - s0^2
    floor = _HAUSMAN_FLOOR_PX**2
    z = (r.delta_avg - p.delta_avg).abs() / (r.delta_avg_std**2 - p.planar_std**2).clamp_min(floor).sqrt()
    use = r.converged & p.converged & (z >= PARALLAX_TEST)  # 0: on every pair

    def kept(a, b, m=use):  # a where m, else b
        return torch.where(m.view(-1, *(1,) * (a.dim() - 1)), a, b)

    nan = torch.full_like(score, float("nan"))
    info = SelfCalInfo(*map(kept, r, p))._replace(
        relief=use, relief_ab=kept(r.ab, p.relief_ab, answered), relief_z=kept(z, nan, answered),
        relief_std=kept(r.delta_avg_std, nan, answered), from_init=p.from_init, planar_ab=p.planar_ab,
        planar_std=p.planar_std, relief_score=score)
    return (*map(kept, relief[:3], planar[:3]), info)


def _relief_start(lv: Level, theta, cfg: SelfCalConfig, h0: int, w0: int):
    """The score test of the relief at the planar answer ``theta`` and one step of the plane + parallax model.

    On the planar fit's own samples (``lv``, its full-size level, one row per pair), the relief's
    columns appended at 0: the robust normal
    equations give :func:`~lensdist_torch.selfcal.prior.relief_score` and
    :func:`~lensdist_torch.selfcal.prior.relief_step`; the step's answer is read with the posterior
    at ``theta`` (the model linear about it). Returns the score (B,) and (k2, k4, H, info) of the step.
    """
    lv = lv._replace(basis=_bumps(lv.ux_d, lv.uy_d, cfg, h0, w0), direction=relief_direction(theta))
    res, valid, J = evaluate(theta, lv)
    loss = _model.ROBUST_LOSS
    sigma = robust_scale(res, valid, NOISE_FLOOR)
    w = robust_weights(res, sigma, loss, robust_constant(loss))
    w = valid.float() if w is None else w * valid
    jtj, jtr = solver.normal_equations(J, res, w)
    score = relief_score(jtj, jtr, solver.residual_variance(res, w, J.shape[1], cfg), cfg)
    stepped, tau2 = relief_step(theta, jtj, jtr, sigma, px=lv.px, cfg=cfg)
    untried = sigma.new_zeros(len(sigma), dtype=torch.float64)  # one step, taken unconditionally: no cost to compare
    state = solver.State(res=res, valid=valid, J=J, sigma=sigma, cost=untried, start_cost=untried, tau2=tau2, jtj=jtj)
    return score, _result(stepped, state, 1, False, h0, w0, cfg, SAMPLE_BLOCK[-1])[1:]


def _level(pyr1, pyr2, lev: int, theta, n_starts: int, cfg: SelfCalConfig, relief: bool) -> Level:
    """The fixed data of level ``lev`` (samples of img1, img2 and its gradients), repeated per start."""
    i1, h, w = pyr1[lev], *pyr1[lev].shape[-2:]
    h0, w0 = pyr1[0].shape[-2:]
    idx = select_samples(i1, PARALLAX_BLOCK if relief else SAMPLE_BLOCK[LEVELS - 1 - lev], MARGIN)
    ud = normalized_grid(lev, h, w, full_height=h0, full_width=w0, device=i1.device).view(-1, 2)
    ux_d, uy_d = ud[idx, 0], ud[idx, 1]
    lv = [torch.gather(i1.flatten(1), 1, idx), with_gradients(pyr2[lev]), ux_d, uy_d, ux_d * ux_d + uy_d * uy_d]
    i1s, stack2, ux_d, uy_d, rho = (x.repeat(n_starts, *(1,) * (x.dim() - 1)) if n_starts > 1 else x for x in lv)
    basis, direction = (_bumps(ux_d, uy_d, cfg, h0, w0), relief_direction(theta)) if relief else (None, None)
    return Level(i1=i1s, stack2=stack2, ux_d=ux_d, uy_d=uy_d, rho=rho, px=half_diagonal(h0, w0) / 2**lev,
                 to_grid=level_to_grid(lev, h, w, full_height=h0, full_width=w0), newton=NEWTON, margin=MARGIN,
                 photometric=_model.PHOTOMETRIC_MODEL, floor=NOISE_FLOOR, basis=basis, direction=direction,
                 interpolation=_RELIEF_INTERPOLATION if relief else SAMPLING)


def _bumps(ux_d, uy_d, cfg: SelfCalConfig, h0: int, w0: int):
    return relief_basis(ux_d, uy_d, n=cfg.parallax, width=PARALLAX_WIDTH, h0=h0, w0=w0)


def _delta_avg_std(
    ab, st: solver.State, h0: int, w0: int, cfg: SelfCalConfig, region: torch.Tensor | None
) -> torch.Tensor:
    """Std (px) of Delta_avg from the covariance of the final fit; inf where not finite.

    The weighted Gauss-Newton covariance, or (with the samples' ``region``, ``clusters`` > 1) the
    cluster-robust one where it is larger (:func:`~lensdist_torch.selfcal.regions.cluster_robust_covariance`).
    """
    w = robust_weights(st.res, st.sigma, _model.ROBUST_LOSS, robust_constant(_model.ROBUST_LOSS))
    w = st.valid.float() if w is None else w * st.valid
    jtj = solver.normal_equations(st.J, st.res, w)[0] if st.jtj is None else st.jtj
    s2 = solver.residual_variance(st.res, w, st.J.shape[1], cfg)
    inv = posterior_inverse(jtj, s2, st.tau2, cfg)  # with the relief: precision J W J^T / s^2 + I / tau^2
    cov = s2[:, None, None] * inv
    if region is not None:  # cluster-robust: the larger of the two
        score = (st.J * (w * st.res)[:, None]).double()  # (B, P, N)
        cov = torch.maximum(cov, cluster_robust_covariance(inv, score, region, CLUSTERS**2))
    # Delta_avg and its gradient in (a, b): R * mean |a u^3 + b u^5|, the mean over the centres
    # of 4 x 4 blocks (the gradient is smooth; 16 times fewer terms)
    grid = normalized_grid(2, h0 // 4, w0 // 4, full_height=h0, full_width=w0, dtype=torch.float64, device=ab.device)
    u2 = (grid.view(1, -1, 2) ** 2).sum(-1)
    m3, m5 = u2**1.5, u2**2.5
    sgn = torch.sign(ab[:, :1] * m3 + ab[:, 1:] * m5)
    sgn = torch.where(sgn == 0, torch.ones_like(sgn), sgn)  # the kink of |.| at 0: one side
    grad = half_diagonal(h0, w0) * torch.stack([(sgn * m3).mean(1), (sgn * m5).mean(1)], -1)
    std = torch.einsum("bi,bij,bj->b", grad, cov[:, 8:10, 8:10], grad).clamp_min(0).sqrt()
    return torch.where(torch.isfinite(std), std, torch.full_like(std, float("inf")))


def _choose(st: solver.State, ok: torch.Tensor, n_starts: int, cfg: SelfCalConfig) -> torch.Tensor:
    """(B,) row index of the kept start per pair: the lower robust cost at the smaller sigma."""
    bsz = ok.shape[0] // n_starts
    rows = torch.arange(bsz, device=ok.device)
    if n_starts == 1:
        return rows
    sigma = st.sigma.view(n_starts, bsz).amin(0).repeat(n_starts)
    cost = robust_cost(st.res, st.valid, sigma, loss=_model.ROBUST_LOSS, k=robust_constant(_model.ROBUST_LOSS))
    cost = torch.where(ok & torch.isfinite(cost), cost, torch.full_like(cost, float("inf"))).view(n_starts, bsz)
    return rows + bsz * cost.argmin(0)  # ties: the first start (init)


def _result(theta, st: solver.State, n_starts: int, has_init: bool, h0: int, w0: int, cfg: SelfCalConfig, block: int):
    """k2, k4, H and :class:`SelfCalInfo` of a chunk from its final fits; NaN where it diverged."""
    dev = theta.device
    overlap = st.valid.float().mean(1)
    ab = theta[:, 8:10]
    ok = (torch.isfinite(theta).all(1) & (ab.abs() <= MAX_COEFFICIENT).all(1) & (overlap >= MIN_OVERLAP)
          & plausible(theta, _model.PHOTOMETRIC_MODEL) & (st.cost <= st.start_cost * (1 + 1e-6)))
    keep = _choose(st, ok, n_starts, cfg)
    theta, ok, overlap, ab = theta[keep], ok[keep], overlap[keep], ab[keep].clone()
    st = solver.State(*(None if x is None else x[keep] for x in st))
    r0 = half_diagonal(h0, w0)
    # the frame's rectangles of the samples: the cluster-robust covariance and the aligned residual
    region = region_ids(h0, w0, block=block, clusters=CLUSTERS, device=dev) if CLUSTERS > 1 else None
    std = _delta_avg_std(ab, st, h0, w0, cfg, region)
    nan = torch.tensor(float("nan"), dtype=torch.float64, device=dev)
    k2, k4 = (torch.where(ok, k, nan) for k in from_normalized(ab, h0, w0))
    nrm = normalizer(h0, w0, device=dev)
    H = torch.linalg.inv(nrm) @ h_matrix(theta) @ nrm
    H = torch.where(ok[:, None, None], H / H[:, 2:, 2:], nan)
    d_avg = pixel_offsets(torch.nan_to_num(k2), torch.nan_to_num(k4), h0, w0, device=dev).flatten(1).mean(1)
    d_avg = torch.where(ok, d_avg, nan)
    # what the covariance leaves out: a registration error of the order of the interpolation's,
    # which the pair's motion m turns into a Delta error ~ 1 / m (the distortion cancels where the
    # views did not move); fitted on rendered validation pairs (docs/method.md, section 10)
    motion = mean_displacement(torch.where(ok[:, None, None], H, torch.eye(3, dtype=H.dtype, device=dev)), h0, w0)
    floor = SMALL_MOTION_ERROR * r0**2 / motion.clamp_min(1e-3)  # 1e-3 px: no motion, no information
    std = torch.where(ok, torch.sqrt(std**2 + floor**2), torch.full_like(std, float("inf")))
    conf = CANNOT_TELL_STD_PX / (CANNOT_TELL_STD_PX + std)
    unit = torch.tensor([1.0, 0.0], device=dev).expand(len(theta), 2)  # gain 1, bias 0
    gb = theta[:, 10:12] if _model.PHOTOMETRIC_MODEL == "gain_bias" else unit
    rms = aligned_residual(st.res, st.valid)
    n_regions = CLUSTERS**2
    aligned = aligned_residual(st.res, st.valid, region, n_regions=n_regions, drop=int(OCCLUDED_SHARE * n_regions))
    from_init = (keep < len(keep)) & has_init  # rows [init start, phase-correlation start]
    info = SelfCalInfo(
        converged=ok, confident=ok & (conf >= CONFIDENCE_THRESHOLD), confidence=conf, delta_avg=d_avg,
        delta_avg_std=std, residual=rms, overlap=overlap, ab=ab, gain_bias=gb.double(), scale=st.sigma.double(),
        from_init=from_init, relief=torch.zeros_like(ok), motion=torch.where(ok, motion, nan), planar_ab=ab,
        relief_ab=torch.full_like(ab, float("nan")), relief_z=torch.full_like(d_avg, float("nan")), planar_std=std,
        relief_std=torch.full_like(std, float("nan")), aligned_residual=aligned,
        relief_score=torch.full_like(std, float("nan")))
    return theta, k2, k4, H, info
