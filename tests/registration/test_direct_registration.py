"""Tests of lensdist_torch.registration: homography estimation, warping, class-R perturbation."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lensdist_torch.core.images import load_scene
from lensdist_torch.registration import direct
from lensdist_torch.registration.direct import (
    RegistrationConfig,
    corner_error,
    estimate_homography,
    match_intensity,
    perturb_homography,
    warp_to_reference,
)

H0, W0 = 320, 424  # the analysis size (docs/method.md, section 1)


def _translation(x: float, y: float) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], dtype=torch.float64)


def _apply(m: torch.Tensor, x: torch.Tensor, y: torch.Tensor):
    q = m @ torch.stack([x, y, torch.ones_like(x)])
    return q[0] / q[2], q[1] / q[2]


def _motion(g: torch.Generator, h: int, w: int) -> torch.Tensor:
    """Section 7's M = T(p0) A T(-p0), I2's coordinates -> I1's."""

    def u(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))

    ty, tx, th, s = u(0, 40), u(-4, 4), math.radians(u(-1, 1)), u(0.98, 1.02)
    a = torch.tensor([[s * math.cos(th), -s * math.sin(th), tx], [s * math.sin(th), s * math.cos(th), ty],
                      [u(-2e-5, 2e-5), u(-2e-5, 2e-5), 1.0]], dtype=torch.float64)
    return _translation((w - 1) / 2, (h - 1) / 2) @ a @ _translation(-(w - 1) / 2, -(h - 1) / 2)


def _distortion(h: int, w: int, k2: float, k4: float):
    """Section 6: the ideal point p of every pixel p_d, as flat x, y (float64)."""
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    dx, dy = x.flatten() - (w - 1) / 2, y.flatten() - (h - 1) / 2
    f = 1 + k2 * (dx * dx + dy * dy) + k4 * (dx * dx + dy * dy) ** 2
    return (w - 1) / 2 + f * dx, (h - 1) / 2 + f * dy


def make_pairs(n: int, h: int = H0, w: int = W0, seed: int = 0, scene: str = "gravel", distort: float = 0.0):
    """n pairs I1(p) = S(P p), I2(p) = S(P M p) (section 7), one generator per pair; returns img1,
    img2 (n, 1, h, w) and the true H = M^-1 (n, 3, 3). ``distort`` scales section 6's coefficients
    (0: undistorted)."""
    s = load_scene(scene)
    side = s.shape[-1] - 1
    i1, i2, hs = [], [], []
    for i in range(n):
        g = torch.Generator().manual_seed(1000 * seed + i)
        m = _motion(g, h, w)
        k2, k4 = (distort * c * float(torch.rand((), generator=g, dtype=torch.float64)) for c in (2.5e-6, 2.5e-11))
        x, y = _distortion(h, w, k2, k4)
        pts = [_apply(q, x, y) for q in (torch.eye(3, dtype=torch.float64), m)]
        span = max(max(float(p[k].max()) for p in pts) - min(float(p[k].min()) for p in pts) for k in (0, 1))
        z = min(1.0, 0.98 * side / span) * (0.95 + 0.05 * float(torch.rand((), generator=g)))  # the zoom of P
        lo = [-z * min(float(p[k].min()) for p in pts) for k in (0, 1)]
        hi = [side - z * max(float(p[k].max()) for p in pts) for k in (0, 1)]
        off = [a + (b - a) * float(torch.rand((), generator=g, dtype=torch.float64)) for a, b in zip(lo, hi)]
        place = torch.tensor([[z, 0, off[0]], [0, z, off[1]], [0, 0, 1]], dtype=torch.float64)
        for out, q in ((i1, place), (i2, place @ m)):
            sx, sy = _apply(q, x, y)
            grid = torch.stack([2 * sx / side - 1, 2 * sy / side - 1], -1).view(1, h, w, 2).float()
            out.append(F.grid_sample(s, grid, mode="bilinear", align_corners=True))
        hs.append(torch.linalg.inv(m))
    h_true = torch.stack(hs)
    return torch.cat(i1), torch.cat(i2), h_true / h_true[:, 2:, 2:]


pytestmark = pytest.mark.usefixtures("one_thread_module")


@pytest.fixture(scope="module")
def pairs():
    return make_pairs(24, seed=1)


# ----------------------------------------------------------------------------- estimation


