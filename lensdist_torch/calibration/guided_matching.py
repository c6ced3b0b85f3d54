"""Guided matching: a sequence's feature matches found again where the homography model predicts them.

On repetitive texture (a chessboard, tiles, a brick wall) a SIFT descriptor has many look-alikes
in the other view, so the matcher's ratio test discards most true matches and the epipolar
verification keeps some wrong ones, so few pairs keep enough homography inliers and the lens
map's bending is poorly known (docs/method.md, section 12). Once the
homography model has a lens, each pair's ideal points are one homography apart, so a feature's
partner must lie within a few pixels of where that homography sends it; there the look-alikes
are gone. docs/method.md, section 12, step 10.

It runs where fewer than ``PLANAR_GUIDED_BELOW`` of the verified pairs kept their homography
inliers in the first fit (:func:`self_calibrate_guided`).

1. **Each view on the plane**: every verified pair's homography between the lens's ideal points
   by LO-RANSAC (``PLANAR_INLIER_PX``; pairs with ``PLANAR_MIN_MATCHES`` inliers count); a
   spanning tree of the counting pairs, the pairs with most inliers first, chains the views onto
   one plane, so a pair whose own matches failed gets its homography through the others.
2. **Guided matches**: for every verified pair of two chained views (the pairs COLMAP matched,
   none added), each keypoint of the first view mapped by the pair's homography (its own where
   it counts, the chain's otherwise); its partner is the keypoint of the second view within
   :data:`PLANAR_GUIDED_PX` (ideal pixels) whose descriptor is closest, kept where the two are each
   other's closest and the closest is clearly closer than the next candidate more than 2 px away
   (``PLANAR_GUIDED_RATIO`` on the descriptors' distances; nearer ones are the same point's other
   SIFT orientations). A match found through several orientations is kept once.

The matches are then fitted again (:func:`~lensdist_torch.calibration.planar_features.self_calibrate_planar`
from the first lens). They are chosen near the first fit's prediction, so they cannot say
whether the scene is a plane: that test stays with the verified matches (the first fit).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch

from lensdist_torch.calibration.match_refinement import PLANAR_REFINE_PX, refine_matches
from lensdist_torch.calibration.matches import (
    PLANAR_MIN_MATCHES,
    PLANAR_PAIR_MATCHES,
    PlanarMatches,
    read_verified_matches,
    thin_matches,
)
from lensdist_torch.calibration.multiview import pycolmap_or_error
from lensdist_torch.calibration.planar_features import (
    PLANAR_INLIER_PX,
    PLANAR_MIN_INLIER_SHARE,
    pair_homographies,
    self_calibrate_planar,
)
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.geometry.radial_lens import lens_ideal_points

__all__ = ["PLANAR_GUIDED_BELOW", "PLANAR_GUIDED_PX", "PLANAR_GUIDED_RATIO", "chain_views", "guided_matches",
           "pair_homography", "read_features", "refined_matches", "self_calibrate_guided"]

#: A guided match's descriptor distance at most this share of the next candidate's (the ratio test, among the
#: candidates within :data:`PLANAR_GUIDED_PX`).
PLANAR_GUIDED_RATIO = 0.8
#: Guided matching runs where fewer than this share of the verified pairs keep ``PLANAR_MIN_MATCHES`` homography
#: inliers in the first fit (repetitive texture lost them); where most keep them guided matches would only cost time.
PLANAR_GUIDED_BELOW = 0.5
#: The homography model's matches are found again within this many ideal pixels of where its first fit sends each
#: keypoint, and fitted again; 0: the first fit answers.
PLANAR_GUIDED_PX = 3.0


def read_features(database, names: list[str]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Every frame's SIFT keypoints and descriptors from a COLMAP database, in ``names``' order.

    Returns:
        Per frame (points (K, 2) float64 in pixels with centres at integers, descriptors (K, 128)
        float32 of unit length); a point with several orientations appears once per orientation.
    """
    pc = pycolmap_or_error()
    import numpy as np

    db = pc.Database.open(str(database))
    try:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        out = []
        for name in names:
            if name not in ids:
                raise ValueError(f"database: no image named {name!r}")
            points = torch.tensor(np.asarray(db.read_keypoints(ids[name]))[:, :2], dtype=torch.float64) - 0.5
            desc = torch.tensor(np.asarray(db.read_descriptors(ids[name]).data), dtype=torch.float32)
            out.append((points, torch.nn.functional.normalize(desc, dim=1)))
    finally:
        db.close()
    return out


