"""The robust Levenberg-Marquardt of the self-calibration's model: its steps, cost and normal equations.

What :mod:`~lensdist_torch.selfcal.fit` runs on each pyramid level and on the plane + parallax
stage (docs/method.md, section 10): IRLS steps on the photometric residual of
:func:`~lensdist_torch.selfcal.model.evaluate`, Tukey's (or Huber's) weights at a scale
re-estimated every step, the relief's Gaussian prior (:mod:`~lensdist_torch.selfcal.prior`) in the
normal equations and the cost where the model has a relief.

References:
    K. Levenberg, "A method for the solution of certain non-linear problems in least squares",
    Quarterly of Applied Mathematics 2(2), 1944; D. W. Marquardt, "An algorithm for least-squares
    estimation of nonlinear parameters", SIAM J. Applied Mathematics 11(2), 1963.
    P. W. Holland, R. E. Welsch, "Robust regression using iteratively reweighted least-squares",
    Communications in Statistics 6(9), 1977.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from lensdist_torch.config import SelfCalConfig
from lensdist_torch.selfcal import model as _model  # ROBUST_LOSS, PHOTOMETRIC_MODEL read at call time
from lensdist_torch.selfcal.model import (
    NOISE_FLOOR,
    Level,
    evaluate,
    plausible,
    robust_constant,
    robust_cost,
    robust_scale,
    robust_weights,
)
from lensdist_torch.selfcal.prior import add_relief_prior, evidence_tau2, relief_precision, start_tau2

__all__ = ["State", "normal_equations", "levenberg_marquardt", "objective", "residual_variance"]


class State(NamedTuple):
    """The final full-resolution fit of each row.

    Residual, mask, Jacobian, sigma, cost, start cost, the relief prior's variance tau^2
    (normalised units; None without the relief), and the robust normal matrix J W J^T at theta
    where it is already known (else None: computed from the rest).
    """

    res: torch.Tensor
    valid: torch.Tensor
    J: torch.Tensor
    sigma: torch.Tensor
    cost: torch.Tensor
    start_cost: torch.Tensor
    tau2: torch.Tensor | None = None
    jtj: torch.Tensor | None = None


def normal_equations(J, res, weights):
    """J W J^T (B, P, P) and J W r (B, P), float64 (W = I when weights is None)."""
    Jw = J if weights is None else J * weights[:, None]
    return torch.bmm(Jw, J.transpose(1, 2)).double(), (Jw * res[:, None]).sum(-1, dtype=torch.float64)


def levenberg_marquardt(theta, lam, lv: Level, *, iterations: int, cfg: SelfCalConfig, free_ab: bool = True):
    """``iterations`` robust Levenberg-Marquardt (IRLS) steps on one level.

    A pair's step is accepted where the robust cost at the current sigma falls, the model stays
    plausible and some overlap remains; sigma is then re-estimated, and with the relief the
    prior's variance where it is estimated per pair (:func:`~lensdist_torch.selfcal.prior.evidence_tau2`).
    Returns theta, lambda and the :class:`State` at theta.
    """
    loss, k = _model.ROBUST_LOSS, robust_constant(_model.ROBUST_LOSS)
    res, valid, J = evaluate(theta, lv)
    sigma = robust_scale(res, valid, NOISE_FLOOR)
    tau2 = None if lv.basis is None else start_tau2(len(theta), lv.px, cfg, theta.device)
    cost = objective(theta, res, valid, sigma, cfg=cfg, tau2=tau2)
    theta0, res0, valid0 = theta, res, valid
    normal = None  # the evidence's normal equations at theta, reused by the next step
    for _ in range(iterations):
        jtj, jtr = normal_equations(J, res, robust_weights(res, sigma, loss, k)) if normal is None else normal
        if not free_ab:  # (a, b) held: their rows and columns out of the system (step 0)
            jtj[:, 8:10], jtj[:, :, 8:10], jtr[:, 8:10] = 0, 0, 0
        if tau2 is not None:  # the relief's Gaussian prior
            prec, rel = add_relief_prior(jtj, sigma.double() ** 2, tau2, cfg)
            jtr[:, rel] += prec[:, None] * theta[:, rel]
        diag = torch.diagonal(jtj, dim1=1, dim2=2).clamp_min(1e-9)
        A = jtj + torch.diag_embed(lam[:, None] * diag + 1e-9 * diag.amax(1, keepdim=True))
        step = -torch.linalg.solve(A, jtr)
        cand = theta + torch.nan_to_num(step, nan=0.0)
        res_c, valid_c, J_c = evaluate(cand, lv)
        cost_c = objective(cand, res_c, valid_c, sigma, cfg=cfg, tau2=tau2)
        acc = (cost_c < cost) & torch.isfinite(cost_c) & plausible(cand, _model.PHOTOMETRIC_MODEL)
        acc &= valid_c.float().mean(1) > 0.05
        m = acc[:, None]
        theta = torch.where(m, cand, theta)
        res, valid = torch.where(m, res_c, res), torch.where(m, valid_c, valid)
        J = torch.where(m[..., None], J_c, J)
        lam = torch.where(acc, lam / 3, lam * 4).clamp(1e-7, 1e7)
        if loss != "none":  # sigma re-estimated
            sigma = torch.where(acc, robust_scale(res, valid, NOISE_FLOOR), sigma)
        if tau2 is not None and cfg.parallax_evidence:  # and the relief prior's variance
            normal = normal_equations(J, res, robust_weights(res, sigma, loss, k))
            tau2 = evidence_tau2(theta, normal[0], sigma, tau2, px=lv.px, cfg=cfg)
        cost = objective(theta, res, valid, sigma, cfg=cfg, tau2=tau2)  # the cost moves with them
    start_cost = objective(theta0, res0, valid0, sigma, cfg=cfg, tau2=tau2)
    return theta, lam, State(res=res, valid=valid, J=J, sigma=sigma, cost=cost, start_cost=start_cost, tau2=tau2)


def objective(theta, res, valid, sigma, *, cfg: SelfCalConfig, tau2: torch.Tensor | None = None):
    """The robust cost, plus the relief prior's term (on the same per-sample scale) where fitted."""
    cost = robust_cost(res, valid, sigma, loss=_model.ROBUST_LOSS, k=robust_constant(_model.ROBUST_LOSS))
    if tau2 is None:
        return cost
    prec, rel = relief_precision(sigma.double() ** 2, tau2, cfg)
    return cost + prec * (theta[:, rel].double() ** 2).sum(1) / valid.sum(1).clamp_min(1).double()


def residual_variance(res, w, n_par: int, cfg: SelfCalConfig) -> torch.Tensor:
    """(B,) the weighted residual variance, floored at 8-bit quantisation: no certainty without texture."""
    s2 = (w.double() * res.double() ** 2).sum(1) / (w.double().sum(1) - n_par).clamp_min(1)
    return s2.clamp_min(NOISE_FLOOR**2)