def test_recovers_the_true_homography(pairs):
    img1, img2, h_true = pairs
    h, info = estimate_homography(img1, img2)
    err = corner_error(h, h_true, H0, W0)
    assert h.shape == (24, 3, 3) and h.dtype == torch.float64
    assert torch.equal(h[:, 2, 2], torch.ones(24, dtype=torch.float64))
    assert bool(info.converged.all()) and bool(info.textured.all())
    assert float(err.max()) < 0.05, err
    assert float(err.median()) < 0.01
    assert bool((info.overlap > 0.8).all()) and bool((info.residual < 0.02).all())
    assert bool((info.iterations >= 2).all())


@pytest.mark.parametrize("seed, scene", [(2, "gravel"), (3, "grass")])
def test_recovers_more_draws(seed, scene):
    img1, img2, h_true = make_pairs(8, seed=seed, scene=scene)
    h, info = estimate_homography(img1, img2)
    assert bool(info.converged.all())
    assert float(corner_error(h, h_true, H0, W0).max()) < 0.05


def test_recovers_at_a_reduced_size():
    img1, img2, h_true = make_pairs(8, 160, 216, seed=4)
    h, info = estimate_homography(img1, img2)
    assert bool(info.converged.all())
    assert float(corner_error(h, h_true, 160, 216).max()) < 0.05


def test_rgb_and_uint8_inputs(pairs):
    img1, img2, h_true = (x[:4] for x in pairs)
    h_grey, _ = estimate_homography(img1, img2)
    h_rgb, info = estimate_homography(img1.expand(-1, 3, -1, -1), img2.expand(-1, 3, -1, -1))
    assert bool(info.converged.all())
    assert float(corner_error(h_rgb, h_grey, H0, W0).max()) < 1e-3
    u8 = [(x * 255).round().to(torch.uint8) for x in (img1, img2)]
    h_u8, info = estimate_homography(*u8)
    assert bool(info.converged.all()) and float(corner_error(h_u8, h_true, H0, W0).max()) < 0.05


def test_batch_size_invariance(pairs):
    img1, img2, _ = pairs
    h_all, _ = estimate_homography(img1[:12], img2[:12])
    h_chunk, _ = estimate_homography(img1[:12], img2[:12], config=RegistrationConfig(chunk_size=5))
    for i in (0, 7, 11):
        h_one, _ = estimate_homography(img1[i : i + 1], img2[i : i + 1])
        for other in (h_all[i], h_chunk[i]):
            assert torch.allclose(other, h_one[0], rtol=1e-6, atol=1e-8), (other, h_one[0])


def test_distorted_pairs_converge():
    img1, img2, _ = make_pairs(6, seed=5, distort=1.0)  # up to section 6's strongest distortion
    _, info = estimate_homography(img1, img2)
    assert bool(info.converged.all()), info


def test_init_replaces_phase_correlation(pairs):
    img1, img2, h_true = (x[:4] for x in pairs)
    h, info = estimate_homography(img1, img2, init=h_true)
    assert bool(info.converged.all()) and float(corner_error(h, h_true, H0, W0).max()) < 0.05
    far = h_true.clone()
    far[:, 1, 2] += 25.0  # far outside the convergence basin: must not report success
    _, info = estimate_homography(img1, img2, init=far)
    assert not bool(info.converged.any())


def test_textureless_pairs_are_not_converged():
    flat = torch.full((2, 1, 64, 96), 0.5)
    h, info = estimate_homography(flat, flat)
    assert not bool(info.converged.any()) and not bool(info.textured.any())
    assert bool(torch.isfinite(h).all())
    noise = flat + 1e-4 * torch.randn(flat.shape, generator=torch.Generator().manual_seed(0))
    assert not bool(estimate_homography(noise, noise)[1].converged.any())
    stripes = (0.5 + 0.4 * torch.sin(torch.arange(96.0) / 3)).expand(2, 1, 64, 96)  # no vertical information
    assert not bool(estimate_homography(stripes, stripes)[1].converged.any())


def test_unrelated_images_are_not_converged():
    gravel, _, _ = make_pairs(3, seed=6)
    grass, _, _ = make_pairs(3, seed=6, scene="grass")
    _, info = estimate_homography(gravel, grass)
    assert not bool(info.converged.any())


def test_estimate_homography_rejects_bad_input(pairs):
    img1, img2, _ = pairs
    with pytest.raises(ValueError, match="img1 and img2"):
        estimate_homography(img1[:2], img2[:3])
    with pytest.raises(ValueError, match="init"):
        estimate_homography(img1[:2], img2[:2], init=torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="16 x 16"):
        estimate_homography(img1[:1, :, :8, :8], img2[:1, :, :8, :8])
    with pytest.raises(TypeError, match="config"):
        estimate_homography(img1[:1], img2[:1], config={"levels": (2, 0)})
    with pytest.raises(TypeError, match="img1"):
        estimate_homography(img1[:1].numpy(), img2[:1])