def chain_views(matches: PlanarMatches, coefficients, *, centre, size: tuple[int, int],
                config: MultiViewConfig | None = None) -> tuple[dict, dict]:
    """Step 1: the counting pairs' homographies and each chained view's homography onto one plane.

    Args:
        matches: the verified matches (:func:`~lensdist_torch.calibration.matches.read_verified_matches`).
        coefficients: the lens's a_1 .. a_n (:func:`~lensdist_torch.calibration.planar_model.lens_ideal_points`).
        centre: its distortion centre (x, y) in pixels; None: the frame centre.
        size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig` (``seed``;
            the constant ``PLANAR_INLIER_PX``).

    Returns:
        (pairs, views): {(i, j): 3 x 3 homography from view i's ideal pixels to view j's} for the
        counting pairs, and {view: 3 x 3 homography from its ideal pixels onto the plane of the
        view with most inliers} for the views the tree reaches.

    Example:
        >>> p = torch.rand(40, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 300
        >>> m = PlanarMatches(p, p + torch.tensor([5.0, -3.0], dtype=torch.float64), torch.zeros(40, dtype=torch.long),
        ...                   torch.tensor([0]), torch.tensor([1]), ("a", "b"))
        >>> pairs, views = chain_views(m, [0.0], centre=None, size=(240, 320))
        >>> [round(float(v), 3) for v in pairs[(0, 1)][:2, 2]], sorted(views)  # a shift of (5, -3) px
        ([5.0, -3.0], [0, 1])
    """
    cfg = or_defaults(config, MultiViewConfig)
    h, w = size
    pairs, weight = {}, {}
    u1 = lens_ideal_points(matches.x1, coefficients, h, w, centre=centre)
    u2 = lens_ideal_points(matches.x2, coefficients, h, w, centre=centre)
    for p, _, hm, mask in pair_homographies(u1, u2, matches.pair, which=range(len(matches.first)),
                                            max_error=PLANAR_INLIER_PX, seed=cfg.seed):
        if hm is not None and int(mask.sum()) >= PLANAR_MIN_MATCHES:
            key = (int(matches.first[p]), int(matches.second[p]))
            pairs[key], weight[key] = hm, int(mask.sum())
    if not pairs:
        return pairs, {}
    strength: dict[int, int] = {}
    for (i, j), n in weight.items():
        strength[i], strength[j] = strength.get(i, 0) + n, strength.get(j, 0) + n
    root = max(sorted(strength), key=lambda v: strength[v])
    views = {root: torch.eye(3, dtype=torch.float64)}
    edges = sorted(weight, key=lambda k: -weight[k])
    grown = True
    while grown:  # Prim's tree: the strongest pair that reaches a new view, until none does
        grown = False
        for i, j in edges:
            if (i in views) != (j in views):
                hm = pairs[(i, j)]  # u_j ~ hm u_i
                if i in views:
                    views[j] = views[i] @ torch.linalg.inv(hm)
                else:
                    views[i] = views[j] @ hm
                grown = True
                break
    return pairs, views


def pair_homography(pairs: dict, views: dict, i: int, j: int) -> torch.Tensor | None:
    """View i's ideal pixels to view j's: the pair's own homography if it counts, else the chain's (None: unchained)."""
    hm = pairs.get((i, j))
    if hm is None and i in views and j in views:
        hm = torch.linalg.inv(views[j]) @ views[i]
    return hm


