"""The homography model's lens models weighed by held-out pairs: the held lens, the posterior, the folds."""

import math

import pytest
import torch

from lensdist_torch.calibration.matches import PlanarMatches
from lensdist_torch.calibration.multiview_evidence import fold_ranges
from lensdist_torch.calibration.planar_evidence import score_models
from lensdist_torch.calibration.planar_model import (
    fit_lens_and_homographies,
    lens_covariance,
    lens_deltas,
    transfer_jacobians,
    transfer_residuals,
)
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.opencv_model import map_grid_step

SIZE = (120, 160)
F64 = {"dtype": torch.float64}


def _views(theta, *, views=5, points=80, noise=0.002, seed=0):
    """Matches between ``views`` views of a plane through the lens ``theta`` (normalised frame), every pair.

    Returns (v1, v2, pair, first, second, homographies (P, 8) of the ideal points, the frames' ideal points).
    """
    g = torch.Generator().manual_seed(seed)
    ideal = torch.rand(points, 2, generator=g, **F64) * 1.2 - 0.6
    hs_view = [torch.eye(3, **F64)]
    for _ in range(views - 1):  # a turn of up to 0.3 rad, a scale of 15 %, a shift of 0.25 R and some perspective
        u = torch.rand(6, generator=g, **F64) * 2 - 1
        ang, sc = 0.3 * u[0], 1 + 0.15 * u[1]
        hs_view.append(torch.tensor([[sc * math.cos(ang), -sc * math.sin(ang), 0.25 * u[2]],
                                     [sc * math.sin(ang), sc * math.cos(ang), 0.25 * u[3]],
                                     [0.1 * u[4], 0.1 * u[5], 1.0]], **F64))
    seen = []
    for m in hs_view:
        q = ideal @ m[:, :2].T + m[:, 2]
        u = q[:, :2] / q[:, 2:]
        # the distorted point: invert the lens map u = v (1 + a1 |v|^2 + ...) by fixed-point iteration
        v = u.clone()
        for _ in range(60):
            s = (v * v).sum(-1, keepdim=True)
            v = u / (1 + sum(a * s ** (k + 1) for k, a in enumerate(theta.tolist())))
        seen.append(v + noise * torch.randn(v.shape, generator=g, **F64))
    v1, v2, pair, first, second, hs = [], [], [], [], [], []
    for i in range(views):
        for j in range(i + 1, views):
            v1.append(seen[i])
            v2.append(seen[j])
            pair.append(torch.full((points,), len(first)))
            first.append(i)
            second.append(j)
            h = hs_view[j] @ torch.linalg.inv(hs_view[i])
            hs.append((h / h[2, 2]).reshape(-1)[:8])
    return (torch.cat(v1), torch.cat(v2), torch.cat(pair), torch.tensor(first), torch.tensor(second),
            torch.stack(hs))


def test_the_folds_cover_every_frame_once_in_order():
    for n, b in ((12, 6), (7, 6), (3, 6), (22, 5)):
        blocks = fold_ranges(n, b)
        assert len(blocks) == min(n, b) and all(len(r) >= 1 for r in blocks)
        assert [i for r in blocks for i in r] == list(range(n))


def test_a_held_lens_moves_only_the_weighted_pairs_homographies():
    theta = torch.tensor([0.08, -0.01], **F64)
    v1, v2, pair, _, _, hs = _views(theta, noise=0.0)
    start = hs + 0.002 * torch.randn(hs.shape, generator=torch.Generator().manual_seed(1), **F64)
    w = (pair < 3).double()  # pairs 0-2 weighted, the others left out
    a, h = fit_lens_and_homographies(theta.clone(), start.clone(), v1, v2, pair=pair, w=w, iterations=50,
                                     lens_held=True)
    assert torch.equal(a, theta)
    assert torch.equal(h[3:], start[3:])
    assert torch.allclose(h[:3], hs[:3], atol=1e-8)  # the true homographies: noise-free matches, the true lens


def test_the_lens_covariance_is_the_full_normal_equations_inverse():
    """The Schur complement's inverse against the dense (lens + every homography) normal matrix, inverted whole."""
    theta = torch.tensor([0.08, -0.01, 0.02, -0.01], **F64)  # two terms and a free centre
    v1, v2, pair, _, _, hs = _views(torch.tensor([0.08, -0.01], **F64))
    w = torch.ones(len(pair), **F64)
    a, h = fit_lens_and_homographies(theta, hs.clone(), v1, v2, pair=pair, w=w, iterations=100, terms=2)
    cov = lens_covariance(a, h, v1, v2, pair=pair, w=w, terms=2)
    ja, jh = transfer_jacobians(a, h, v1, v2, terms=2, pair=pair)
    n, n_pairs = a.numel(), h.shape[0]
    dense = torch.zeros(len(pair) * 4, n + 8 * n_pairs, **F64)
    rows = torch.arange(len(pair) * 4).reshape(-1, 4)
    dense[rows.reshape(-1), :n] = ja.reshape(-1, n)
    for k in range(len(pair)):
        dense[rows[k], n + 8 * pair[k]:n + 8 * pair[k] + 8] = jh[k]
    r = transfer_residuals(a, h, v1, v2, terms=2, pair=pair)
    sigma2 = float((r * r).sum()) / (2 * len(pair) - 8 * n_pairs - n)  # two residuals of four per misfit
    want = sigma2 * torch.linalg.inv(dense.T @ dense)[:n, :n]
    assert torch.allclose(cov, want, rtol=1e-6, atol=0)
    # the noise's scale (the centre fixed): ten times the noise, a hundred times the variance, to the fit's order
    covs = []
    for noise in (0.001, 0.01):
        v1b, v2b, _, _, _, _ = _views(torch.tensor([0.08, -0.01], **F64), noise=noise)
        a2, h2 = fit_lens_and_homographies(theta[:2], hs.clone(), v1b, v2b, pair=pair, w=w, iterations=100)
        covs.append(torch.diagonal(lens_covariance(a2, h2, v1b, v2b, pair=pair, w=w)))
    assert bool(((covs[1] / covs[0] > 80) & (covs[1] / covs[0] < 125)).all())


