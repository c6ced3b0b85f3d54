"""The losses compared in the fine stage: photometric L1, local NCC, NGF, and the quality loss.

Every peer loss is a masked mean over valid pixels (or valid windows), averaged over a
``levels``-level pyramid of 2 x 2 means (the mask shrinks with it, as in learnreg's L1). Each
can reduce over the batch (``per_pair=False``: sum over the batch / count over the batch, what
training uses) or per pair (``per_pair=True``: a (B,) vector, what test-time refinement sums so
that pairs do not interact).

* L1: |warped - b|.
* NCC: 1 - the mean over valid window centres of the normalised cross-correlation in a k x k
  box window, cov / sqrt((var_a + eps)(var_b + eps)); invariant to a gain and offset of either
  image (up to eps).
* NGF (Haber & Modersitzki 2006): 1 - mean (g1.g2 + e1 e2)^2 / ((|g1|^2 + e1^2)(|g2|^2 + e2^2))
  with central-difference gradients and e_i = eta * the RMS gradient of image i over its valid
  pixels (detached): a gain of either image scales its gradients and its eps alike. By
  Cauchy-Schwarz on (g1, e1) and (g2, e2) each term is <= 1, with equality for identical images.
* quality: ``lensdist_torch.RegistrationQualityLoss`` with ``reduction="masked_mean"`` (the
  mean over the blocks whose pixels are all valid after the metric's 3 x 3 erosion); per pair
  the same mean taken pair by pair from ``reduction="none"``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from lensdist_torch import QualityConfig, RegistrationQualityLoss
from lensdist_torch.metric import erode_valid

__all__ = ["PEER_TERMS", "l1_term", "ncc_term", "ngf_term", "peer_loss", "quality_per_pair", "Criterion"]


def _reduce(num: torch.Tensor, den: torch.Tensor, per_pair: bool) -> torch.Tensor:
    """Per-pair sums (B,) and counts (B,) -> (B,) means, or the batch's sum / count."""
    if per_pair:
        return num / den.clamp_min(1.0)
    return num.sum() / den.sum().clamp_min(1.0)