# ----------------------------------------------------------------------------- warping


@pytest.mark.parametrize("backend", ["grid", "kornia"])
def test_warp_identity(pairs, backend):
    img = pairs[1][:2]
    warped, valid = warp_to_reference(img, torch.eye(3, dtype=torch.float64).repeat(2, 1, 1), backend=backend)
    assert torch.allclose(warped, img, atol=1e-4)  # float32 grid: ~1e-5 px
    assert valid.shape == (2, 1, H0, W0) and bool((valid == 1).all())


@pytest.mark.parametrize("backend", ["grid", "kornia"])
def test_warp_translation_invalidates_exactly_the_columns_outside(pairs, backend):
    img = pairs[1][:2]
    warped, valid = warp_to_reference(img, _translation(5.0, 0.0).repeat(2, 1, 1), backend=backend)
    assert bool((valid[..., : W0 - 5] == 1).all()) and bool((valid[..., W0 - 5 :] == 0).all())
    assert torch.allclose(warped[..., : W0 - 5], img[..., 5:], atol=1e-4)  # warped(p) = img2(p + 5)


def test_warp_backends_agree_and_match_the_registration(pairs):
    img1, img2, h_true = (x[:4] for x in pairs)
    w_grid, v_grid = warp_to_reference(img2, h_true)
    w_k, v_k = warp_to_reference(img2, h_true, backend="kornia")
    assert torch.equal(v_grid, v_k)
    assert float((w_grid - w_k).abs().max()) < 5e-4
    inner = F.max_pool2d(-v_grid, 5, 1, 2) == -1  # away from the mask's border
    assert float((w_grid - img1).abs()[inner].mean()) < 0.02  # the pair is registered
    w_small, v_small = warp_to_reference(img2, h_true, dsize=(100, 120))
    assert w_small.shape == (4, 1, 100, 120) and v_small.shape == (4, 1, 100, 120)
    w_u8, _ = warp_to_reference((img2 * 255).round().to(torch.uint8), h_true)
    assert w_u8.dtype == torch.float32 and float((w_u8 - w_grid).abs().max()) < 0.01


def test_warp_rejects_bad_input(pairs):
    img = pairs[1][:2]
    with pytest.raises(ValueError, match="H must have shape"):
        warp_to_reference(img, torch.eye(3))
    with pytest.raises(ValueError, match="H must have shape"):
        warp_to_reference(img, torch.eye(3).repeat(3, 1, 1))
    with pytest.raises(ValueError, match="H must be invertible"):
        warp_to_reference(img, torch.zeros(2, 3, 3))
    with pytest.raises(ValueError, match="dsize"):
        warp_to_reference(img, torch.eye(3).repeat(2, 1, 1), dsize=(10,))
    with pytest.raises(ValueError, match="backend"):
        warp_to_reference(img, torch.eye(3).repeat(2, 1, 1), backend="cv2")
    with pytest.raises(TypeError, match="H"):
        warp_to_reference(img, [[1, 0, 0], [0, 1, 0], [0, 0, 1]])


# ----------------------------------------------------------------------------- perturbation


def _gens(n: int, seed: int = 0):
    return [torch.Generator().manual_seed(seed + i) for i in range(n)]


def test_perturbation_of_identity_stays_close():
    eye = torch.eye(3, dtype=torch.float64)
    p = perturb_homography(eye.repeat(200, 1, 1), _gens(200), size=(H0, W0))
    assert p.shape == (200, 3, 3) and torch.equal(p[:, 2, 2], torch.ones(200, dtype=torch.float64))
    assert float((p[:, :2, :2] - eye[:2, :2]).abs().max()) <= 0.01 + 1e-12
    assert float(corner_error(p, eye.repeat(200, 1, 1), H0, W0).max()) < 3.0
    assert torch.equal(perturb_homography(eye, _gens(1)[0], amount=0.0, size=(H0, W0)), eye)


def test_perturbation_size_matches_spec():
    """Section 7: a 1 % perturbation moves pixels by about 0.8 px on average (the mean over all
    pixels; the image corners, farthest from p0, move about 1.4 px on average)."""
    n = 2000
    base = _translation(2.0, 20.0).repeat(n, 1, 1)
    p = perturb_homography(base, _gens(n, seed=7), size=(H0, W0))
    y, x = torch.meshgrid(*(torch.arange(0, n, 4.0, dtype=torch.float64) for n in (H0, W0)), indexing="ij")
    pts = torch.stack([x.flatten(), y.flatten(), torch.ones(x.numel(), dtype=torch.float64)])
    mapped = [(m @ pts)[:, :2] / (m @ pts)[:, 2:] for m in (p[:200], base[:200])]
    pixel_mean = float((mapped[0] - mapped[1]).norm(dim=1).mean())
    corner_mean = float(corner_error(p, base, H0, W0).mean())
    assert 0.65 < pixel_mean < 0.9, pixel_mean
    assert 1.25 < corner_mean < 1.65, corner_mean


