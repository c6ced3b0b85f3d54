"""Tests of the pair protocol (docs/method.md, section 7) in lensdist_torch/data/synthesis.py.

Seeds and draws, the motion matrix against a hand-built one, the composed single-grid rendering
against a step-by-step float64 rendering, samples inside the scene, and pair identity whatever
the batch or shard. Small images (96 x 128) keep it fast.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
import torch

from lensdist_torch.config import config_from_dict
from lensdist_torch.core.images import load_scene
from lensdist_torch.data.shards import generate_shard
from lensdist_torch.data.synthesis import (
    PERSPECTIVE,
    ROTATION_DEG,
    SCALE_RANGE,
    TX_RANGE,
    TY_RANGE,
    PairParams,
    draw_pairs,
    footprint,
    is_distorted,
    make_pairs,
    motion_matrix,
    pair_seed,
    render_pairs,
    scene_zoom,
    set_size,
)
from lensdist_torch.geometry.distortion import (
    REJECT,
    delta_metric,
    distortion_center,
    distortion_grid,
    sample_at_pixels,
)

HS, WS = 96, 128
CFG = config_from_dict(
    {
        "image": {"height": HS, "width": WS},
        "protocol": {"n_train": 40, "n_test_distorted": 6, "n_test_undistorted": 3, "shard_size": 4},
    }
)


pytestmark = pytest.mark.usefixtures("one_thread_module")


@pytest.fixture(scope="module")
def scenes() -> list[torch.Tensor]:
    return [load_scene("gravel"), load_scene("grass")]


# ---------------------------------------------------------------------------------- seeds


class TestSeeds:
    def test_deterministic(self):
        assert pair_seed(0, "train", 17) == pair_seed(0, "train", 17)
        assert 0 <= pair_seed(0, "train", 17) < 2**63

    def test_differs_across_sets_indices_and_seeds(self):
        seeds = {pair_seed(s, name, i) for s in (0, 1) for name in ("train", "test") for i in range(50)}
        assert len(seeds) == 2 * 2 * 50

    def test_unknown_set(self):
        with pytest.raises(ValueError, match="set_name"):
            pair_seed(0, "validation", 0)

    def test_set_sizes(self):
        assert set_size(CFG, "train") == 40
        assert set_size(CFG, "test") == 9
        with pytest.raises(ValueError):
            set_size(CFG, "val")
        assert is_distorted(CFG, "train", 39)
        assert is_distorted(CFG, "test", 5) and not is_distorted(CFG, "test", 6)


# ---------------------------------------------------------------------------------- draws


class TestDraws:
    def test_ranges(self):
        cfg = config_from_dict({})  # the method's defaults: 12,000 training pairs
        idx = list(range(0, 12000, 60))  # 200 pairs
        p = draw_pairs(cfg, "train", idx, n_scenes=2)
        assert p.k2.dtype == torch.float64 and p.k2.shape == (200,)
        assert bool(((p.k2 > 0) & (p.k2 <= 2.5e-6)).all())
        assert bool(((p.k4 > 0) & (p.k4 <= 2.5e-11)).all())
        ty, tx, deg, s, h31, h32 = p.motion.unbind(1)
        assert bool(((ty >= 0) & (ty <= 40)).all())
        assert bool(((tx >= -4) & (tx <= 4)).all())
        assert bool(((deg >= -1) & (deg <= 1)).all())
        assert bool(((s >= 0.98) & (s <= 1.02)).all())
        for h in (h31, h32):
            assert bool(((h >= -2e-5) & (h <= 2e-5)).all())
        assert bool(((p.position >= 0) & (p.position < 1)).all())
        assert set(p.scene.tolist()) == {0, 1}
        assert not bool(p.perturbed.any())
        # the draws fill their ranges (uniform: 200 draws reach near both ends)
        assert float(ty.min()) < 2 and float(ty.max()) > 38
        assert float(tx.min()) < -3.5 and float(tx.max()) > 3.5
        assert float(p.k2.max()) > 2.3e-6 and float(p.k2.min()) < 0.2e-6
        assert float(p.k4.max()) > 2.3e-11 and float(p.k4.min()) < 0.2e-11
        # k2 and k4 are drawn independently
        assert abs(float(torch.corrcoef(torch.stack([p.k2, p.k4]))[0, 1])) < 0.2
        # M is the motion matrix of the drawn motion
        torch.testing.assert_close(p.M, motion_matrix(p.motion, 320, 424), atol=0, rtol=0)
        assert p.index.tolist() == idx
        assert p.seed.tolist() == [pair_seed(0, "train", i) for i in idx]
        assert len(p.generators) == 200

    def test_test_set_undistorted_tail(self):
        p = draw_pairs(CFG, "test", range(9), n_scenes=2)
        assert bool((p.k2[:6] > 0).all()) and bool((p.k4[:6] > 0).all())
        assert not bool(p.perturbed[:6].any())
        assert bool((p.k2[6:] == 0).all()) and bool((p.k4[6:] == 0).all())
        assert bool(p.perturbed[6:].all())

    def test_independent_of_the_batch(self):
        one = draw_pairs(CFG, "train", [5], n_scenes=2)
        many = draw_pairs(CFG, "train", [3, 4, 5, 6, 7], n_scenes=2)
        for f in ("seed", "scene", "k2", "k4", "motion", "M", "position", "perturbed"):
            assert torch.equal(getattr(one, f)[0], getattr(many, f)[2]), f
        # the generators continue identically (the perturbation draws come from them)
        assert torch.equal(torch.rand(8, generator=one.generators[0]), torch.rand(8, generator=many.generators[2]))

    def test_seed_changes_the_draws(self):
        other = dataclasses.replace(CFG, protocol=dataclasses.replace(CFG.protocol, seed=1))
        a = draw_pairs(CFG, "train", [0, 1], 2)
        b = draw_pairs(other, "train", [0, 1], 2)
        assert not torch.equal(a.k2, b.k2)

    def test_sets_differ(self):
        a = draw_pairs(CFG, "train", [0, 1, 2], 2)
        b = draw_pairs(CFG, "test", [0, 1, 2], 2)
        assert not torch.equal(a.motion, b.motion)

    @pytest.mark.parametrize("i", [-1, 40])
    def test_index_outside_the_set(self, i):
        with pytest.raises(ValueError, match="outside"):
            draw_pairs(CFG, "train", [i], 2)


# ---------------------------------------------------------------------------------- motion


class TestMotion:
    def test_hand_built(self):
        h, w = 320, 424
        ty, tx, deg, s, h31, h32 = 12.5, -3.0, 0.7, 1.01, 1.5e-5, -0.8e-5
        t = math.radians(deg)
        A = torch.tensor(
            [[s * math.cos(t), -s * math.sin(t), tx], [s * math.sin(t), s * math.cos(t), ty], [h31, h32, 1.0]],
            dtype=torch.float64,
        )
        x0, y0 = (w - 1) / 2, (h - 1) / 2
        T_plus = torch.tensor([[1, 0, x0], [0, 1, y0], [0, 0, 1]], dtype=torch.float64)
        T_minus = torch.tensor([[1, 0, -x0], [0, 1, -y0], [0, 0, 1]], dtype=torch.float64)
        expected = T_plus @ A @ T_minus
        M = motion_matrix(torch.tensor([[ty, tx, deg, s, h31, h32]], dtype=torch.float64), h, w)
        assert M.shape == (1, 3, 3) and M.dtype == torch.float64
        torch.testing.assert_close(M[0], expected, atol=1e-12, rtol=1e-12)

    def test_pure_translation_moves_the_centre(self):
        M = motion_matrix(torch.tensor([[7.0, -2.0, 0.0, 1.0, 0.0, 0.0]]), 96, 128)
        c = torch.tensor([63.5, 47.5, 1.0], dtype=torch.float64)
        assert (M[0] @ c).tolist() == pytest.approx([61.5, 54.5, 1.0])

    def test_rotation_and_scale_keep_the_centre(self):
        M = motion_matrix(torch.tensor([[0.0, 0.0, 1.0, 1.02, 0.0, 0.0]]), 96, 128)
        c = torch.tensor([63.5, 47.5, 1.0], dtype=torch.float64)
        torch.testing.assert_close(M[0] @ c, c, atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------- rendering


def sampling_points(scene_sizes, params: PairParams, config) -> tuple[torch.Tensor, torch.Tensor]:
    """Literal section 7 geometry in float64: the scene points (B, H, W, 2) sampled by I1 and I2.

    distortion grid (eq. 4) -> M (I2 only) -> placement P(q) = c + z (q - p0), the zoom of the
    scene's size and c from the pair's position (c + z * box stays inside the scene).
    """
    h, w = config.image.height, config.image.width
    x0, y0 = distortion_center(h, w)
    p0 = torch.tensor([x0, y0], dtype=torch.float64)
    box = footprint(config)
    q = distortion_grid(params.k2, params.k4, h, w, dtype=torch.float64).reshape(-1, h * w, 2)
    qh = torch.cat([q, torch.ones_like(q[..., :1])], -1) @ params.M.transpose(1, 2)
    mq = qh[..., :2] / qh[..., 2:]
    size = torch.tensor([scene_sizes[int(s)] for s in params.scene], dtype=torch.float64)  # (B, 2) = (hs, ws)
    hs, ws = size[:, 0], size[:, 1]
    z = torch.tensor([scene_zoom(scene_sizes[int(s)], box) for s in params.scene], dtype=torch.float64)
    cx = -z * box[0] + params.position[:, 0] * ((ws - 1) - z * (box[1] - box[0]))
    cy = -z * box[2] + params.position[:, 1] * ((hs - 1) - z * (box[3] - box[2]))
    c = torch.stack([cx, cy], -1)[:, None]
    a = c + z[:, None, None] * (q - p0)  # I1(p) = S(P p)
    b = c + z[:, None, None] * (mq - p0)  # I2(p) = S(P M p)
    return a.view(-1, h, w, 2), b.view(-1, h, w, 2)


def step_by_step(scenes, params: PairParams, config) -> tuple[torch.Tensor, torch.Tensor]:
    """The two views rendered from the literal geometry, one float64 grid_sample per image."""
    a, b = sampling_points([tuple(s.shape[-2:]) for s in scenes], params, config)
    out1, out2 = [], []
    for i in range(a.shape[0]):
        sc = scenes[int(params.scene[i])].double()
        out1.append(sample_at_pixels(sc, a[i : i + 1]))
        out2.append(sample_at_pixels(sc, b[i : i + 1]))
    return torch.cat(out1), torch.cat(out2)


def extreme_params(config, n_scenes: int) -> PairParams:
    """Every corner of the motion ranges, at the largest coefficients, at both ends of the position."""
    motions = list(
        itertools.product(
            TY_RANGE, TX_RANGE, (-ROTATION_DEG, ROTATION_DEG), SCALE_RANGE,
            (-PERSPECTIVE, PERSPECTIVE), (-PERSPECTIVE, PERSPECTIVE),
        )
    )
    rows = []
    for m, pos, s in itertools.product(motions, ((0.0, 0.0), (1.0, 1.0)), range(n_scenes)):
        rows.append((m, pos, s))
    n = len(rows)
    motion = torch.tensor([r[0] for r in rows], dtype=torch.float64)
    return PairParams(
        index=torch.arange(n),
        seed=torch.zeros(n, dtype=torch.int64),
        scene=torch.tensor([r[2] for r in rows]),
        k2=torch.full((n,), config.distortion.k2_max, dtype=torch.float64),
        k4=torch.full((n,), config.distortion.k4_max, dtype=torch.float64),
        motion=motion,
        M=motion_matrix(motion, config.image.height, config.image.width),
        position=torch.tensor([r[1] for r in rows], dtype=torch.float64),
        perturbed=torch.zeros(n, dtype=torch.bool),
        generators=[],
    )


class TestRender:
    def test_footprint_and_zoom(self, scenes):
        box = footprint(CFG)
        assert box[0] < 0 < box[1] and box[2] < 0 < box[3]
        # the vertical translation (0..40 px, downwards) makes the box longer below p0
        assert box[3] - box[2] > HS + 40
        assert box[1] - box[0] > WS
        assert scene_zoom((512, 512), box) == 1.0
        z = scene_zoom((120, 200), box)
        assert 0 < z < 1
        assert z == pytest.approx(min(199 / (box[1] - box[0]), 119 / (box[3] - box[2])))

    def test_composed_equals_step_by_step(self, scenes):
        # two scenes of different sizes (one with zoom < 1), train and test (class R) pairs
        scs = [scenes[0], scenes[1][..., 100:220, 50:250].contiguous()]
        assert scene_zoom(tuple(scs[1].shape[-2:]), footprint(CFG)) < 1
        for set_name, idx in (("train", range(8)), ("test", [4, 5, 6, 7])):
            params = draw_pairs(CFG, set_name, idx, len(scs))
            assert len(params.scene.unique()) == 2
            i1, i2 = render_pairs(scs, params, CFG)
            assert i1.shape == (len(idx), 1, HS, WS) and i1.dtype == torch.float32
            r1, r2 = step_by_step(scs, params, CFG)
            torch.testing.assert_close(i1.double(), r1, atol=1e-4, rtol=0)
            torch.testing.assert_close(i2.double(), r2, atol=1e-4, rtol=0)

    def test_views_differ_by_the_motion(self, scenes):
        params = draw_pairs(CFG, "train", [0], 2)
        i1, i2 = render_pairs(scenes, params, CFG)
        assert float((i1 - i2).abs().mean()) > 0.01
        still = dataclasses.replace(params, M=torch.eye(3, dtype=torch.float64)[None])
        i1, i2 = render_pairs(scenes, still, CFG)
        torch.testing.assert_close(i1, i2, atol=1e-5, rtol=0)

    def test_every_sample_inside_the_scene(self):
        """Scenes of ones, extreme parameters: no zero padding can reach the views."""
        ones = [torch.ones(1, 1, 512, 512), torch.ones(1, 1, 150, 190)]
        params = extreme_params(CFG, 2)
        i1, i2 = render_pairs(ones, params, CFG)
        assert float((i1 - 1).abs().max()) < 1e-6
        assert float((i2 - 1).abs().max()) < 1e-6
        # and the sampling coordinates themselves
        sizes = [tuple(s.shape[-2:]) for s in ones]
        hw = torch.tensor([sizes[int(s)] for s in params.scene], dtype=torch.float64)
        hi = torch.stack([hw[:, 1] - 1, hw[:, 0] - 1], -1)[:, None, None]  # (x, y) upper bounds
        for pts in sampling_points(sizes, params, CFG):
            assert float(pts.min()) >= 0
            assert bool((pts <= hi).all())

    def test_drawn_pairs_inside_the_scene(self):
        ones = [torch.ones(1, 1, 512, 512), torch.ones(1, 1, 140, 170)]
        params = draw_pairs(CFG, "train", range(40), 2)
        i1, i2 = render_pairs(ones, params, CFG)
        assert float((i1 - 1).abs().max()) < 1e-6 and float((i2 - 1).abs().max()) < 1e-6


# ---------------------------------------------------------------------------------- pairs


def assert_same_pair(a, i, b, j):
    """Pair i of batch a equals pair j of batch b: draws exactly, counts exactly, H to 1e-5."""
    for f in ("index", "seed", "scene", "k2", "k4", "motion", "M", "position", "perturbed"):
        assert torch.equal(getattr(a.params, f)[i], getattr(b.params, f)[j]), f
    for m in ("delta_avg", "delta_max"):
        assert torch.equal(a.delta[m][i], b.delta[m][j])
        assert torch.equal(a.classes[m][i], b.classes[m][j])
    assert torch.equal(a.counts[i], b.counts[j])
    assert bool(a.converged[i] == b.converged[j])
    torch.testing.assert_close(a.H[i], b.H[j], atol=1e-5, rtol=0)


class TestMakePairs:
    def test_alone_and_in_a_batch(self, scenes):
        i = 5
        alone = make_pairs(scenes, config=CFG, set_name="train", indices=[i], keep_images=True)
        batch = make_pairs(scenes, config=CFG, set_name="train", indices=list(range(i - 2, i + 4)), keep_images=True)
        assert_same_pair(alone, 0, batch, 2)
        assert torch.equal(alone.img1[0], batch.img1[2]) and torch.equal(alone.img2[0], batch.img2[2])

    def test_class_r_pair_alone_and_in_a_batch(self, scenes):
        """A perturbed pair draws its perturbation from its own generator, not the batch's."""
        alone = make_pairs(scenes, config=CFG, set_name="test", indices=[7])
        batch = make_pairs(scenes, config=CFG, set_name="test", indices=[4, 5, 6, 7, 8])
        assert_same_pair(alone, 0, batch, 3)
        assert bool(batch.params.perturbed[2:].all()) and not bool(batch.params.perturbed[:2].any())

    def test_same_pair_in_another_shard_layout(self, scenes):
        """Pair 6 inside a shard [4, 8) with batches of 3, and as pair 0 of its own shard."""
        ref = make_pairs(scenes, config=CFG, set_name="train", indices=[6])
        a = generate_shard(scenes, config=CFG, set_name="train", start=4, end=8, fingerprint="fp", batch_size=3)
        b = generate_shard(scenes, config=CFG, set_name="train", start=6, end=7, fingerprint="fp", batch_size=16)
        for rec, j in ((a, 2), (b, 0)):
            assert int(rec["index"][j]) == 6
            assert torch.equal(rec["counts"][j], ref.counts[0])
            assert torch.equal(rec["k2"][j], ref.params.k2[0]) and torch.equal(rec["M"][j], ref.params.M[0])
            torch.testing.assert_close(rec["H"][j], ref.H[0], atol=1e-5, rtol=0)

    def test_ground_truth_and_classes(self, scenes):
        out = make_pairs(scenes, config=CFG, set_name="test", indices=[0, 1, 6, 8])
        assert out.counts.shape == (4, 1, HS // 8, WS // 8) and out.counts.dtype == torch.uint8
        assert out.H.shape == (4, 3, 3) and out.H.dtype == torch.float64
        assert out.img1 is None and out.img2 is None
        for m in ("delta_avg", "delta_max"):
            torch.testing.assert_close(out.delta[m], delta_metric(out.params.k2, out.params.k4, HS, WS, metric=m))
            assert out.classes[m][2:].tolist() == [REJECT, REJECT]
            assert all(0 <= c < 4 for c in out.classes[m][:2].tolist())
        assert bool((out.delta["delta_avg"][2:] == 0).all())

    def test_registration_recovers_the_motion(self, scenes):
        """The estimated homography (from the distorted pair) is close to the true motion.

        I2(p) = I1(M p) while H is img1(p) = img2(H p): H estimates M^-1.
        """
        from lensdist_torch.registration.direct import corner_error

        out = make_pairs(scenes, config=CFG, set_name="train", indices=[0, 1, 2])
        ok = out.converged
        assert bool(ok.any())
        err = corner_error(out.H[ok], torch.linalg.inv(out.params.M[ok]), HS, WS)
        # distortion of these small views is below 2 px; registration is far better than the motion (up to 40 px)
        assert float(err.max()) < 3.0