def test_a_singular_fit_has_no_covariance():
    v1, v2, pair, _, _, hs = _views(torch.tensor([0.08], **F64))
    w = torch.zeros(len(pair), **F64)
    w[:4] = 1.0  # four matches of one pair: 8 misfit coordinates for 8 homography entries and the lens
    assert lens_covariance(torch.tensor([0.08], **F64), hs, v1, v2, pair=pair, w=w) is None


@pytest.fixture(scope="module")
def scored():
    theta = torch.tensor([0.1, -0.02], **F64)
    v1, v2, pair, first, second, hs = _views(theta, views=6, points=60, noise=0.002)
    step = map_grid_step(*SIZE)
    inl = torch.ones(len(pair), dtype=torch.bool)
    fits = {}
    starts = {"planar-1": (theta[:1], 1), "planar-2": (theta, 2), "planar-2-centre": (torch.cat([theta, 0 * theta]), 2)}
    for name, (start, n) in starts.items():
        t, h = fit_lens_and_homographies(start.clone(), hs.clone(), v1, v2, pair=pair, w=inl.double(), iterations=100,
                                         terms=n)
        fits[name] = (t, h, lens_deltas(t, n, SIZE, step), n)
    matches = PlanarMatches(v1, v2, pair, first, second, tuple(f"{i}.png" for i in range(6)))
    scores, answer = score_models(fits, matches, v1, v2, inliers=inl, blocks=3, size=SIZE, step=step, iterations=100,
                                  confidence=0.95, stays=lambda t, n: True)
    return theta, fits, scores, answer


def test_held_out_pairs_weigh_the_lens_that_made_them(scored):
    theta, fits, scores, answer = scored
    big_r = half_diagonal(*SIZE)
    # one term cannot bend as the two-term lens did: it predicts held-out pairs worse, and takes no weight
    assert scores["planar-1"]["weight"] < 1e-3
    assert scores["planar-2"]["weight"] + scores["planar-2-centre"]["weight"] == pytest.approx(1.0, abs=1e-3)
    # the true models predict held-out pairs to the noise: 0.002 of R per coordinate at each end of a match
    for m in ("planar-2", "planar-2-centre"):
        assert scores[m]["heldout_rms_px"] == pytest.approx(0.002 * math.sqrt(2) * big_r, rel=0.1)
        assert len(scores[m]["jackknife_thetas"]) == 3 and scores[m]["jackknife_std_px"] > 0
    # the interval holds the true lens's Delta_avg and the jackknife checks the posterior: dispersion near 1
    truth = lens_deltas(theta, 2, SIZE, map_grid_step(*SIZE))["delta_avg_px"]
    lo, hi = answer["intervals"][0]
    assert lo <= truth <= hi and hi - lo < 0.3 * truth
    assert 1.0 <= answer["dispersion"] < 10
    assert math.isfinite(scores["planar-2"]["delta_avg_std_px"]) and scores["planar-2"]["covariance"] is not None
    assert len(scores["planar-2-centre"]["covariance"]) == 4


def test_a_model_whose_folds_stray_is_no_candidate(scored):
    _, fits, _, _ = scored
    v1, v2, pair, first, second, _ = _views(torch.tensor([0.1, -0.02], **F64), views=6, points=60)
    inl = torch.ones(len(pair), dtype=torch.bool)
    matches = PlanarMatches(v1, v2, pair, first, second, tuple(f"{i}.png" for i in range(6)))
    scores, _ = score_models(fits, matches, v1, v2, inliers=inl, blocks=3, size=SIZE, step=map_grid_step(*SIZE),
                             iterations=100, confidence=0.95, stays=lambda t, n: t.numel() == n)  # free centres stray
    assert set(scores) == {"planar-1", "planar-2"}


@pytest.mark.parametrize("step,radius", [(1, 3.0), (5, 28.6), (8, 7.5)])
def test_grid_near_is_the_distance_matrix_rule(step, radius):
    """The bending check's "within the radius of a match", exact: the same mask as the nearest distance."""
    from lensdist_torch.geometry.frame import grid_near, grid_points

    h, w = 61, 97
    g = torch.Generator().manual_seed(step)
    pts = torch.rand(300, 2, generator=g, **F64) * torch.tensor([w + 10.0, h + 10.0]) - 5.0  # some off the frame
    want = torch.cdist(grid_points(h, w, step), pts).amin(1) <= radius
    assert torch.equal(grid_near(pts, h, w, step=step, radius=radius), want)