def l1_term(x: torch.Tensor, y: torch.Tensor, valid: torch.Tensor, **_) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pair (sum, count) of |x - y| over valid pixels."""
    return ((x - y).abs() * valid).sum(dim=(1, 2, 3)), valid.sum(dim=(1, 2, 3))


def local_ncc(x: torch.Tensor, y: torch.Tensor, window: int = 9, eps: float = 1e-4) -> torch.Tensor:
    """NCC of x and y in every k x k box window that fits in the image: (B, 1, H-k+1, W-k+1)."""

    def box(t):
        return F.avg_pool2d(t, window, stride=1)

    mx, my = box(x), box(y)
    vx = (box(x * x) - mx * mx).clamp_min(0.0)
    vy = (box(y * y) - my * my).clamp_min(0.0)
    cov = box(x * y) - mx * my
    return cov / torch.sqrt((vx + eps) * (vy + eps))


def ncc_term(x, y, valid, ncc_window: int = 9, ncc_eps: float = 1e-4, **_):
    """Per-pair (sum of 1 - NCC, count) over windows lying wholly in the valid region."""
    k = int(ncc_window)
    if min(x.shape[-2:]) < k:
        raise ValueError(f"loss.ncc_window = {k} is larger than the image ({tuple(x.shape[-2:])}) at a pyramid level")
    vw = (F.avg_pool2d(valid, k, stride=1) > 0.999).to(x.dtype)
    ncc = local_ncc(x, y, k, float(ncc_eps))
    return ((1.0 - ncc) * vw).sum(dim=(1, 2, 3)), vw.sum(dim=(1, 2, 3))


def _gradients(x: torch.Tensor) -> torch.Tensor:
    """Central differences at the interior pixels: (B, 2, H-2, W-2)."""
    gx = 0.5 * (x[..., 1:-1, 2:] - x[..., 1:-1, :-2])
    gy = 0.5 * (x[..., 2:, 1:-1] - x[..., :-2, 1:-1])
    return torch.cat([gx, gy], dim=1)


def ngf_term(x, y, valid, ngf_eta: float = 0.2, **_):
    """Per-pair (sum of 1 - NGF alignment, count) over interior pixels whose 3 x 3 stencil is valid."""
    g1, g2 = _gradients(x), _gradients(y)
    v = (F.avg_pool2d(valid, 3, stride=1) > 0.999).to(x.dtype)
    n = v.sum(dim=(1, 2, 3)).clamp_min(1.0)

    def eps2(g):  # (eta * RMS gradient)^2 per pair, detached; floored for flat images
        ms = ((g * g).sum(dim=1, keepdim=True) * v).sum(dim=(1, 2, 3)) / n
        return (float(ngf_eta) ** 2 * ms).detach().clamp_min(1e-12).view(-1, 1, 1, 1)

    e1, e2 = eps2(g1), eps2(g2)
    dot = (g1 * g2).sum(dim=1, keepdim=True) + torch.sqrt(e1 * e2)
    n1 = (g1 * g1).sum(dim=1, keepdim=True) + e1
    n2 = (g2 * g2).sum(dim=1, keepdim=True) + e2
    align = dot * dot / (n1 * n2)
    return ((1.0 - align) * v).sum(dim=(1, 2, 3)), v.sum(dim=(1, 2, 3))


PEER_TERMS = {"l1": l1_term, "ncc": ncc_term, "ngf": ngf_term}


def peer_loss(peer: str, x, y, valid, loss_cfg: dict, per_pair: bool = False) -> torch.Tensor:
    """A peer loss averaged over ``loss_cfg["levels"]`` pyramid levels (2 x 2 means)."""
    term = PEER_TERMS[peer]
    total = 0.0
    levels = int(loss_cfg["levels"])
    for level in range(levels):
        if level:
            x, y = F.avg_pool2d(x, 2), F.avg_pool2d(y, 2)
            valid = (F.avg_pool2d(valid, 2) > 0.999).to(valid.dtype)
        total = total + _reduce(*term(x, y, valid, **loss_cfg), per_pair)
    return total / levels


def quality_per_pair(loss_fn: RegistrationQualityLoss, x, y, valid) -> torch.Tensor:
    """The masked mean of the smooth error map pair by pair: (B,). For one pair it equals the
    library's ``reduction="masked_mean"`` (a test checks it). ``loss_fn``: ``reduction="none"``."""
    err = loss_fn(x, y, valid)
    bs = loss_fn.config.block_size
    v = erode_valid((valid >= 0.5).to(x.dtype))
    full = -F.max_pool2d(-v, kernel_size=bs, stride=bs)
    return (err * full).sum(dim=(1, 2, 3)) / full.sum(dim=(1, 2, 3)).clamp_min(1.0)


class Criterion:
    """peer loss + lambda * quality loss, with the metric's temperatures scaled by ``tau_scale``.

    ``__call__(warped, b, valid, lam)`` returns (loss, peer, quality) for the batch, or (B,)
    vectors with ``per_pair=True``. ``warped`` is clamped to [0, 1] for the metric.
    """

    def __init__(self, peer: str, loss_cfg: dict, tau_scale: float = 1.0, per_pair: bool = False) -> None:
        if peer not in PEER_TERMS:
            raise ValueError(f"unknown peer loss {peer!r}; one of {sorted(PEER_TERMS)}")
        self.peer, self.loss_cfg, self.per_pair = peer, dict(loss_cfg), per_pair
        qcfg = QualityConfig().with_temperature_scale(float(tau_scale))
        self.quality = RegistrationQualityLoss(qcfg, reduction="none" if per_pair else "masked_mean", validate=False)

    def __call__(self, warped, b, valid, lam: float):
        p = peer_loss(self.peer, warped, b, valid, self.loss_cfg, self.per_pair)
        if lam <= 0:
            return p, p, torch.zeros_like(p)
        w = warped.clamp(0, 1)
        q = quality_per_pair(self.quality, w, b, valid) if self.per_pair else self.quality(w, b, valid)
        return p + lam * q, p, q
