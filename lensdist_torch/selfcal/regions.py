"""The frame's rectangles of the self-calibration's samples: its cluster-robust covariance and its aligned residual.

The full-size samples of :func:`~lensdist_torch.selfcal.fit.estimate_distortion` (one per
``block`` x ``block`` cell, row-major) are grouped in ``clusters`` x ``clusters`` rectangles of
the frame (``selfcal.fit.CLUSTERS``). Two statistics read them (docs/method.md, section 10):

* the cluster-robust (sandwich) covariance of the fit: residuals that a smooth misfit makes
  alike within a rectangle pull together and widen the std;
* the aligned residual: the RMS residual without the worst ``selfcal.fit.OCCLUDED_SHARE`` of the
  rectangles, what ``analyze`` puts to the registration's test. An occluder or a moving object
  spoils a few rectangles; a lens the model cannot follow spoils most of the border.
"""

from __future__ import annotations

import torch

__all__ = ["region_ids", "cluster_robust_covariance", "aligned_residual"]


def region_ids(h0: int, w0: int, *, block: int, clusters: int, device=None) -> torch.Tensor:
    """(N,) int64: the rectangle (row-major, of ``clusters`` x ``clusters``) of each full-size sample.

    Args:
        h0: the full-size frame's height.
        w0: its width.
        block: one sample per ``block`` x ``block`` cell, row-major (1: every pixel).
        clusters: rectangles per side.
        device: of the result (None: the CPU).

    Example:
        >>> region_ids(4, 6, block=2, clusters=2).tolist()  # 2 x 3 samples in 2 x 2 rectangles
        [0, 0, 1, 2, 2, 3]
    """
    hb, wb = (h0 // block, w0 // block) if block > 1 else (h0, w0)
    rows = torch.arange(hb, device=device) * clusters // hb
    cols = torch.arange(wb, device=device) * clusters // wb
    return (rows[:, None] * clusters + cols[None, :]).flatten()


def cluster_robust_covariance(
    inv: torch.Tensor, score: torch.Tensor, region: torch.Tensor, n_regions: int
) -> torch.Tensor:
    """A^-1 (sum_c g_c g_c^T) A^-1 C / (C - 1), g_c the sum of ``score``'s samples in rectangle c.

    Args:
        inv: (B, P, P) A^-1, the inverse of the weighted normal matrix.
        score: (B, P, N) J_i w_i r_i per sample.
        region: (N,) each sample's rectangle (:func:`region_ids`).
        n_regions: C >= 2.

    For independent noise it matches the Gauss-Newton covariance (it is the linearised
    delete-one-cluster jackknife).
    """
    g = score.new_zeros(*score.shape[:2], n_regions).index_add_(2, region, score)
    return inv @ (g @ g.transpose(1, 2) * (n_regions / (n_regions - 1))) @ inv


def aligned_residual(
    res: torch.Tensor, valid: torch.Tensor, region: torch.Tensor | None = None, *, n_regions: int = 0, drop: int = 0
) -> torch.Tensor:
    """(B,) float32: the RMS of ``res`` over its valid samples, the worst ``drop`` rectangles left out.

    The rectangles are ranked by their mean squared residual (one without a valid sample counts
    as 0: it has nothing to leave out); ``drop`` 0 (or ``region`` None) gives the RMS of every
    valid sample.

    Args:
        res: (B, N) residuals, 0 where not valid.
        valid: (B, N) bool.
        region: (N,) each sample's rectangle (:func:`region_ids`), or None (the plain RMS).
        n_regions: the number of rectangles (with ``region``).
        drop: how many to leave out, < n_regions.

    Example:
        >>> res = torch.tensor([[0.0, 0.0, 3.0, 3.0]])  # rectangle 1 spoiled
        >>> valid, region = torch.ones(1, 4, dtype=torch.bool), torch.tensor([0, 0, 1, 1])
        >>> tuple(float(aligned_residual(res, valid, region, n_regions=2, drop=d)[0]) for d in (0, 1))
        (2.1213202476501465, 0.0)
    """
    sq, n = res.double() ** 2, valid.double()
    if drop == 0 or region is None:
        return torch.sqrt(sq.sum(1) / n.sum(1).clamp_min(1)).float()
    ss = sq.new_zeros(len(sq), n_regions).index_add_(1, region, sq)
    nn = sq.new_zeros(len(sq), n_regions).index_add_(1, region, n)
    keep = torch.where(nn > 0, ss / nn.clamp_min(1), torch.zeros_like(ss)).argsort(1)[:, : n_regions - drop]
    return torch.sqrt(ss.gather(1, keep).sum(1) / nn.gather(1, keep).sum(1).clamp_min(1)).float()
