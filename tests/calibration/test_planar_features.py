"""The homography model: a lens and one homography per pair fitted to feature matches between views of a plane."""

import math

import pytest
import torch

from lensdist_torch.calibration.matches import PlanarMatches
from lensdist_torch.calibration.planar_features import self_calibrate_planar
from lensdist_torch.calibration.planar_model import _adjugate, transfer_jacobians, transfer_residuals
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.geometry.distortion import delta_avg, delta_max, distort_points, undistort_points
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.radial_lens import lens_ideal_points

pytest.importorskip("pycolmap")

SIZE = (240, 320)


def _homography(rng: torch.Generator, h: int, w: int, shift: float) -> torch.Tensor:
    """A view of the plane: a similarity about the centre, a shift of up to ``shift`` px and a little perspective."""
    u = torch.rand(6, generator=rng, dtype=torch.float64) * 2 - 1
    ang, s = 0.15 * u[0], 1 + 0.1 * u[1]
    m = torch.tensor([[s * math.cos(ang), -s * math.sin(ang), shift * u[2]],
                      [s * math.sin(ang), s * math.cos(ang), shift * u[3]],
                      [3e-4 * u[4], 3e-4 * u[5], 1.0]], dtype=torch.float64)
    c = torch.tensor([[1, 0, (w - 1) / 2], [0, 1, (h - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    return c @ m @ torch.linalg.inv(c)


def _apply(m: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    q = p @ m[:, :2].T + m[:, 2]
    return q[:, :2] / q[:, 2:]


def _plane_matches(k2: float, k4: float, views: int = 8, noise: float = 0.3, outliers: float = 0.2, seed: int = 0,
                   depth: float = 0.0, offset: tuple[float, float] = (0.0, 0.0)) -> PlanarMatches:
    """Every pair of ``views`` views of a textured plane through eq. 4's lens (k2, k4), as matches.

    ``noise`` px of Gaussian noise on every point, ``outliers`` of the matches moved anywhere in the
    frame; ``depth`` > 0 gives the points depths 1 .. 1 + depth and moves the camera sideways
    instead (parallax: no homography explains a pair); ``offset`` (px) moves the lens's centre off the frame's.
    """
    h, w = SIZE
    rng = torch.Generator().manual_seed(seed)
    base = torch.rand(400, 2, generator=rng, dtype=torch.float64) * torch.tensor([w * 1.4, h * 1.4]) - torch.tensor(
        [0.2 * w, 0.2 * h]
    )
    z = 1 + depth * torch.rand(400, generator=rng, dtype=torch.float64)
    centre = ((w - 1) / 2 + offset[0], (h - 1) / 2 + offset[1])
    seen = []
    for i in range(views):
        if depth:  # a camera moving sideways over a scene of varied depth
            ideal = base + torch.tensor([12.0 * i, 4.0 * i], dtype=torch.float64) / z[:, None] * 3
        else:
            ideal = _apply(_homography(rng, h, w, 40.0), base)
        dist = distort_points(ideal[None], k2, k4, centre)[0]
        inside = (dist[:, 0] >= 0) & (dist[:, 0] <= w - 1) & (dist[:, 1] >= 0) & (dist[:, 1] <= h - 1)
        seen.append((dist + noise * torch.randn(dist.shape, generator=rng, dtype=torch.float64), inside))
    x1, x2, pair, first, second = [], [], [], [], []
    for i in range(views):
        for j in range(i + 1, views):
            both = seen[i][1] & seen[j][1]
            a, b = seen[i][0][both], seen[j][0][both].clone()
            wrong = torch.rand(len(b), generator=rng) < outliers
            b[wrong] = torch.rand(int(wrong.sum()), 2, generator=rng, dtype=torch.float64) * torch.tensor(
                [w - 1.0, h - 1.0]
            )
            x1.append(a)
            x2.append(b)
            pair.append(torch.full((len(a),), len(first)))
            first.append(i)
            second.append(j)
    return PlanarMatches(torch.cat(x1), torch.cat(x2), torch.cat(pair), torch.tensor(first), torch.tensor(second),
                         tuple(f"frame_{i}.png" for i in range(views)))


def test_the_lens_with_two_terms_is_eq4():
    h, w = SIZE
    r = half_diagonal(h, w)
    k2, k4 = 2e-6, -3e-12
    p = torch.rand(50, 2, dtype=torch.float64) * torch.tensor([w - 1.0, h - 1.0])
    ours = lens_ideal_points(p, [k2 * r**2, k4 * r**4], h, w)
    eq4 = undistort_points(p[None], k2, k4, ((w - 1) / 2, (h - 1) / 2))[0]
    assert torch.allclose(ours, eq4, atol=1e-10)


def test_adjugate_is_the_inverse_times_the_determinant():
    m = torch.tensor([[1.2, 0.1, 3.0], [-0.2, 0.9, -1.0], [1e-3, 2e-3, 1.0]], dtype=torch.float64)
    assert torch.allclose(_adjugate(m), torch.linalg.inv(m) * torch.linalg.det(m), atol=1e-12)


@pytest.mark.parametrize("theta", [[0.1, -0.02, 0.01], [0.1, -0.02, 0.01, 0.03, -0.02]])  # the centre fixed, free
def test_jacobian_agrees_with_finite_differences(theta):
    a = torch.tensor(theta, dtype=torch.float64)
    h = torch.tensor([1.01, 0.02, 0.05, -0.01, 0.98, -0.03, 0.02, -0.01], dtype=torch.float64)[None].repeat(5, 1)
    v1 = torch.rand(5, 2, dtype=torch.float64) - 0.5
    v2 = v1 + 0.03
    ja, jh = transfer_jacobians(a, h, v1, v2, terms=3)
    assert ja.shape == (5, 4, len(theta))
    eps = 1e-7
    for k in range(len(theta)):
        d = torch.zeros(len(theta), dtype=torch.float64)
        d[k] = eps
        fd = (transfer_residuals(a + d, h, v1, v2, terms=3) - transfer_residuals(a - d, h, v1, v2, terms=3)) / (2 * eps)
        assert torch.allclose(ja[..., k], fd, atol=1e-6)
    for k in range(8):
        d = torch.zeros(8, dtype=torch.float64)
        d[k] = eps
        fd = (transfer_residuals(a, h + d, v1, v2, terms=3) - transfer_residuals(a, h - d, v1, v2, terms=3)) / (2 * eps)
        assert torch.allclose(jh[..., k], fd, atol=1e-6)
    # forward-mode AD of the residual, one tangent per parameter: the closed form to rounding
    def along(da, dh):
        return torch.func.jvp(lambda a_, h_: transfer_residuals(a_, h_, v1, v2, terms=3), (a, h), (da, dh))[1]

    n = len(theta)
    tangents = (torch.cat([torch.eye(n, dtype=a.dtype), a.new_zeros(8, n)]),
                torch.cat([h.new_zeros(n, 5, 8), torch.eye(8, dtype=h.dtype)[:, None, :].expand(8, 5, 8)]))
    ad = torch.func.vmap(along)(*tangents)
    assert torch.allclose(ja, ad[:n].permute(1, 2, 0), atol=1e-12)
    assert torch.allclose(jh, ad[n:].permute(1, 2, 0), atol=1e-12)
    # the pairs' homographies once each, indexed by pair: the same residuals and derivatives
    pair = torch.tensor([0, 1, 1, 0, 1])
    hp = torch.stack([h[0], h[0] + 0.01])
    assert torch.allclose(
        transfer_residuals(a, hp, v1, v2, terms=3, pair=pair),
        transfer_residuals(a, hp[pair], v1, v2, terms=3),
        atol=1e-14,
    )
    for got, want in zip(
        transfer_jacobians(a, hp, v1, v2, terms=3, pair=pair), transfer_jacobians(a, hp[pair], v1, v2, terms=3)
    ):
        assert torch.allclose(got, want, atol=1e-12)


# the third lens is 10.5 px at the paper's frame, 0.3 px under class 4: its interval there spans classes 3 and 4
@pytest.mark.parametrize("k2,k4,cls", [(2.5e-6, 0.0, "2"), (-2e-6, 0.0, "2"), (4e-6, 2e-11, None)])
def test_recovers_a_known_lens_from_noisy_matches_with_outliers(k2, k4, cls):
    h, w = SIZE
    res = self_calibrate_planar(_plane_matches(k2, k4), SIZE, config=MultiViewConfig(planar_terms=2))
    truth = float(delta_avg([k2], [k4], h, w)[0])
    lo, hi = res.delta_avg_user_interval
    assert abs(res.delta_avg_user_px - truth) < 0.03 * truth
    assert lo <= truth <= hi
    truth_max = float(delta_max([k2], [k4], h, w)[0])
    lo, hi = res.delta_max_user_interval
    assert lo <= truth_max <= hi
    assert res.class_label == cls and (res.reason == "" if cls else res.reason.endswith("spans classes 3 and 4"))
    # 20 % of the matches were moved anywhere: the inliers are the others
    assert 0.7 < res.inliers / res.matches < 0.85
    assert res.opencv["fit_error_mean_px"] < 0.1
    # the lens's centre is the frame's: a free centre predicts held-out pairs no better, so the centred model of
    # the answer's terms keeps a share of the weight (or all of it), and its Delta_max is the truth's
    centred = res.models[f"planar-{res.terms}"]
    assert centred["weight"] > 0.2
    assert centred["delta_max_px"] == pytest.approx(truth_max, rel=0.05)
    # lines come out straight to half a pixel, or to the few pixels the folds move a free centre by
    assert res.bending_halfwidth_px < (3.0 if res.model.endswith("-centre") else 0.5) and res.matched_fraction > 0.9


def _bending(p: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> float:
    """RMS (px) of what remains of y - x after the best affine map from x to y."""
    design = torch.cat([x, torch.ones(len(x), 1, dtype=x.dtype)], 1)
    return float((y - design @ torch.linalg.lstsq(design, y).solution).norm(dim=-1).pow(2).mean().sqrt())


def test_a_lens_off_the_frame_centre_is_found_with_its_centre(planar_constant):
    # a strong lens (Delta_avg 9 px at 240 x 320) centred 12 px right of and 8 px above the frame's centre
    h, w = SIZE
    k2, off = 6e-6, (12.0, -8.0)
    res = self_calibrate_planar(_plane_matches(k2, 0.0, offset=off), SIZE, config=MultiViewConfig(planar_terms=2))
    centre = ((w - 1) / 2 + off[0], (h - 1) / 2 + off[1])
    assert res.model.endswith("-centre") and res.class_label is not None
    assert math.dist(res.centre, centre) < 2.5  # 1.9 px off (0.3 px noise, 8 views)
    p = torch.stack(
        torch.meshgrid(
            torch.arange(0.0, w, 8, dtype=torch.float64), torch.arange(0.0, h, 8, dtype=torch.float64), indexing="xy"
        ),
        -1,
    ).reshape(-1, 2)
    truth = undistort_points(p[None], k2, 0.0, centre)[0]
    ours = lens_ideal_points(p, res.coefficients, h, w, centre=res.centre)
    bent = _bending(p, truth, ours)  # 0.26 px: lines as straight as the true lens makes them, to a quarter pixel
    assert bent < 0.3 and bent < res.bending_halfwidth_px  # and its own half-width (0.49) covers that
    assert abs(res.delta_avg_user_px - float((truth - p).norm(dim=-1).mean())) < 0.03 * float(
        (truth - p).norm(dim=-1).mean()
    )
    # the frame-centred model cannot follow it: 2.1 px of bending (BIC prefers the free centre by 589)
    planar_constant("PLANAR_CENTRE_MAX", 0.0)
    fixed = self_calibrate_planar(_plane_matches(k2, 0.0, offset=off), SIZE, config=MultiViewConfig(planar_terms=2))
    assert _bending(p, truth, lens_ideal_points(p, fixed.coefficients, h, w)) > 5 * _bending(p, truth, ours)
    # OpenCV's camera about the same centre
    assert res.opencv["camera_matrix"][0][2] == pytest.approx(res.centre[0]) and res.opencv["fit_error_mean_px"] < 0.1


def test_no_distortion_gives_a_small_delta_and_no_class_where_the_interval_spans_the_threshold():
    res = self_calibrate_planar(_plane_matches(0.0, 0.0), SIZE, config=MultiViewConfig(planar_terms=2))
    assert (
        res.delta_avg_user_px < 0.2 and res.delta_avg_user_interval[0] == 0.0
    )  # 0.17 (60 matches a pair kept of ~300)
    # the interval starts at 0 and reaches past 0.25 px at the paper's frame: R or class 1 cannot be told
    assert res.class_label is None and "spans the no-distortion threshold (0.25 px)" in res.reason


def test_a_scene_with_depth_is_not_a_plane():
    # depths 1 .. 2 (or 1 .. 3) under a camera moving sideways: a homography fits a band of depths, about 30 %
    # of a pair's matches, where a plane keeps all but its outliers (80 % here, 61 % on the GoPro's chessboard)
    for depth in (1.0, 2.0):
        res = self_calibrate_planar(
            _plane_matches(2e-6, 0.0, depth=depth, outliers=0.0), SIZE, config=MultiViewConfig(planar_terms=2)
        )
        assert res.class_label is None and res.inlier_share < 0.4
        assert res.reason.startswith("not a plane: one homography per pair explains"), res.reason
    plane = self_calibrate_planar(_plane_matches(2e-6, 0.0), SIZE, config=MultiViewConfig(planar_terms=2))
    assert plane.inlier_share > 0.75


def test_too_few_pairs_say_so():
    m = _plane_matches(2e-6, 0.0, views=3)
    res = self_calibrate_planar(m, SIZE, config=MultiViewConfig())
    assert res.class_label is None and math.isnan(res.delta_avg_user_px)
    assert res.reason == "too few matched pairs: 3 of at least 4"


def test_bending_halfwidth_is_the_jackknife_of_what_no_affine_map_takes_away():
    from lensdist_torch.calibration.planar_model import bending_halfwidth, lens_deltas

    h, w = SIZE
    theta = torch.tensor([0.2, 0.05], dtype=torch.float64)
    dl = lens_deltas(theta, 2, SIZE, 8)
    seen = dl["points"]  # matches everywhere: every monotone pixel counts
    same, _ = bending_halfwidth(theta, [theta, theta.clone()], n=2, size=SIZE, dl=dl, confidence=0.95, seen=seen)
    assert same < 1e-9
    # two replicates, one the answer, one with a_1 0.01 larger: t(1) sqrt(1/2 m), m its mean squared bending
    other = torch.tensor([0.21, 0.05], dtype=torch.float64)
    got, share = bending_halfwidth(theta, [theta, other], n=2, size=SIZE, dl=dl, confidence=0.95, seen=seen)
    p = dl["points"][dl["ok"]]
    m = _bending(p, lens_ideal_points(p, [0.2, 0.05], h, w), lens_ideal_points(p, [0.21, 0.05], h, w)) ** 2
    assert got == pytest.approx(12.7062047 * math.sqrt(0.5 * m), rel=1e-6) and share == pytest.approx(
        float(dl["ok"].double().mean())
    )
    # pixels no match comes near do not count
    corner = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    _, few = bending_halfwidth(theta, [theta, other], n=2, size=SIZE, dl=dl, confidence=0.95, seen=corner)
    assert few < 0.02


def test_thinning_keeps_every_pair_evenly_and_the_answer(planar_constant):
    from lensdist_torch.calibration.matches import thin_matches

    m = _plane_matches(4e-6, 2e-11)
    counts = torch.bincount(m.pair)
    thin = thin_matches(m, 40)
    got = torch.bincount(thin.pair)
    assert torch.equal(got, counts.clamp(max=40)) and thin_matches(m, 0) is m
    # every kept match is one of the pair's own, and none twice
    assert len(torch.cat([thin.x1, thin.x2], 1).unique(dim=0)) == len(thin.pair)
    planar_constant("PLANAR_PAIR_MATCHES", 0)
    full = self_calibrate_planar(m, SIZE, config=MultiViewConfig(planar_terms=2))
    planar_constant("PLANAR_PAIR_MATCHES", 40)
    fewer = self_calibrate_planar(m, SIZE, config=MultiViewConfig(planar_terms=2))
    lo, hi = fewer.delta_avg_user_interval
    assert lo <= full.delta_avg_user_px <= hi and fewer.matches == int(got.sum()) < full.matches
