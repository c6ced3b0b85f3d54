"""Tests of lensdist_torch.registration.wide_baseline: the feature fallback of registration (docs/method.md,
section 10) on planar pairs far apart (rotation, zoom, strong perspective), unrelated and flat pairs."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry import warp_perspective

from lensdist_torch.config import RegistrationConfig
from lensdist_torch.core.images import load_scene
from lensdist_torch.geometry.homography import corner_error
from lensdist_torch.registration import wide_baseline
from lensdist_torch.registration.direct import estimate_homography
from lensdist_torch.registration.wide_baseline import SiftMemo, estimate_homography_robust, feature_homography

H0, W0 = 320, 424  # the analysis size (docs/method.md, section 1)

pytestmark = pytest.mark.usefixtures("one_thread_module")


def _shift(x: float, y: float) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], dtype=torch.float64)


def true_h(deg: float, scale: float, persp: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
    """img1 -> img2: a rotation by ``deg``, a zoom by ``scale`` and the perspective row (h31, h32),
    about the image centre (pixel units)."""
    c, s = scale * math.cos(math.radians(deg)), scale * math.sin(math.radians(deg))
    a = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [persp[0], persp[1], 1.0]], dtype=torch.float64)
    h = _shift((W0 - 1) / 2, (H0 - 1) / 2) @ a @ _shift(-(W0 - 1) / 2, -(H0 - 1) / 2)
    return h / h[2, 2]


def render(hs: list[torch.Tensor], scene: str = "gravel") -> tuple[torch.Tensor, torch.Tensor]:
    """img1 the centre 320 x 424 of the 512 x 512 scene, img2(H p) = img1(p) (zeros outside the scene)."""
    s = load_scene(scene).double()
    a1 = _shift(255.5, 255.5) @ _shift(-(W0 - 1) / 2, -(H0 - 1) / 2)  # img1 pixel -> scene pixel
    warp = [torch.linalg.inv(a1 @ torch.linalg.inv(h)) for h in hs]  # scene -> img2
    img1 = warp_perspective(s, torch.linalg.inv(a1)[None], (H0, W0), align_corners=True).float()
    img2 = warp_perspective(s.expand(len(hs), -1, -1, -1), torch.stack(warp), (H0, W0), align_corners=True)
    return img1.expand(len(hs), -1, -1, -1).contiguous(), img2.float()


# far apart: rotations up to 45 degrees, zooms 0.6-1.6, perspective up to 1e-3 (measured corner
# errors of the fallback on the 40-pair grid of benchmarks/bench_wide_baseline.py: median 0.012 px,
# max 0.08 px)
WIDE = [(45.0, 0.6, (1e-3, -5e-4)), (33.75, 1.6, (0.0, 0.0)), (22.5, 1.25, (1e-3, -5e-4)), (45.0, 0.9, (0.0, 0.0))]


@pytest.fixture(scope="module")
def wide():
    hs = [true_h(*c) for c in WIDE]
    return (*render(hs), torch.stack(hs))


def test_recovers_far_apart_pairs(wide):
    img1, img2, h_true = wide
    h_fast, info_fast = estimate_homography(img1, img2)
    assert not bool(info_fast.converged.any())  # the first run alone fails on every one
    h, info = estimate_homography_robust(img1, img2)
    err = corner_error(h, h_true, H0, W0)
    assert bool(info.converged.all()), info
    assert float(err.median()) < 0.05 and float(err.max()) < 0.25, err
    assert bool((info.overlap >= 0.3).all()) and bool(info.textured.all())
    assert bool((info.iterations > info_fast.iterations).all())  # both runs counted
    assert torch.equal(h[:, 2, 2], torch.ones(4, dtype=torch.float64))


def test_feature_homography(wide):
    img1, img2, h_true = wide
    h, ok, n = feature_homography(img1[:1], img2[:1])
    assert h.shape == (1, 3, 3) and h.dtype == torch.float64 and n.dtype == torch.int64
    assert bool(ok[0]) and int(n[0]) >= wide_baseline.MIN_INLIERS
    assert float(corner_error(h, h_true[:1], H0, W0)[0]) < 2.0  # the coarse estimate: < 1 px measured


def test_memo_describes_each_image_once_and_changes_nothing(wide, monkeypatch):
    """The same homographies bit for bit; img1 repeated in every pair is described once."""
    img1, img2, _ = wide
    plain = estimate_homography_robust(img1, img2)
    calls = []
    describe = wide_baseline._describe
    monkeypatch.setattr(wide_baseline, "_describe", lambda img, k: calls.append(1) or describe(img, k))
    memo = SiftMemo()
    got = estimate_homography_robust(img1, img2, memo=memo)
    assert len(calls) == len(memo) == 1 + len(WIDE)  # one img1 (the four pairs share it), four img2
    assert torch.equal(got[0], plain[0]) and all(torch.equal(x, y) for x, y in zip(got[1], plain[1]))
    again = estimate_homography_robust(img1, img2, memo=memo)  # a second call describes nothing
    assert len(calls) == 1 + len(WIDE) and torch.equal(again[0], plain[0])


def test_converged_pairs_keep_the_first_answer(wide, monkeypatch):
    """Pairs the first run registers are returned bit for bit; only the others are redone."""
    img1, img2, _ = wide
    small = render([true_h(0.5, 1.0), true_h(0.0, 1.01, (1e-5, 0.0))])
    a, b = torch.cat([small[0], img1[:1]]), torch.cat([small[1], img2[:1]])
    h_fast, info_fast = estimate_homography(a, b)
    assert info_fast.converged.tolist() == [True, True, False]
    h, info = estimate_homography_robust(a, b)
    assert torch.equal(h[:2], h_fast[:2]) and info.converged.tolist() == [True, True, True]
    for x, y in zip(info, info_fast):
        assert torch.equal(x[:2], y[:2])
    monkeypatch.setattr(wide_baseline, "FEATURE_FALLBACK", False)
    off = estimate_homography_robust(a, b)
    assert torch.equal(off[0], h_fast) and all(torch.equal(x, y) for x, y in zip(off[1], info_fast))


def test_uint8_colour_pair():
    img1, img2 = render([true_h(40.0, 0.8, (5e-4, 5e-4))])
    h_true = true_h(40.0, 0.8, (5e-4, 5e-4))[None]
    a, b = ((x.expand(-1, 3, -1, -1) * 255).round().to(torch.uint8) for x in (img1, img2))
    h, info = estimate_homography_robust(a, b)
    assert bool(info.converged[0]) and float(corner_error(h, h_true, H0, W0)[0]) < 0.25


def test_unrelated_and_flat_pairs_do_not_register():
    gravel, grass = (load_scene(n)[..., 96:416, 44:468] for n in ("gravel", "grass"))
    flat = torch.full_like(gravel, 0.5)
    img1, img2 = torch.cat([gravel, flat, flat]), torch.cat([grass, gravel, flat])
    h, info = estimate_homography_robust(img1, img2)
    assert info.converged.tolist() == [False, False, False]
    assert bool(torch.isfinite(h).all())
    _, ok, n = feature_homography(img1[:1], img2[:1])
    assert not bool(ok[0]) and int(n[0]) < wide_baseline.MIN_INLIERS


@pytest.mark.parametrize(
    "field, value",
    [("chunk_size", 0), ("chunk_size", 2.0), ("chunk_size", True)],
)
def test_config_fields_are_checked(field, value):
    with pytest.raises(ValueError, match=rf"^registration\.{field} must be [^\n]*$"):
        RegistrationConfig(**{field: value})


def test_bad_arguments():
    x = torch.rand(1, 1, 32, 32)
    with pytest.raises(TypeError, match="config must be a RegistrationConfig"):
        estimate_homography_robust(x, x, config={"min_inliers": 4})
    with pytest.raises(TypeError, match="config must be a RegistrationConfig"):
        feature_homography(x, x, "defaults")
    with pytest.raises(ValueError, match="same shape"):
        feature_homography(x, torch.rand(1, 1, 32, 40))
    with pytest.raises(ValueError, match="same shape"):
        estimate_homography_robust(x, torch.rand(1, 1, 32, 40))
