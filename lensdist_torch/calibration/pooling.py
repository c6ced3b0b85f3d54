"""Pooling many noisy estimates of one quantity, some of them failures (a sequence's pairs).

The pairs of a sequence each estimate the camera's one Delta_avg with a std sigma_i. On rendered
frames they agree within those stds; on real footage some pairs fail (a registration held in a
wrong minimum, a view the model cannot follow) and report a value anywhere, often with a small
sigma_i, and the pairs that work scatter beyond their sigma_i (what the per-pair model leaves
out). An inverse-variance mean then follows the tightest failure, and its chi-square, far above
its degrees of freedom, widens the interval until it says nothing. The model here (the
"good-and-bad data" model of Sivia and Skilling, *Data Analysis*, section 8.3; a mixture as in
Hogg, Bovy and Lang, *Data analysis recipes: fitting a model to data*, 2010, section 5) says
what the pairs are:

    d_i ~ pi N(mu, (kappa sigma_i)^2) + (1 - pi) U(width),   kappa >= 1,

a share pi of good pairs around mu whose stds are too small by a common factor kappa (Birge's
ratio: the tight pairs keep their weight relative to the loose ones), and failures spread evenly
over ``width``. A scatter added to every std instead (random effects, sigma_i^2 + tau^2) was
tried first and rejected: it gives a pair that cannot tell (0 +- 3 px, the typical failure of a
pair whose views do not constrain the lens) the weight of a tight one, and where such pairs are
many a single broad component around their midpoint wins the likelihood (docs/method.md,
section 10). :func:`good_and_bad` maximises the likelihood over (mu, kappa, pi): a grid for the
global maximum (the failures may outnumber the good pairs, so the median is no safe start), then
EM from it. Each pair's posterior probability of being good, p_i, and its weight
p_i / (kappa sigma_i)^2 come back; with every pair good and kappa = 1 the weights are the
inverse variances, so sequences whose pairs agree combine exactly as by inverse variance.

Example:
    >>> import torch
    >>> d = torch.tensor([6.1, 6.3, 5.9, 6.2, 0.0, 14.8, -3.0], dtype=torch.float64)  # three failures
    >>> s = torch.tensor([0.2, 0.3, 0.2, 0.25, 0.08, 1.0, 0.5], dtype=torch.float64)
    >>> fit = good_and_bad(d, s, width=57.6)  # the good four agree: their inverse-variance mean, 6.08
    >>> round(fit.mean, 2), [round(p) for p in fit.p_good.tolist()]
    (6.08, [1, 1, 1, 1, 0, 0, 0])
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from lensdist_torch.config import CalibrationConfig

__all__ = [
    "jackknife_std",
    "GoodBadFit",
    "good_and_bad",
    "pair_weights",
    "pool_pairs",
    "t_quantile",
    "within_mads",
    "JACKKNIFE_BLOCKS",
    "OUTLIER_MADS",
    "OUTLIER_RANGE",
    "jackknife_interval",
]

_SHARES = (0.2, 0.35, 0.5, 0.65, 0.8, 0.95)  # the grid's good shares pi
_KAPPAS = 64  # the grid's std scales, geometric from 1 to the values' spread over their smallest std
_MEANS = 801  # the grid's means over [min, max] of the values
_EM_STEPS = 200


class GoodBadFit(NamedTuple):
    """What :func:`good_and_bad` returns.

    Attributes:
        mean: mu, the good pairs' common value.
        kappa: the factor (>= 1) by which the good pairs' stds are too small (1 when they agree within them).
        good_share: pi, the share of good pairs.
        p_good: (n,) float64, each value's posterior probability of being good.
        weights: (n,) float64, p_i / (kappa sigma_i)^2: mean = sum w d / sum w.

    Example:
        >>> fit = good_and_bad(torch.tensor([1.0, 1.0, 9.0]), torch.tensor([0.1, 0.1, 0.1]), width=20.0)
        >>> fit.mean, fit.kappa, round(fit.good_share, 2), fit.p_good.round().tolist()
        (1.0, 1.0, 0.66, [1.0, 1.0, 0.0])
    """

    mean: float
    kappa: float
    good_share: float
    p_good: torch.Tensor
    weights: torch.Tensor


def _log_good(d, s2, mu, k2):
    v = s2 * k2
    return -0.5 * (d - mu) ** 2 / v - 0.5 * torch.log(2 * math.pi * v)


def _posterior(d, s2, mu, k2, pi, log_bad):
    good = math.log(pi) + _log_good(d, s2, mu, k2)
    bad = torch.full_like(good, math.log1p(-pi) + log_bad)
    return torch.exp(good - torch.logaddexp(good, bad))


def good_and_bad(values: torch.Tensor, std: torch.Tensor, width: float) -> GoodBadFit:
    """Maximum-likelihood good-and-bad mixture of estimates ``values`` with stds ``std`` (module docstring).

    Args:
        values: (n,) finite estimates, n >= 1.
        std: (n,) their finite stds, > 0.
        width: the span over which a failed estimate may fall (its density is 1 / width), > 0.

    Returns:
        :class:`GoodBadFit`.

    Raises:
        ValueError: values and std of different shapes, empty, not finite, std <= 0 or width <= 0.

    Example:
        >>> d = torch.tensor([3.0, 3.4, 2.6, 3.2, 2.8, 0.0], dtype=torch.float64)  # five agree, one failed
        >>> fit = good_and_bad(d, torch.full((6,), 0.1, dtype=torch.float64), width=50.0)
        >>> round(fit.mean, 3), round(fit.kappa, 2), fit.p_good[-1].item() < 1e-6  # ML: kappa^2 = 0.08 / 0.1^2
        (3.0, 2.83, True)
    """
    d, s = (
        torch.as_tensor(values, dtype=torch.float64).reshape(-1),
        torch.as_tensor(std, dtype=torch.float64).reshape(-1),
    )
    if d.shape != s.shape or d.numel() == 0:
        raise ValueError(
            f"values and std must be two (n,) tensors with n >= 1, got {tuple(d.shape)} and {tuple(s.shape)}"
        )
    if not (bool(torch.isfinite(d).all()) and bool(torch.isfinite(s).all()) and bool((s > 0).all())):
        raise ValueError("values must be finite and std finite and > 0")
    if not (isinstance(width, (int, float)) and math.isfinite(width) and width > 0):
        raise ValueError(f"width must be a finite number > 0, got {width!r}")
    s2, log_bad = s * s, -math.log(width)
    lo, hi = float(d.min()), float(d.max())
    mus = torch.linspace(lo, hi, _MEANS, dtype=torch.float64) if hi > lo else d[:1]
    top = max(2.0, (hi - lo) / float(s.min()))
    k2s = torch.logspace(0.0, math.log10(top), _KAPPAS, dtype=torch.float64) ** 2
    best = (-math.inf, lo, 1.0, _SHARES[-1])
    for pi in _SHARES:  # the global maximum on the grid: (kappa, mu) at once for each share
        good = math.log(pi) + _log_good(d, s2, mus[None, :, None], k2s[:, None, None])  # (K, M, n)
        ll = torch.logaddexp(good, torch.tensor(math.log1p(-pi) + log_bad, dtype=torch.float64)).sum(-1)
        k = int(ll.argmax())
        if float(ll.flatten()[k]) > best[0]:
            best = (float(ll.flatten()[k]), float(mus[k % mus.numel()]), float(k2s[k // mus.numel()]), pi)
    _, mu, k2, pi = best
    for _ in range(_EM_STEPS):  # EM from the grid's maximum
        p = _posterior(d, s2, mu, k2, pi, log_bad)
        w = p / s2
        mu_new = float((w * d).sum() / w.sum())
        k2_new = max(1.0, float((w * (d - mu_new) ** 2).sum() / p.sum()))  # the stds are too small, never too large
        pi_new = min(max(float(p.mean()), 1e-3), 1 - 1e-9)
        done = abs(mu_new - mu) <= 1e-12 * (1 + abs(mu)) and abs(k2_new - k2) <= 1e-12 * k2
        mu, k2, pi = mu_new, k2_new, pi_new
        if done:
            break
    p = _posterior(d, s2, mu, k2, pi, log_bad)
    return GoodBadFit(mean=mu, kappa=math.sqrt(k2), good_share=pi, p_good=p, weights=p / (s2 * k2))


# ------------------------------------------------------------------ a sequence's pairs
def t_quantile(p: float, dof: int) -> float:
    """Student's t quantile: Newton on the CDF (Simpson's rule on the density) from the normal's."""
    c = math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2)) / math.sqrt(dof * math.pi)

    def density(x):
        return c * (1 + x * x / dof) ** (-(dof + 1) / 2)

    t = float(torch.special.ndtri(torch.tensor(p, dtype=torch.float64)))
    for _ in range(100):  # the CDF is concave above 0: Newton from below climbs monotonically
        x = torch.linspace(0, t, 401, dtype=torch.float64)
        f = density(x)
        cdf = 0.5 + float(f[0] + 4 * f[1:-1:2].sum() + 2 * f[2:-1:2].sum() + f[-1]) * t / 1200
        t += (p - cdf) / density(t)
        if abs(p - cdf) < 1e-10:
            break
    return t