def guided_matches(features: list, matches: PlanarMatches, coefficients, *, centre, size: tuple[int, int],
                   config: MultiViewConfig | None = None) -> PlanarMatches:
    """Step 2: the verified pairs matched again where the lens and the pairs' homographies predict.

    Args:
        features: per frame (points, descriptors), :func:`read_features`.
        matches: the verified matches (their pairs are the ones matched again).
        coefficients: the first fit's lens, a_1 .. a_n.
        centre: its distortion centre (x, y) in pixels; None: the frame centre.
        size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig` (:func:`chain_views`' ``seed``; the
            constants :data:`PLANAR_GUIDED_PX`, ``PLANAR_MIN_MATCHES`` and :data:`PLANAR_GUIDED_RATIO`).

    Returns:
        :class:`~lensdist_torch.calibration.matches.PlanarMatches` (pairs with at least
        ``PLANAR_MIN_MATCHES`` guided matches; the pairs' indices renumbered).

    Example:
        >>> g = torch.Generator().manual_seed(1)
        >>> pts = torch.rand(60, 2, dtype=torch.float64, generator=g) * 200 + 20
        >>> desc = torch.nn.functional.normalize(torch.randn(60, 128, generator=g), dim=1)
        >>> feats = [(pts, desc), (pts + torch.tensor([4.0, 2.0], dtype=torch.float64), desc)]
        >>> verified = PlanarMatches(pts[:20], feats[1][0][:20], torch.zeros(20, dtype=torch.long),
        ...                          torch.tensor([0]), torch.tensor([1]), ("a", "b"))
        >>> len(guided_matches(feats, verified, [0.0], centre=None, size=(240, 320)).pair)  # 20 verified, all 60 guided
        60
    """
    cfg = or_defaults(config, MultiViewConfig)
    h, w = size
    pairs, views = chain_views(matches, coefficients, centre=centre, size=size, config=cfg)
    ideal = {v: lens_ideal_points(features[v][0], coefficients, h, w, centre=centre) for v in views}
    x1, x2, pair, first, second = [], [], [], [], []
    for p in range(len(matches.first)):
        i, j = int(matches.first[p]), int(matches.second[p])
        if i not in views or j not in views:
            continue
        hm = pair_homography(pairs, views, i, j)
        ok_i, ok_j = _guided_pair(
            apply_homography(hm[None], ideal[i])[0], ideal[j], features[i][1], features[j][1]
        )
        if len(ok_i) < PLANAR_MIN_MATCHES:
            continue
        both = torch.cat([features[i][0][ok_i], features[j][0][ok_j]], 1).unique(dim=0)
        x1.append(both[:, :2])
        x2.append(both[:, 2:])
        pair.append(torch.full((len(both),), len(first), dtype=torch.long))
        first.append(i)
        second.append(j)
    empty = torch.zeros(0, 2, dtype=torch.float64)
    return PlanarMatches(
        x1=torch.cat(x1) if x1 else empty, x2=torch.cat(x2) if x2 else empty,
        pair=torch.cat(pair) if pair else torch.zeros(0, dtype=torch.long),
        first=torch.tensor(first, dtype=torch.long), second=torch.tensor(second, dtype=torch.long),
        names=matches.names)