def test_perturbation_is_deterministic_per_pair():
    h = _translation(1.0, 30.0).repeat(5, 1, 1)
    a = perturb_homography(h, _gens(5, seed=3), size=(H0, W0))
    assert torch.equal(a, perturb_homography(h, _gens(5, seed=3), size=(H0, W0)))
    assert torch.equal(a[2], perturb_homography(h[2], _gens(5, seed=3)[2], size=(H0, W0)))  # batch-invariant
    assert not torch.equal(a, perturb_homography(h, _gens(5, seed=4), size=(H0, W0)))
    assert perturb_homography(h.float(), _gens(5), size=(H0, W0)).dtype == torch.float32


def test_perturbation_draw_order():
    """The 8 factors are 1 + amount * (2 rand(8) - 1), in row-major order of the centred H."""
    e = 0.01 * (2 * torch.rand(8, generator=torch.Generator().manual_seed(11), dtype=torch.float64) - 1)
    p = perturb_homography(torch.eye(3, dtype=torch.float64), torch.Generator().manual_seed(11), size=(H0, W0))
    centred = _translation(-(W0 - 1) / 2, -(H0 - 1) / 2) @ p @ _translation((W0 - 1) / 2, (H0 - 1) / 2)
    expected = torch.diag(torch.stack([1 + e[0], 1 + e[4], torch.tensor(1.0, dtype=torch.float64)]))
    assert torch.allclose(centred / centred[2, 2], expected, atol=1e-12)


def test_perturbation_rejects_bad_input():
    h = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1)
    with pytest.raises(ValueError, match="generator"):
        perturb_homography(h, torch.Generator(), size=(H0, W0))  # one generator for 2 pairs
    with pytest.raises(ValueError, match="H must"):
        perturb_homography(torch.eye(4), torch.Generator(), size=(H0, W0))
    with pytest.raises(ValueError, match="amount"):
        perturb_homography(h, _gens(2), amount=1.5, size=(H0, W0))
    with pytest.raises(ValueError, match="size"):
        perturb_homography(h, _gens(2), size=(H0,))
    with pytest.raises(TypeError):
        perturb_homography(h, _gens(2))  # size is required


def test_corner_error():
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.equal(corner_error(eye, eye, H0, W0), torch.zeros(1, dtype=torch.float64))
    err = corner_error(_translation(3.0, 4.0)[None], eye[None], H0, W0)
    assert torch.allclose(err, torch.tensor([5.0], dtype=torch.float64))
    with pytest.raises(ValueError, match="H_true"):
        corner_error(eye.repeat(2, 1, 1), eye.repeat(3, 1, 1), H0, W0)


def test_match_intensity_maps_mean_and_std():
    g = torch.Generator().manual_seed(0)
    ref, img = torch.rand(3, 40, 50, generator=g), torch.rand(3, 40, 50, generator=g) * 0.3 + 0.5
    out = match_intensity(ref, img)
    assert torch.allclose(out.mean((1, 2)), ref.mean((1, 2)), atol=1e-6)
    assert torch.allclose(out.std(dim=(1, 2)), ref.std(dim=(1, 2)), atol=1e-6)
    flat = match_intensity(ref, torch.full((3, 40, 50), 0.2))  # nothing to scale: only shifted
    assert torch.allclose(flat, ref.mean((1, 2), keepdim=True).expand_as(flat), atol=1e-6)


@pytest.mark.parametrize("gain, offset", [(0.7, 0.1), (1.3, -0.1), (1.0, 0.2)])
def test_an_exposure_change_still_registers(gain, offset, monkeypatch):
    """A shifted view with another gain and offset: registered as well as with none."""
    s = load_scene("gravel")
    a, b = s[..., 10:170, 20:232], s[..., 22:182, 23:235]  # img1(p) = img2(p - (3, 12))
    b2 = (gain * b + offset).clamp(0, 1)
    H, info = estimate_homography(a, b2)
    assert bool(info.converged[0])
    assert float(H[0, 0, 2]) == pytest.approx(-3.0, abs=0.02) and float(H[0, 1, 2]) == pytest.approx(-12.0, abs=0.02)
    monkeypatch.setattr(direct, "MATCH_INTENSITY", False)
    _, off = estimate_homography(a, b2)
    assert float(info.residual[0]) < float(off.residual[0])
