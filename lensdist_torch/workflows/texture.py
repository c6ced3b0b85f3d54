"""The texture of a scene, for the learned methods' domain check (docs/method.md, section 10).

A checkpoint fitted on a few scenes stores their gradient-magnitude histograms
(:func:`texture_statistics`, in its ``extra``); a pair whose histogram is farther from every
training scene than ``decision.TEXTURE_FACTOR`` times the largest distance of a training view is
out of domain (:func:`~lensdist_torch.workflows.decision.domain_checks`).

Example:
    >>> h = texture_histogram(torch.rand(2, 1, 32, 32, generator=torch.Generator().manual_seed(0)))
    >>> tuple(h.shape), bool(torch.allclose(h.sum(1), torch.ones(2, dtype=torch.float64)))
    ((2, 18), True)
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.metric.criteria import local_criteria

__all__ = ["TEXTURE_EDGES", "texture_histogram", "texture_statistics", "texture_distance"]

#: Bin edges of the gradient-magnitude histogram (normalised Sobel on [0, 1] intensities),
#: log-spaced; values below and above fall into two more bins.
TEXTURE_EDGES = tuple(float(v) for v in torch.logspace(math.log10(0.002), math.log10(0.5), 17, dtype=torch.float64))


def texture_histogram(img: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) grey images in [0, 1] -> (B, 18) float64 histograms of the gradient magnitude G."""
    g = local_criteria(img, img, validate=False).g1.flatten(1).double()
    idx = torch.bucketize(g, torch.tensor(TEXTURE_EDGES, dtype=torch.float64, device=g.device))
    n = len(TEXTURE_EDGES) + 1
    hist = torch.zeros(g.shape[0], n, dtype=torch.float64, device=g.device).scatter_add_(1, idx, torch.ones_like(g))
    return (hist / hist.sum(1, keepdim=True)).cpu()


def texture_statistics(config: LensdistConfig, scenes: list[torch.Tensor], names: list[str], n_views: int = 24) -> dict:
    """The training scenes' texture, for a checkpoint's ``extra``.

    Renders the first ``n_views`` training views (I1) of every scene through the protocol
    (docs/method.md, section 7), and returns {"names", "reference": the mean histogram per
    scene, "spread": the largest total-variation distance of a view from its scene's mean}.
    """
    n_scenes = len(scenes)
    params = draw_pairs(config, "train", range(min(config.protocol.n_train, 4 * n_views * n_scenes)), n_scenes)
    refs, spread = [], 0.0
    for s in range(n_scenes):
        sel = (params.scene == s).nonzero().flatten()[:n_views].tolist()
        if not sel:
            raise ValueError(f"no training view of scene {names[s]!r} among the first pairs")
        sub = draw_pairs(config, "train", params.index[sel].tolist(), n_scenes)
        img1, _ = render_pairs(scenes, sub, config)
        h = texture_histogram(img1.clamp(0, 1))
        ref = h.mean(0)
        refs.append(ref.tolist())
        spread = max(spread, float(0.5 * (h - ref).abs().sum(1).max()))
    return {"names": list(names), "edges": list(TEXTURE_EDGES), "reference": refs, "spread": spread}


def texture_distance(hist: torch.Tensor, stats: dict) -> torch.Tensor:
    """(B,) total-variation distance of histograms (B, n) from the nearest training scene."""
    ref = torch.tensor(stats["reference"], dtype=torch.float64)
    return 0.5 * (hist[:, None, :] - ref[None]).abs().sum(-1).min(1).values