def _guided_pair(predicted: torch.Tensor, target: torch.Tensor, d1: torch.Tensor, d2: torch.Tensor,
                 chunk: int = 2048) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices (rows of view 1, rows of view 2) of the guided matches of one pair (module docstring, step 2)."""
    r = PLANAR_GUIDED_PX
    ci, cj = [], []
    for s in range(0, len(predicted), chunk):  # the candidates: within r of the prediction
        near = (torch.cdist(predicted[s:s + chunk], target) < r).nonzero()
        ci.append(near[:, 0] + s)
        cj.append(near[:, 1])
    ci, cj = torch.cat(ci), torch.cat(cj)
    if len(ci) == 0:
        return ci, cj
    sim = (d1[ci] * d2[cj]).sum(1)
    n1, n2 = len(predicted), len(target)
    best1 = torch.full((n1,), -2.0, dtype=sim.dtype).scatter_reduce(0, ci, sim, "amax")
    best2 = torch.full((n2,), -2.0, dtype=sim.dtype).scatter_reduce(0, cj, sim, "amax")
    top = (sim == best1[ci]) & (sim == best2[cj])  # each the other's closest
    # the next candidate of the same row more than 2 px from the chosen one (other orientations of a point are one)
    chosen = torch.full((n1,), -1, dtype=torch.long)
    chosen[ci[top]] = cj[top]
    other = (chosen[ci] >= 0) & ((target[cj] - target[chosen[ci].clamp_min(0)]).norm(dim=-1) > 2.0)
    runner = torch.full((n1,), -2.0, dtype=sim.dtype).scatter_reduce(0, ci[other], sim[other], "amax")
    dist = lambda s: torch.sqrt((2 - 2 * s).clamp_min(0))  # noqa: E731 - unit vectors' distance from their cosine
    clear = (runner[ci] < -1.5) | (dist(sim) < PLANAR_GUIDED_RATIO * dist(runner[ci]))
    keep = top & clear
    return ci[keep], cj[keep]


def self_calibrate_guided(database, names: list[str], size: tuple[int, int], *, config: MultiViewConfig | None = None,
                          settings=None, images: Callable[[int], torch.Tensor] | None = None):
    """The homography model on a COLMAP database, refitted on guided matches, then on refined ones (module docstring).

    The first fit is on the verified matches
    (:func:`~lensdist_torch.calibration.planar_features.self_calibrate_planar`); where it has a lens
    and found a plane, and under :data:`PLANAR_GUIDED_BELOW` of the verified pairs kept their
    homography inliers, the verified pairs are matched again under it (:func:`guided_matches`) and
    fitted again from its lens, the plane test's share carried over. The second fit answers where
    it has an estimate and counts more pairs than the first (guided matching is there to bring
    lost pairs back, and a second fit on fewer pairs than the first has lost them instead);
    ``guided`` says what was found, whether it answered and the first fit's figures.
    :data:`PLANAR_GUIDED_PX` 0: the first fit alone.

    With ``images``, the matches of the fit that answers are then moved to sub-pixel agreement
    under its lens (:func:`~lensdist_torch.calibration.match_refinement.refine_matches`, each pair's
    homography its own or the chain's) and fitted again from its lens; that fit answers where it
    has an estimate (``refined`` says what was kept and the figures before).

    Args:
        database: a COLMAP database after feature extraction and matching.
        names: the frames' names in recording order.
        size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig`.
        settings: the library's config (the class rule and the paper's frame).
        images: view index (into ``names``) -> its (H, W) grey image in [0, 1]; None: no refinement.

    Returns:
        :class:`~lensdist_torch.calibration.planar_features.PlanarCalibration`.
    """
    cfg = or_defaults(config, MultiViewConfig)
    verified = read_verified_matches(database, names, PLANAR_MIN_MATCHES)
    first = self_calibrate_planar(verified, size, config=cfg, settings=settings)
    res, used = first, verified
    if (
        PLANAR_GUIDED_PX > 0
        and math.isfinite(first.delta_avg_user_px)
        and first.inlier_share >= PLANAR_MIN_INLIER_SHARE
        and first.pairs < PLANAR_GUIDED_BELOW * len(verified.first)
    ):
        found = guided_matches(read_features(database, names), verified, first.coefficients, centre=first.centre,
                               size=size, config=cfg)
        info = {"pairs_verified": len(verified.first), "pairs_matched": len(found.first), "matches": len(found.pair),
                "radius_px": PLANAR_GUIDED_PX, "first_fit": _figures(first)}
        again = self_calibrate_planar(found, size, config=cfg, settings=settings, start=first.coefficients,
                                      plane_share=first.inlier_share)
        if not math.isfinite(again.delta_avg_user_px):
            res = dataclasses.replace(first, guided={**info, "used": False, "reason": again.reason})
        elif again.pairs <= first.pairs:  # it was to bring lost pairs back: where it did not, the first fit stands
            res = dataclasses.replace(
                first,
                guided={
                    **info,
                    "used": False,
                    "reason": f"the guided matches count {again.pairs} pairs, the verified ones {first.pairs}",
                },
            )
        else:
            res, used = dataclasses.replace(again, guided={**info, "used": True, "reason": ""}), found
    if (images is None or PLANAR_REFINE_PX <= 0 or not math.isfinite(res.delta_avg_user_px)
            or res.inlier_share < PLANAR_MIN_INLIER_SHARE):
        return res
    refined, info = refined_matches(used, images, res.coefficients, centre=res.centre, size=size, config=cfg)
    info = {**info, "half_px": PLANAR_REFINE_PX, "before": _figures(res)}
    again = self_calibrate_planar(
        refined, size, config=cfg, settings=settings, start=res.coefficients, plane_share=first.inlier_share
    )
    if not math.isfinite(again.delta_avg_user_px):
        return dataclasses.replace(res, refined={**info, "used": False, "reason": again.reason})
    return dataclasses.replace(again, guided=res.guided, refined={**info, "used": True, "reason": ""})


def refined_matches(matches: PlanarMatches, images: Callable[[int], torch.Tensor], coefficients, *, centre,
                    size: tuple[int, int], config: MultiViewConfig | None = None):
    """A sequence's matches moved to sub-pixel agreement under a lens (the refinement of :func:`self_calibrate_guided`).

    Each pair's homography is its own where it counts, the chain's otherwise (:func:`chain_views`);
    each pair's matches are thinned to twice ``PLANAR_PAIR_MATCHES`` first.

    Args:
        matches: :class:`~lensdist_torch.calibration.matches.PlanarMatches` (verified or guided).
        images: view index (into ``matches.names``) -> its (H, W) grey image in [0, 1].
        coefficients: the lens's a_1 .. a_n.
        centre: its distortion centre (x, y) in pixels; None: the frame centre.
        size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig`.

    Returns:
        (matches, info) as :func:`~lensdist_torch.calibration.match_refinement.refine_matches` gives them.
    """
    cfg = or_defaults(config, MultiViewConfig)
    pairs, views = chain_views(matches, coefficients, centre=centre, size=size, config=cfg)
    hs = {}
    for i, j in zip(matches.first.tolist(), matches.second.tolist()):
        hm = pair_homography(pairs, views, i, j)
        if hm is not None:
            hs[(i, j)] = hm
    return refine_matches(thin_matches(matches, 2 * PLANAR_PAIR_MATCHES), images, hs, coefficients, centre=centre,
                          size=size, min_matches=PLANAR_MIN_MATCHES)


def _figures(res) -> dict:
    """A fit's figures kept beside the one that replaced it."""
    return {k: getattr(res, k) for k in ("model", "delta_avg_user_px", "delta_avg_user_interval", "pairs", "inliers",
                                         "matches", "reprojection_px", "bending_halfwidth_px", "class_label")}
