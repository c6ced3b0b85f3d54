"""The confidence of an answer, mapped to P(class right), and how well it is calibrated.

The self-calibration and the regression give a raw confidence c = s0 / (s0 + std)
(docs/method.md, section 10). The reported confidence is its Platt map sigmoid(scale logit(c)
+ shift) (:func:`platt`), fitted on a validation split (:func:`fit_platt`, by
:func:`~lensdist_torch.workflows.decision_fit.fit_confidence`); :func:`reliability` and
:func:`expected_calibration_error` measure it on the test split.

Example:
    >>> c = torch.tensor([0.5, 0.9])
    >>> [round(float(v), 3) for v in platt(c, 1.0, 0.0)]  # the identity map
    [0.5, 0.9]
    >>> round(expected_calibration_error(torch.tensor([0.9, 0.9]), torch.tensor([True, False])), 3)
    0.4
"""

from __future__ import annotations

import math

import torch

__all__ = ["platt", "fit_platt", "reliability", "expected_calibration_error", "precision_bound"]

# ------------------------------------------------------------------ confidence
def _logit(c: torch.Tensor) -> torch.Tensor:
    c = c.double().clamp(1e-9, 1 - 1e-9)
    return torch.log(c) - torch.log1p(-c)


def platt(confidence, scale: float, shift: float) -> torch.Tensor:
    """sigmoid(scale * logit(c) + shift) of raw confidences c in (0, 1]; (1, 0) is the identity."""
    c = torch.as_tensor(confidence, dtype=torch.float64)
    return torch.where(torch.isfinite(c), torch.sigmoid(scale * _logit(c) + shift), c)


def fit_platt(confidence: torch.Tensor, right: torch.Tensor, ridge: float = 1.0) -> tuple[float, float]:
    """(scale, shift) of the Platt map maximising the likelihood of ``right`` given ``confidence``.

    Newton's method on the logistic log-likelihood of right ~ sigmoid(scale * logit(c) + shift)
    plus ``ridge`` / 2 x the squared distance of (scale, shift) from the identity (1, 0): a unit
    Gaussian prior, which keeps a fit on a few dozen pairs near the identity and is negligible
    on hundreds. The scale stays positive (a higher raw confidence never means a lower
    calibrated one).
    """
    x, y = _logit(confidence), right.double()
    if x.numel() < 2 or bool((y == y[0]).all()):
        return 1.0, 0.0  # nothing to fit on: keep the identity
    theta = torch.tensor([1.0, 0.0], dtype=torch.float64)
    feats = torch.stack([x, torch.ones_like(x)], 1)
    for _ in range(50):
        p = torch.sigmoid(feats @ theta)
        grad = feats.T @ (p - y) + ridge * (theta - torch.tensor([1.0, 0.0], dtype=torch.float64))
        hess = feats.T @ (feats * (p * (1 - p))[:, None]) + ridge * torch.eye(2, dtype=torch.float64)
        step = torch.linalg.solve(hess, grad)
        theta = theta - step
        if float(step.abs().max()) < 1e-10:
            break
    scale, shift = float(theta[0]), float(theta[1])
    return (scale, shift) if scale > 1e-3 and math.isfinite(scale) and math.isfinite(shift) else (1.0, 0.0)


def reliability(confidence: torch.Tensor, right: torch.Tensor, n_bins: int = 10) -> dict:
    """Per equal-width confidence bin: pairs, mean confidence, share right; and the ECE.

    ECE = sum over bins of (pairs in bin / pairs) x |share right - mean confidence|.
    """
    c, y = confidence.double().reshape(-1), right.double().reshape(-1)
    ok = torch.isfinite(c)
    c, y = c[ok], y[ok]
    idx = (c * n_bins).long().clamp(0, n_bins - 1)
    n = torch.bincount(idx, minlength=n_bins).double()
    mean_c = torch.bincount(idx, c, minlength=n_bins) / n.clamp_min(1)
    acc = torch.bincount(idx, y, minlength=n_bins) / n.clamp_min(1)
    ece = float((n * (acc - mean_c).abs()).sum() / n.sum().clamp_min(1))
    nan = float("nan")
    return {
        "n": [int(v) for v in n],
        "confidence": [float(v) if k else nan for v, k in zip(mean_c, n)],
        "accuracy": [float(v) if k else nan for v, k in zip(acc, n)],
        "ece": ece if int(n.sum()) else nan,
        "pairs": int(n.sum()),
    }


def expected_calibration_error(confidence: torch.Tensor, right: torch.Tensor, n_bins: int = 10) -> float:
    """The expected calibration error of confidences against outcomes (equal-width bins)."""
    return reliability(confidence, right, n_bins)["ece"]


def precision_bound(right: int, answered: int, level: float = 0.95) -> float:
    """The lower end of Wilson's ``level`` interval of a share right (``right`` of ``answered``).

    What a validation split can promise of the share of answers that are right on other pairs
    of the same kind: a decision fitted to reach a target on its split reaches it elsewhere only
    with a margin for the split's own chance. NaN without an answer.

    Example:
        >>> round(precision_bound(471 - 6, 471), 4)  # 98.7 % right of 471: at least 97.2 % (95 %)
        0.9725
        >>> precision_bound(10, 10) < 1.0  # ten of ten is not a certainty
        True
    """
    if answered <= 0:
        return float("nan")
    z = float(torch.special.ndtri(torch.tensor(0.5 + level / 2, dtype=torch.float64)))
    p, n = right / answered, answered
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half
