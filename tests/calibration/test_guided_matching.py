"""Guided matching: the homography model's matches found again where its first fit predicts them."""

import math

import pytest
import torch

from lensdist_torch.calibration.matches import PlanarMatches
from lensdist_torch.calibration.planar_features import self_calibrate_planar
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.geometry.distortion import distort_points
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.radial_lens import lens_ideal_points

pytest.importorskip("pycolmap")
from lensdist_torch.calibration.guided_matching import chain_views, guided_matches  # noqa: E402

SIZE = (240, 320)
K2 = 4e-6  # eq. 4's k2 (about 13 px of Delta at the corners of 320 x 240)


def _similarity(angle: float, scale: float, tx: float, ty: float) -> torch.Tensor:
    c, s = scale * math.cos(angle), scale * math.sin(angle)
    return torch.tensor([[c, -s, tx], [s, c, ty], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _apply(m: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    q = p @ m[:, :2].T + m[:, 2]
    return q[:, :2] / q[:, 2:]


def _views(n_views: int = 4, period: float = 14.0, noise: float = 0.05, seed: int = 0):
    """A tiled plane (4 descriptors repeated every ``period`` px: a chessboard's look-alikes) seen through eq. 4's lens.

    Returns per view (distorted keypoints, descriptors), the views' homographies (the plane to each
    view's ideal pixels) and, per keypoint, the index of its plane point.
    """
    h, w = SIZE
    g = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.arange(-60.0, h + 60, period, dtype=torch.float64),
                            torch.arange(-60.0, w + 60, period, dtype=torch.float64), indexing="ij")
    plane = torch.stack([xs.reshape(-1), ys.reshape(-1)], 1)
    tile = ((xs / period).round().long() % 2 + 2 * ((ys / period).round().long() % 2)).reshape(-1)
    kinds = torch.nn.functional.normalize(torch.randn(4, 128, generator=g), dim=1)
    centre = ((w - 1) / 2, (h - 1) / 2)
    feats, homs, ids = [], [], []
    for v in range(n_views):
        m = _similarity(0.02 * v, 1 + 0.02 * v, 9.0 * v, -5.0 * v)
        ideal = _apply(m, plane)
        dist = distort_points(ideal[None], K2, 0.0, centre)[0] + noise * torch.randn(
            len(plane), 2, generator=g, dtype=torch.float64
        )
        inside = (dist[:, 0] >= 0) & (dist[:, 0] <= w - 1) & (dist[:, 1] >= 0) & (dist[:, 1] <= h - 1)
        desc = torch.nn.functional.normalize(kinds[tile] + 0.05 * torch.randn(len(plane), 128, generator=g), dim=1)
        feats.append((dist[inside], desc[inside]))
        homs.append(m)
        ids.append(inside.nonzero()[:, 0])
    return feats, homs, ids


def _verified(feats, ids, pairs, good: int = 20, wrong: int = 40, seed: int = 1) -> PlanarMatches:
    """Verified matches as a matcher leaves them on repetitive texture: ``good`` right, ``wrong`` to look-alikes."""
    g = torch.Generator().manual_seed(seed)
    x1, x2, pair, first, second = [], [], [], [], []
    for i, j in pairs:
        common = torch.tensor(sorted(set(ids[i].tolist()) & set(ids[j].tolist())))
        pick = common[torch.randperm(len(common), generator=g)[:good]]
        a = torch.searchsorted(ids[i], pick)
        b = torch.searchsorted(ids[j], pick)
        bad_a = torch.randint(len(ids[i]), (wrong,), generator=g)
        bad_b = torch.randint(len(ids[j]), (wrong,), generator=g)
        x1.append(torch.cat([feats[i][0][a], feats[i][0][bad_a]]))
        x2.append(torch.cat([feats[j][0][b], feats[j][0][bad_b]]))
        pair.append(torch.full((good + wrong,), len(first)))
        first.append(i)
        second.append(j)
    return PlanarMatches(torch.cat(x1), torch.cat(x2), torch.cat(pair), torch.tensor(first), torch.tensor(second),
                         tuple(f"v{k}.png" for k in range(len(feats))))


def _lens():
    """eq. 4's K2 as the homography model's a_1 (about the frame centre)."""
    return [K2 * half_diagonal(*SIZE) ** 2]


def test_chain_views_recovers_a_pair_whose_own_matches_failed():
    feats, homs, ids = _views()
    verified = _verified(feats, ids, [(0, 1), (1, 2), (2, 3)], good=30, wrong=0)
    wrong = _verified(feats, ids, [(0, 3)], good=0, wrong=40, seed=5)  # only look-alikes: no homography counts
    both = PlanarMatches(
        torch.cat([verified.x1, wrong.x1]),
        torch.cat([verified.x2, wrong.x2]),
        torch.cat([verified.pair, wrong.pair + 3]),
        torch.tensor([0, 1, 2, 0]),
        torch.tensor([1, 2, 3, 3]),
        verified.names,
    )
    pairs, views = chain_views(both, _lens(), centre=None, size=SIZE)
    assert set(pairs) == {(0, 1), (1, 2), (2, 3)} and sorted(views) == [0, 1, 2, 3]
    chained = torch.linalg.inv(views[3]) @ views[0]
    truth = homs[3] @ torch.linalg.inv(homs[0])  # view 0's ideal pixels to view 3's
    p = torch.tensor([[20.0, 30.0], [300.0, 200.0], [160.0, 120.0]], dtype=torch.float64)
    # three chained pairs of 30 matches with 0.05 px of noise: well inside the 3 px radius (the pair moves by 30 px)
    assert (_apply(chained, p) - _apply(truth, p)).norm(dim=-1).max() < 0.5


def test_guided_matches_find_the_true_partners_among_look_alikes(planar_constant):
    feats, homs, ids = _views()
    pairs = [(0, 1), (1, 2), (2, 3), (0, 2)]
    verified = _verified(feats, ids, pairs)  # a third right, the rest look-alikes
    out = guided_matches(feats, verified, _lens(), centre=None, size=SIZE)
    assert len(out.first) == len(pairs)
    for p, (i, j) in enumerate(pairs):
        sel = out.pair == p
        # each guided match: the same plane point in both views (their ideal points one homography apart)
        u1 = lens_ideal_points(out.x1[sel], _lens(), *SIZE)
        u2 = lens_ideal_points(out.x2[sel], _lens(), *SIZE)
        err = (_apply(homs[j] @ torch.linalg.inv(homs[i]), u1) - u2).norm(dim=-1)
        assert float(err.max()) < 0.5
        common = len(set(ids[i].tolist()) & set(ids[j].tolist()))
        assert int(sel.sum()) >= 0.9 * common  # nearly every shared point, where the matcher kept 20
    # a look-alike at the next tile (14 px) is never within the 3 px radius; a radius over the period admits them
    planar_constant("PLANAR_GUIDED_PX", 30.0)
    wide = guided_matches(feats, verified, _lens(), centre=None, size=SIZE)
    assert len(wide.pair) < 0.1 * len(out.pair)  # the ratio test rejects the look-alikes' ties


def test_the_plane_test_can_be_carried_over(planar_constant):
    """``plane_share``: guided matches cannot say whether the scene is a plane; the first fit's share decides."""
    feats, homs, ids = _views(n_views=5)
    verified = _verified(feats, ids, [(i, j) for i in range(5) for j in range(i + 1, 5)], good=40, wrong=0)
    found = guided_matches(feats, verified, _lens(), centre=None, size=SIZE)
    planar_constant("PLANAR_CENTRE_MAX", 0.0)
    cfg = MultiViewConfig(planar_terms=2)
    plain = self_calibrate_planar(found, SIZE, config=cfg)
    carried = self_calibrate_planar(found, SIZE, config=cfg, start=_lens(), plane_share=0.3)
    assert plain.inlier_share > 0.9 and plain.class_label is not None
    assert carried.inlier_share == 0.3 and carried.class_label is None and carried.reason.startswith("not a plane: ")
    assert carried.delta_avg_user_px == pytest.approx(
        plain.delta_avg_user_px, rel=1e-3
    )  # from the lens, not the scan: same fit


def _stub_database(monkeypatch, verified: PlanarMatches, feats: list, keep_pairs: int | None = None):
    """``self_calibrate_guided`` reading ``verified`` and ``feats`` instead of a COLMAP database; with
    ``keep_pairs``, the guided matches cut to that many pairs."""
    import lensdist_torch.calibration.guided_matching as gm

    monkeypatch.setattr(gm, "read_verified_matches", lambda database, names, min_matches=15: verified)
    monkeypatch.setattr(gm, "read_features", lambda database, names: feats)
    if keep_pairs is not None:
        real = gm.guided_matches

        def fewer(*args, **kwargs):
            m = real(*args, **kwargs)
            sel = m.pair < keep_pairs
            return PlanarMatches(
                m.x1[sel], m.x2[sel], m.pair[sel], m.first[:keep_pairs], m.second[:keep_pairs], m.names
            )

        monkeypatch.setattr(gm, "guided_matches", fewer)


@pytest.mark.slow
def test_guided_matches_answer_only_where_they_bring_pairs_back(monkeypatch, planar_constant):
    """Five views, 10 verified pairs: the 4 of neighbours with 14 right matches among 20 look-alikes, the
    others with 5 right among 40 (too few for a homography: they do not count in the first fit)."""
    from lensdist_torch.calibration.guided_matching import self_calibrate_guided

    feats, homs, ids = _views(n_views=5)
    near = _verified(feats, ids, [(i, i + 1) for i in range(4)], good=14, wrong=20)
    far = _verified(feats, ids, [(i, j) for i in range(5) for j in range(i + 2, 5)], good=5, wrong=40, seed=2)
    verified = PlanarMatches(
        torch.cat([near.x1, far.x1]),
        torch.cat([near.x2, far.x2]),
        torch.cat([near.pair, far.pair + 4]),
        torch.cat([near.first, far.first]),
        torch.cat([near.second, far.second]),
        near.names,
    )
    for name, value in (("PLANAR_CENTRE_MAX", 0.0), ("PLANAR_MIN_MATCHES", 10), ("PLANAR_MIN_INLIER_SHARE", 0.2)):
        planar_constant(name, value)
    cfg = MultiViewConfig(planar_terms=2)
    _stub_database(monkeypatch, verified, feats)
    res = self_calibrate_guided("db", list(verified.names), SIZE, config=cfg)
    first = res.guided["first_fit"]
    assert res.guided["used"] and res.pairs > first["pairs"] and res.guided["pairs_verified"] == 10
    assert first["pairs"] < 0.5 * 10  # why it ran: under PLANAR_GUIDED_BELOW of the verified pairs counted
    lo, hi = res.delta_avg_user_interval
    assert lo <= res.delta_avg_user_px <= hi and (hi - lo) < (
        first["delta_avg_user_interval"][1] - first["delta_avg_user_interval"][0]
    )
    # guided matches that count fewer pairs than the first fit: the first fit stands, and says why
    _stub_database(monkeypatch, verified, feats, keep_pairs=first["pairs"])
    fewer = self_calibrate_guided("db", list(verified.names), SIZE, config=cfg)
    assert not fewer.guided["used"] and fewer.guided["reason"].startswith("the guided matches count ")
    assert fewer.delta_avg_user_px == pytest.approx(first["delta_avg_user_px"], rel=1e-6)
    # most verified pairs counted: no guided matching at all
    planar_constant("PLANAR_GUIDED_BELOW", 0.1)
    assert self_calibrate_guided("db", list(verified.names), SIZE, config=cfg).guided is None
