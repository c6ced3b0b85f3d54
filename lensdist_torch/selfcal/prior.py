"""The Gaussian prior on the relief of the self-calibration's plane + parallax model.

Each bump's height c_k has the prior N(0, tau^2) (normalised units). In the robust normal
equations J W J^T, which carry no 1 / sigma^2, it adds sigma^2 / tau^2 to the relief's diagonal
(:func:`relief_precision`, added by :func:`add_relief_prior`), the same in the posterior
covariance (:func:`posterior_inverse`). tau is ``selfcal.parallax_px``
over the level's pixels per unit, or, with ``selfcal.parallax_evidence``, re-estimated per pair
from the evidence after every Levenberg-Marquardt step (:func:`evidence_tau2`, MacKay's update
:func:`evidence_variance`): a flat pair drives it down to the floor of :data:`PARALLAX_PX_RANGE`, a
relief the data pin up (docs/method.md, section 10). Whether a pair's evidence asks for the relief
at all: :func:`relief_score`, Rao's score test of the relief at zero.
"""

from __future__ import annotations

import torch

from lensdist_torch.config import SelfCalConfig
from lensdist_torch.selfcal import model as selfcal_model
from lensdist_torch.selfcal.model import planar_parameters

__all__ = [
    "PARALLAX_PX_RANGE",
    "RIDGE",
    "evidence_variance",
    "relief_precision",
    "add_relief_prior",
    "posterior_inverse",
    "start_tau2",
    "evidence_tau2",
    "relief_score",
    "relief_p_value",
    "relief_step",
    "EVIDENCE_STEPS",
]

#: Absolute ridge on J W J^T in the posterior covariance and the score test (docs/method.md, section 10).
RIDGE = 1e-6
#: (low, high) px: the range the evidence may move the relief prior's std in (``selfcal.parallax_evidence``;
#: docs/method.md, section 10).
PARALLAX_PX_RANGE = (0.02, 2.0)
#: Evidence updates of the prior's variance in :func:`relief_step` (the model linear about the planar answer).
EVIDENCE_STEPS = 8


