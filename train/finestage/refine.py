"""Test-time refinement: the losses optimising the eight corner offsets of each pair directly.

The simplest way to plug a loss into registration: start from the coarse stage's answer (here
no correction, 0.5-3 px from the truth), run a fixed budget of Adam steps on the offsets of a
whole batch of pairs at once. The loss is the sum of per-pair losses, so the pairs do not
interact (Adam is element-wise): a pair's result does not depend on its batch.
"""

from __future__ import annotations

import torch
from learnreg.losses import corner_error, warp_a_to_b

from .data import load_scenes, make_pairs
from .losses import Criterion

__all__ = ["refine_batch", "refine"]


def refine_batch(a, b, gt, crit: Criterion, lam: float, lr: float, steps: int):
    """Adam on the (N, 4, 2) offsets from zero; returns (final offsets, (steps + 1, N) errors)."""
    delta = torch.zeros_like(gt, requires_grad=True)
    opt = torch.optim.Adam([delta], lr=float(lr))
    curve = [(delta.detach() - gt).norm(dim=-1).mean(dim=-1)]
    for _ in range(int(steps)):
        warped, valid = warp_a_to_b(a, delta)
        loss = crit(warped, b, valid, lam)[0]
        opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        opt.step()
        curve.append((delta.detach() - gt).norm(dim=-1).mean(dim=-1))
    return delta.detach(), torch.stack(curve)


def refine(cfg, peer, lam, tau_scale, lr, seeds, split, distorted, device="cpu", scenes=None):
    """Refine the pairs of ``seeds``; returns (per-pair corner errors (N,) float64 px, mean
    error per Adam step (steps + 1,))."""
    scenes = scenes if scenes is not None else load_scenes(cfg)
    r, patch = cfg["refine"], int(cfg["data"]["patch"])
    crit = Criterion(peer, cfg["loss"], tau_scale, per_pair=True)
    errs, curves = [], []
    for i in range(0, len(seeds), int(r["batch_size"])):
        batch = make_pairs(scenes, seeds[i : i + int(r["batch_size"])], cfg["data"], distorted, split)
        a, b, gt = (batch[k].to(device) for k in ("a", "b", "delta"))
        delta, curve = refine_batch(a, b, gt, crit, lam, lr, int(r["steps"]))
        errs.append(corner_error(delta.cpu(), batch["delta"], patch))
        curves.append(curve.cpu().double())
    return torch.cat(errs), torch.cat(curves, dim=1).mean(dim=1)