def jackknife_std(replicates) -> float:
    """The delete-a-block jackknife's std of B ``replicates``: sqrt((B - 1) / B sum (x_b - mean)^2).

    NaN where a replicate is not finite (a fold whose fit has no Delta): no jackknife to check against.

    Example:
        >>> jackknife_std([9.0, 11.0]), jackknife_std([1.0, float("nan")])
        (1.0, nan)
    """
    x = torch.as_tensor(replicates, dtype=torch.float64)
    b = len(x)
    return math.sqrt((b - 1) / b * float(((x - x.mean()) ** 2).sum()))


def jackknife_interval(value: float, replicates: list[float], extra: float, confidence: float) -> tuple[float, float]:
    """The delete-a-block jackknife interval of a Delta (>= 0), an ``extra`` spread added in quadrature.

    Half-width t sqrt((B - 1) / B sum (x_b - mean)^2 + extra^2), t Student's on B - 1 degrees of
    freedom for B ``replicates``; the lower end clipped at 0.

    Example:
        >>> [round(v, 3) for v in jackknife_interval(10.0, [9.0, 11.0], 0.0, 0.95)]  # sqrt(1/2 * 2) = 1, t(1) = 12.706
        [0.0, 22.706]
    """
    half = t_quantile(0.5 + confidence / 2, len(replicates) - 1) * math.hypot(jackknife_std(replicates), extra)
    return max(0.0, value - half), value + half


