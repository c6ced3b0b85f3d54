"""A sequence's verified matches: every pair's inlier matches read from COLMAP's database, and their thinning.

What the homography model (:mod:`~lensdist_torch.calibration.planar_features`), its guided
matching and its match refinement fit: per match its two points (pixels, centres at integers),
its pair, and per pair its two frames.

Example:
    >>> import torch
    >>> p = torch.arange(6.0, dtype=torch.float64)[:, None].repeat(1, 2)
    >>> m = PlanarMatches(x1=p, x2=p + 1, pair=torch.zeros(6, dtype=torch.long), first=torch.tensor([0]),
    ...                   second=torch.tensor([1]), names=("a", "b"))
    >>> len(thin_matches(m, 3).pair)
    3
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from lensdist_torch.calibration.multiview import pycolmap_or_error

__all__ = ["PLANAR_MIN_MATCHES", "PLANAR_PAIR_MATCHES", "PlanarMatches", "read_verified_matches", "thin_matches"]

#: A pair counts in the homography model with at least this many verified matches, and then inliers.
PLANAR_MIN_MATCHES = 15
#: A pair's matches beyond this many are thinned to this many, evenly over its list (a homography needs few; the
#: fits' time grows with the matches).
PLANAR_PAIR_MATCHES = 60


class PlanarMatches(NamedTuple):
    """Feature matches of a sequence, flat, in pixels with centres at integers.

    x1, x2 (N, 2) float64: the matched points in frames first[pair] and second[pair]; pair (N,)
    the pair of each match; first, second (P,) the frames' indices in ``names`` (recording order).

    Example:
        >>> p = torch.tensor([[10.0, 20.0]], dtype=torch.float64)
        >>> m = PlanarMatches(p, p + 1, torch.tensor([0]), torch.tensor([0]), torch.tensor([1]), ("a.png", "b.png"))
        >>> len(m.first), m.names[int(m.second[0])]
        (1, 'b.png')
    """

    x1: torch.Tensor
    x2: torch.Tensor
    pair: torch.Tensor
    first: torch.Tensor
    second: torch.Tensor
    names: tuple


def read_verified_matches(database, names: list[str], min_matches: int = 15) -> PlanarMatches:
    """Every verified pair's inlier matches from a COLMAP database, in pixels with centres at integers.

    Args:
        database: the path of a COLMAP database after feature extraction and matching.
        names: the frames' names in recording order (the jackknife's blocks follow it).
        min_matches: pairs with fewer verified matches are left out.

    Returns:
        :class:`PlanarMatches` (float64; COLMAP's pixel centres lie at +0.5, taken off).
    """
    pc = pycolmap_or_error()
    order = {n: i for i, n in enumerate(names)}
    x1, x2, pair, first, second = [], [], [], [], []
    db = pc.Database.open(str(database))
    try:
        ids = {im.image_id: im.name for im in db.read_all_images()}
        keypoints = {}
        pair_ids, geometries = db.read_two_view_geometries()
        for pid, m in zip(pair_ids, (g.inlier_matches for g in geometries)):
            a, b = pc.pair_id_to_image_pair(pid)
            if len(m) < min_matches or ids.get(a) not in order or ids.get(b) not in order:
                continue
            for i in (a, b):
                if i not in keypoints:
                    keypoints[i] = torch.as_tensor(db.read_keypoints(i)[:, :2], dtype=torch.float64) - 0.5
            # SIFT gives a point several orientations, so a match can repeat: keep each once
            both = torch.cat([keypoints[a][torch.as_tensor(m[:, 0], dtype=torch.long)],
                              keypoints[b][torch.as_tensor(m[:, 1], dtype=torch.long)]], 1).unique(dim=0)
            if len(both) < min_matches:
                continue
            x1.append(both[:, :2])
            x2.append(both[:, 2:])
            m = both
            pair.append(torch.full((len(m),), len(first), dtype=torch.long))
            first.append(order[ids[a]])
            second.append(order[ids[b]])
    finally:
        db.close()

    def cat(t: list, empty: tuple) -> torch.Tensor:
        return torch.cat(t) if t else torch.zeros(empty, dtype=torch.float64)

    return PlanarMatches(
        x1=cat(x1, (0, 2)), x2=cat(x2, (0, 2)), pair=torch.cat(pair) if pair else torch.zeros(0, dtype=torch.long),
        first=torch.tensor(first, dtype=torch.long), second=torch.tensor(second, dtype=torch.long),
        names=tuple(names))


def thin_matches(matches: PlanarMatches, cap: int) -> PlanarMatches:
    """Each pair's matches beyond ``cap`` thinned to ``cap``, evenly over the pair's list (0: all kept).

    Example:
        >>> p = torch.arange(10.0, dtype=torch.float64)[:, None].repeat(1, 2)
        >>> m = PlanarMatches(p, p, torch.zeros(10, dtype=torch.long), torch.tensor([0]), torch.tensor([1]), ("a", "b"))
        >>> thin_matches(m, 4).x1[:, 0].tolist()
        [2.0, 4.0, 7.0, 9.0]
    """
    if cap <= 0 or len(matches.pair) == 0:
        return matches
    order = torch.sort(matches.pair, stable=True).indices
    pair = matches.pair[order]
    count = torch.bincount(pair, minlength=len(matches.first))
    start = torch.cumsum(count, 0) - count
    rank = torch.arange(len(pair)) - start[pair]
    n = count[pair]
    keep = (n <= cap) | ((rank + 1) * cap // n > rank * cap // n)  # exactly cap of n, evenly spaced
    idx = order[keep]
    return PlanarMatches(
        x1=matches.x1[idx], x2=matches.x2[idx], pair=matches.pair[idx], first=matches.first, second=matches.second,
        names=matches.names)