def evidence_variance(coef: torch.Tensor, posterior_trace: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
    """MacKay's re-estimate of a Gaussian prior's variance from the evidence (type-II ML).

    For coefficients ``coef`` (B, K) at the posterior mode under the prior N(0, ``variance`` I)
    (B,), whose posterior covariance has trace ``posterior_trace`` (B,): gamma = K - trace /
    variance coefficients are pinned by the data, and the new variance is |coef|^2 / gamma
    (gamma floored at 0.5). Its fixed point maximises the marginal likelihood of a linear model.

    Example:
        >>> c = torch.tensor([[0.3, -0.4]])
        >>> evidence_variance(c, torch.tensor([0.5]), torch.tensor([1.0]))  # gamma = 1.5
        tensor([0.1667])
    """
    gamma = coef.shape[-1] - posterior_trace / variance
    return (coef * coef).sum(-1) / gamma.clamp_min(0.5)


def relief_precision(variance: torch.Tensor, tau2: torch.Tensor, cfg: SelfCalConfig):
    """(precision (B,) float64, columns of theta) of the relief coefficients' Gaussian prior.

    ``tau2`` (B,): the prior's variance per coefficient in normalised units; in the units of the
    normal equations the precision is the residual ``variance`` over it. MAP, not a hard
    constraint.

    Example:
        >>> cfg = SelfCalConfig(parallax=2)
        >>> relief_precision(torch.tensor([4.0]), torch.tensor([0.5]), cfg)
        (tensor([8.]), slice(12, 16, None))
    """
    start = planar_parameters(selfcal_model.PHOTOMETRIC_MODEL)
    return variance / tau2, slice(start, start + cfg.parallax**2)


def add_relief_prior(jtj: torch.Tensor, variance: torch.Tensor, tau2: torch.Tensor, cfg: SelfCalConfig):
    """Add the prior's precision (:func:`relief_precision`) to the relief's diagonal of ``jtj`` (B, P, P), in place.

    Returns:
        (precision (B,), columns of theta), for the right-hand side's term.
    """
    prec, rel = relief_precision(variance, tau2, cfg)
    torch.diagonal(jtj, dim1=1, dim2=2)[:, rel] += prec[:, None]
    return prec, rel


def posterior_inverse(
    jtj: torch.Tensor, variance: torch.Tensor, tau2: torch.Tensor | None, cfg: SelfCalConfig
) -> torch.Tensor:
    """(B, P, P) float64 (J W J^T + the relief prior + :data:`RIDGE` I)^-1: the posterior covariance over ``variance``.

    ``jtj`` (B, P, P) the robust normal matrix without the prior (not changed); ``tau2`` (B,) the
    prior's variance, or None without the relief (no prior term).

    Example:
        >>> cfg = SelfCalConfig(parallax=1)  # 12 planar parameters (gain and bias among them), 1 bump
        >>> a = torch.eye(13, dtype=torch.float64)[None]
        >>> inv = posterior_inverse(a, torch.tensor([1.0]), torch.tensor([0.5]), cfg)
        >>> round(float(inv[0, 12, 12]), 5), round(float(inv[0, 0, 0]), 5)  # 1 / (1 + 1 / 0.5) on the bump
        (0.33333, 1.0)
    """
    post = jtj.clone()
    if tau2 is not None:
        add_relief_prior(post, variance, tau2, cfg)
    eye = torch.eye(post.shape[1], dtype=torch.float64, device=post.device)
    return torch.linalg.inv(post + RIDGE * eye)


def _normalised(px_std: float, px: float) -> float:
    """A prior std in pixels as a variance in normalised units (``px`` the level's pixels per unit)."""
    return (px_std / px) ** 2


def start_tau2(n: int, px: float, cfg: SelfCalConfig, device=None) -> torch.Tensor:
    """(n,) float64 the relief prior's variance a fit starts from: ``parallax_px`` at ``px`` pixels per unit.

    Example:
        >>> start_tau2(2, 100.0, SelfCalConfig(parallax_px=0.5))  # (0.5 / 100)^2
        tensor([2.5000e-05, 2.5000e-05], dtype=torch.float64)
    """
    return torch.full((n,), _normalised(cfg.parallax_px, px), dtype=torch.float64, device=device)


def evidence_tau2(theta, jtj, sigma, tau2, *, px: float, cfg: SelfCalConfig,
                  inverse: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) the relief prior's variance re-estimated per pair at ``theta`` (B, P).

    ``jtj`` (B, P, P): the fit's robust normal matrix J W J^T there, without the prior (left as
    it is); ``sigma`` (B,) the residual scale, ``tau2`` (B,) the current variance, ``px`` the
    level's pixels per unit; ``inverse``: :func:`posterior_inverse` of these where the caller has
    formed it already. The posterior's trace over the relief gives :func:`evidence_variance`, kept
    within :data:`PARALLAX_PX_RANGE` (px); a row whose update is not finite keeps its variance.
    """
    variance = sigma.double() ** 2
    rel = relief_precision(variance, tau2, cfg)[1]
    inverse = posterior_inverse(jtj, variance, tau2, cfg) if inverse is None else inverse
    trace = variance * torch.diagonal(inverse, dim1=1, dim2=2)[:, rel].sum(1)
    new = evidence_variance(theta[:, rel].double(), trace, tau2)
    lo, hi = (_normalised(v, px) for v in PARALLAX_PX_RANGE)
    return torch.where(torch.isfinite(new), new.clamp(lo, hi), tau2)


def relief_score(jtj: torch.Tensor, jtr: torch.Tensor, variance: torch.Tensor, cfg: SelfCalConfig) -> torch.Tensor:
    """(B,) Rao's score statistic of the relief coefficients at zero, from the planar answer.

    ``jtj`` (B, P, P) and ``jtr`` (B, P): the robust normal equations J W J^T and J W r of the
    planar model with the relief's columns appended (the relief at 0), ``variance`` (B,) the
    weighted residual variance. The relief's efficient score over its information, (g^T A^-1 g
    - g_p^T A_pp^-1 g_p) / s^2 (the planar parameters' own gradient, near 0 at the planar answer,
    projected out), is chi-square with ``parallax**2`` degrees of freedom under a flat scene:
    no prior, no refit.

    Example:
        >>> cfg = SelfCalConfig(parallax=1)  # 12 planar parameters (gain and bias among them), 1 bump
        >>> jtj, jtr = torch.eye(13, dtype=torch.float64)[None], torch.zeros(1, 13, dtype=torch.float64)
        >>> jtr[0, 12] = 3.0  # the bump's gradient, 3 s.d. of its information
        >>> round(float(relief_score(jtj, jtr, torch.tensor([1.0], dtype=torch.float64), cfg)), 4)
        9.0
    """
    p = planar_parameters(selfcal_model.PHOTOMETRIC_MODEL)
    eye = torch.eye(jtj.shape[1], dtype=torch.float64, device=jtj.device)

    def quadratic(a, g):  # g^T (a + ridge)^-1 g
        return (g * torch.linalg.solve(a + RIDGE * eye[: a.shape[1], : a.shape[1]], g)).sum(1)

    return (quadratic(jtj, jtr) - quadratic(jtj[:, :p, :p], jtr[:, :p])) / variance


def relief_p_value(score: torch.Tensor, cfg: SelfCalConfig) -> torch.Tensor:
    """(B,) the p-value of :func:`relief_score` under a flat scene (chi-square, ``parallax**2`` dof); NaN stays NaN.

    Example:
        >>> round(float(relief_p_value(torch.tensor([44.314]), SelfCalConfig(parallax=5))), 4)  # chi2(25)'s 99 % point
        0.01
    """
    k = torch.tensor(cfg.parallax**2 / 2, dtype=torch.float64, device=score.device)
    return torch.special.gammaincc(k, score.double().clamp_min(0) / 2)


def relief_step(theta, jtj, jtr, sigma, *, px: float, cfg: SelfCalConfig):
    """One Gauss-Newton step of the plane + parallax model from the planar answer, under the relief's prior.

    ``theta`` (B, P): the planar answer with the relief's columns at 0; ``jtj`` (B, P, P), ``jtr``
    (B, P): the robust normal equations there (:func:`relief_score`'s); ``sigma`` (B,) the residual
    scale, ``px`` the level's pixels per unit. The model is taken as linear about ``theta`` (the
    score test found no relief, so the answer stays near it): the step solves the normal equations
    with the prior, whose variance starts at ``parallax_px`` and, with ``parallax_evidence``, is
    re-estimated from the evidence :data:`EVIDENCE_STEPS` times on the same equations
    (:func:`evidence_tau2`). Returns the stepped theta (B, P) and the prior's variance tau2 (B,),
    what the fitted stage's posterior reads.

    Example:
        >>> cfg = SelfCalConfig(parallax=1, parallax_evidence=False, parallax_px=2.0**0.5)  # tau2 0.5 at px 2
        >>> jtj, jtr = torch.eye(13, dtype=torch.float64)[None], torch.zeros(1, 13, dtype=torch.float64)
        >>> jtr[0, 12] = -3.0  # the bump's gradient; its prior precision 1 / 0.5: the step 3 / (1 + 2)
        >>> theta, tau2 = relief_step(torch.zeros(1, 13, dtype=torch.float64), jtj, jtr, torch.ones(1), px=2.0, cfg=cfg)
        >>> round(float(theta[0, 12]), 6), round(float(tau2[0]), 6)
        (1.0, 0.5)
    """
    variance = sigma.double() ** 2
    tau2 = start_tau2(len(theta), px, cfg, theta.device)
    for _ in range(EVIDENCE_STEPS if cfg.parallax_evidence else 1):
        inverse = posterior_inverse(jtj, variance, tau2, cfg)  # one inverse for the step and the evidence
        out = theta - (inverse @ jtr.unsqueeze(-1)).squeeze(-1)
        if cfg.parallax_evidence:
            tau2 = evidence_tau2(out, jtj, sigma, tau2, px=px, cfg=cfg, inverse=inverse)
    return out, tau2