#: Step 4's first cut: a pair beyond this many robust deviations (1.4826 MAD, at least the median sigma) of the
#: pairs' median signed Delta_avg does not count (docs/method.md, section 10).
OUTLIER_MADS = 4.0
#: A failed pair's signed Delta_avg falls anywhere within +- this many times the classes' range (``delta_top``),
#: evenly: the bad half of the good-and-bad mixture that decides which pairs count (docs/method.md, section 10).
OUTLIER_RANGE = 2.0
#: Step 5's jackknife: the pooled answer is computed again without each of this many contiguous blocks of pairs.
JACKKNIFE_BLOCKS = 8


def within_mads(lin, std) -> torch.Tensor:
    """(P,) bool: finite, and within :data:`OUTLIER_MADS` robust deviations of the median.

    A robust deviation: 1.4826 MAD, at least the median sigma.
    """
    ok = torch.isfinite(lin) & torch.isfinite(std) & (std > 0)
    if not bool(ok.any()):
        return ok
    med = lin[ok].median()
    spread = torch.maximum(1.4826 * (lin[ok] - med).abs().median(), std[ok].median())
    return ok & ((lin - med).abs() <= OUTLIER_MADS * spread)


def pair_weights(lin, std, width: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 4: each pair's weight (P,) and whether it counts (P,) bool, from its signed Delta_avg ``lin``.

    Pairs beyond :data:`OUTLIER_MADS` robust deviations go first; the good-and-bad mixture
    (:func:`good_and_bad`, failures spread over ``width``), fitted to the sharper half of the rest
    (stds at most their median: a pair that cannot tell by itself, 0 +- 4 px stuck at its start,
    does not choose which pairs are good), then keeps every pair more likely good than failed under
    it, each weighted 1 / sigma_i^2 (their scatter beyond the stds, the mixture's kappa, is what
    :func:`pool_pairs`' Birge factor and jackknife take in).
    """
    keep = within_mads(lin, std)
    if not bool(keep.any()):
        return torch.zeros_like(std), keep
    idx = keep.nonzero()[:, 0]
    sharp = std[idx] <= std[idx].median()  # a pair that cannot tell by itself does not choose the good ones
    fit = good_and_bad(lin[idx][sharp], std[idx][sharp], width)
    p = _posterior(lin[idx], std[idx] ** 2, fit.mean, fit.kappa**2, fit.good_share, -math.log(width))
    keep[idx[p <= 0.5]] = False
    return torch.where(keep, 1.0 / std.clamp_min(1e-12) ** 2, torch.zeros_like(std)), keep


def pool_pairs(ab, w, keep, first, *, fun, cfg: CalibrationConfig):
    """Step 5: the weighted mean (a, b) (2,), the sd (K,) of the functionals ``fun`` (K, 2) and t.

    Row 0 of ``fun`` is the analysis frame's signed Delta_avg; NaN sd below 2 kept pairs.
    """
    nan = torch.full((fun.shape[0],), float("nan"), dtype=torch.float64)
    n = int(keep.sum())
    if n == 0:
        return torch.full((2,), float("nan"), dtype=torch.float64), nan, float("nan")
    theta = (w[:, None] * torch.nan_to_num(ab)).sum(0) / w.sum()
    if n < 2:
        return theta, nan, float("nan")
    blocks = min(JACKKNIFE_BLOCKS, n)
    idx = keep.nonzero()[:, 0]
    rank = torch.empty(n, dtype=torch.int64)
    rank[torch.argsort(first[idx], stable=True)] = torch.arange(n)
    block = rank * blocks // n
    loo = []
    for g in range(blocks):
        wg = w.clone()
        wg[idx[block == g]] = 0
        loo.append((wg[:, None] * torch.nan_to_num(ab)).sum(0) / wg.sum())
    vals = torch.stack(loo) @ fun.T  # (G, K)
    var_jk = (blocks - 1) / blocks * ((vals - vals.mean(0)) ** 2).sum(0)
    lin = torch.nan_to_num(ab) @ fun[0]
    birge = max(1.0, float((w * (lin - theta @ fun[0]) ** 2).sum()) / (n - 1))
    var_b = birge / float(w.sum())
    if float(var_jk[0]) > 0:
        var = var_jk * max(1.0, var_b / float(var_jk[0]))
    else:  # identical estimates: the pairs' own sigma, carried over by the functionals' sizes
        var = var_b * (fun.norm(dim=1) / fun[0].norm()) ** 2
    return theta, var.sqrt(), t_quantile(0.5 + cfg.confidence / 2, blocks - 1)
