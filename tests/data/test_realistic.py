"""Tests of the realistic pair protocol (docs/method.md, section 7, "the realistic protocol").

The default protocol is unchanged (its draws pinned by a digest recorded before the realistic
protocol existed; the realistic fields are ignored while it is off); each effect is present
and within its range (gain and offset by least squares against the clean render of the same
pair, noise std, JPEG against libjpeg and its 8 x 8 blockiness, parallax measured on a linear
scene, the occluder share); pairs are the same whatever the batch; bad values are one-line
errors. Small images (96 x 128) keep it fast.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from pathlib import Path

import pytest
import torch

from lensdist_torch.config import LensdistConfig, config_from_dict, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.data import realism, synthesis
from lensdist_torch.data.realism import (
    N_BUMPS,
    PHOTOMETRIC,
    degrade,
    draw_realism,
    height_field,
    illumination_field,
    jpeg,
    jpeg_table,
    occluder_patch,
    realism_seed,
)
from lensdist_torch.data.synthesis import draw_pairs, make_pairs, render_pairs

HS, WS = 96, 128
BASE = {
    "image": {"height": HS, "width": WS},
    "protocol": {"n_train": 400, "n_test_distorted": 6, "n_test_undistorted": 3, "shard_size": 4},
}
CFG = config_from_dict(BASE)
REAL = config_from_dict({**BASE, "protocol": {**BASE["protocol"], "realistic": True}})
#: Every effect off, as the constants of data/realism.py (JPEG at quality 100: steps of 1, about 0.3 grey levels of
#: error; no occluder).
NEUTRAL = {
    "GAIN_RANGE": (1.0, 1.0), "OFFSET_RANGE": (0.0, 0.0), "GAMMA_RANGE": (1.0, 1.0), "ILLUMINATION": 0.0,
    "NOISE_RANGE": (0.0, 0.0), "JPEG_QUALITY": (100, 100), "OCCLUDER_RATE": 0.0,
}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"

pytestmark = pytest.mark.usefixtures("one_thread_module")


@pytest.fixture
def only(monkeypatch):
    """``only(relief=0.0, **effects)``: the realistic protocol with every effect off but ``effects`` (the
    constants of data/realism.py, patched for the test) and the config's relief."""

    def make(relief: float = 0.0, **effects) -> LensdistConfig:
        for name, value in {**NEUTRAL, **effects}.items():
            monkeypatch.setattr(realism, name, value)
        return config_from_dict({**BASE, "protocol": {**BASE["protocol"], "realistic": True, "relief": relief}})

    return make


@pytest.fixture(scope="module")
def scenes() -> list[torch.Tensor]:
    return [load_scene("gravel"), load_scene("grass")]


def clean_of(scenes, params, config):
    """The clean render of the same pairs (no realism)."""
    return render_pairs(scenes, dataclasses.replace(params, realism=None), config)


def rendered(only, scenes, n: int, **effects):
    """The first ``n`` training pairs of ``only(**effects)``: their draws, their renders (r1, r2)
    and the clean renders of the same pairs (c1, c2)."""
    cfg = only(**effects)
    p = draw_pairs(cfg, "train", range(n), 2)
    return p, render_pairs(scenes, p, cfg), clean_of(scenes, p, cfg)


# ------------------------------------------------------------------------ the default protocol


class TestDefaultUnchanged:
    def test_draws_digest(self):
        """Recorded with the protocol before the realistic one was added (the same digest)."""
        h = hashlib.sha256()
        for s, idx in (("train", range(16)), ("test", range(9))):
            p = draw_pairs(CFG, s, idx, 2)
            assert p.realism is None
            for t in (p.seed, p.scene, p.k2, p.k4, p.motion, p.position, p.perturbed):
                h.update(t.contiguous().numpy().tobytes())
            # the class-R perturbation's draws follow on the pair's own generator
            later = torch.stack([torch.rand(8, generator=g, dtype=torch.float64) for g in p.generators])
            h.update(later.numpy().tobytes())
        assert h.hexdigest() == "c3a6313b8c100374c75b3a4e7730bd42785189c4f22a546771ca8ae695b6d8a4"

    def test_realistic_fields_ignored_while_off(self, scenes, monkeypatch):
        a = {s: make_pairs(scenes, config=CFG, set_name=s, indices=idx, keep_images=True)
             for s, idx in (("train", [0, 1, 2]), ("test", [5, 6, 7]))}
        fp = synthesis.footprint(CFG)
        for name, value in {**NEUTRAL, "GAIN_RANGE": (0.5, 0.6), "NOISE_RANGE": (0.1, 0.2), "OCCLUDER_RATE": 1.0}.items():
            monkeypatch.setattr(realism, name, value)
        off = config_from_dict({**BASE, "protocol": {**BASE["protocol"], "relief": 0.3}})
        for s, idx in (("train", [0, 1, 2]), ("test", [5, 6, 7])):
            b = make_pairs(scenes, config=off, set_name=s, indices=idx, keep_images=True)
            for x, y in ((a[s].img1, b.img1), (a[s].img2, b.img2), (a[s].H, b.H), (a[s].counts, b.counts),
                         (a[s].residual, b.residual)):
                assert torch.equal(x, y)
        assert synthesis.footprint(off) == fp

    def test_realism_leaves_the_protocol_draws(self):
        a = draw_pairs(CFG, "test", range(9), 2)
        b = draw_pairs(REAL, "test", range(9), 2)
        for f in ("seed", "scene", "k2", "k4", "motion", "M", "position", "perturbed"):
            assert torch.equal(getattr(a, f), getattr(b, f)), f
        # the generators stand where they stood: the class-R perturbation draws the same numbers
        assert all(torch.equal(g.get_state(), h.get_state()) for g, h in zip(a.generators, b.generators))
        assert b.realism is not None and b.realism.photometric.shape == (9, 2, len(PHOTOMETRIC))

    def test_realistic_toml_is_the_paper_protocol_plus_the_switch(self):
        paper, real = load_config(CONFIGS / "paper.toml"), load_config(CONFIGS / "realistic.toml")
        assert paper == LensdistConfig() and not paper.protocol.realistic
        assert real == dataclasses.replace(paper, protocol=dataclasses.replace(paper.protocol, realistic=True))


# ------------------------------------------------------------------------------ the draws


@pytest.fixture(scope="module")
def drawn():
    """The realism of 400 pairs of the realistic protocol with relief up to 3 %."""
    cfg = config_from_dict({**BASE, "protocol": {**BASE["protocol"], "realistic": True, "relief": 0.03}})
    return draw_pairs(cfg, "train", range(400), 2).realism


class TestDraws:
    def test_photometric_ranges(self, drawn):
        ph = drawn.photometric
        col = {name: ph[..., i] for i, name in enumerate(PHOTOMETRIC)}
        assert ph.shape == (400, 2, 8) and ph.dtype == torch.float64
        assert col["gain"].min() >= 0.7 and col["gain"].max() <= 1.3
        assert col["offset"].min() >= -0.1 and col["offset"].max() <= 0.1
        assert col["gamma"].min() >= 0.8 and col["gamma"].max() <= 1.25
        # log-uniform: log gamma is symmetric about 0 in [log 0.8, log 1.25]
        assert abs(float(col["gamma"].log().mean())) < 0.02
        assert col["illumination"].min() >= 0 and col["illumination"].max() <= 0.25
        assert col["noise_sigma"].min() >= 0 and col["noise_sigma"].max() <= 0.02
        q = col["jpeg_quality"]
        assert torch.equal(q, q.round()) and int(q.min()) == 60 and int(q.max()) == 95
        # per view: the two views of a pair differ
        assert bool((col["gain"][:, 0] != col["gain"][:, 1]).all())

    def test_relief_and_occluder_ranges(self, drawn):
        amp = drawn.relief[:, 0]
        assert drawn.relief.shape == (400, 1 + 4 * N_BUMPS)
        assert amp.min() >= 0 and amp.max() <= 0.03 and amp.max() > 0.029
        assert bool((draw_pairs(REAL, "train", range(20), 2).realism.relief[:, 0] == 0).all())  # default: a plane
        share = float(drawn.occluded.double().mean())
        assert 0.13 <= share <= 0.27, share  # 20 % of 400: 3.5 standard deviations either side
        rect = drawn.occluder
        present = rect[..., 2] > 0
        assert torch.equal(present.any(1), drawn.occluded)
        x0, y0, w, h = rect[present].unbind(-1)
        assert bool((x0 >= 0).all() and (y0 >= 0).all() and (x0 + w <= WS).all() and (y0 + h <= HS).all())
        area = (w * h).double() / (HS * WS)
        assert area.min() >= 0.045 and area.max() <= 0.16  # 5-15 % of the frame, up to rounding
        # one view only, or both views at different places (a moving object), about 1/3 each
        both = present.all(1)
        assert 0.15 < float(both[drawn.occluded].double().mean()) < 0.55
        assert bool((rect[both][:, 0, :2] != rect[both][:, 1, :2]).any(-1).all())

    def test_seeds_hash_the_pair_seed(self):
        p = draw_pairs(REAL, "train", [3], 2)
        again = draw_realism(REAL, [int(p.seed[0])])
        assert torch.equal(p.realism.photometric, again.photometric)
        assert realism_seed(1) != realism_seed(2) and 0 <= realism_seed(7) < 2**63

    def test_ranges_do_not_shift_other_draws(self, only, monkeypatch):
        a = draw_pairs(REAL, "train", range(40), 2).realism
        with monkeypatch.context() as mp:
            mp.setattr(realism, "NOISE_RANGE", (0.0, 0.0))
            b = draw_pairs(REAL, "train", range(40), 2).realism
        assert bool((b.photometric[..., 6] == 0).all())
        assert torch.equal(a.photometric[..., :6], b.photometric[..., :6])
        assert torch.equal(a.photometric[..., 7], b.photometric[..., 7])
        for f in ("relief", "occluded", "occluder", "look", "seeds"):
            assert torch.equal(getattr(a, f), getattr(b, f)), f
        # the bump geometry and the seeds do not depend on any range
        c = draw_pairs(only(), "train", range(40), 2).realism
        assert torch.equal(a.relief[:, 1:], c.relief[:, 1:]) and torch.equal(a.seeds, c.seeds)


# ------------------------------------------------------------------------------ each effect


def _fit(clean: torch.Tensor, real: torch.Tensor) -> tuple[float, float, float]:
    """Least-squares a, b of real = a clean + b over unclipped pixels; and the residual std."""
    x, y = clean.flatten().double(), real.flatten().double()
    keep = (y > 0.02) & (y < 0.98)
    x, y = x[keep], y[keep]
    a_mat = torch.stack([x, torch.ones_like(x)], 1)
    sol = torch.linalg.lstsq(a_mat, y[:, None]).solution[:, 0]
    res = y - a_mat @ sol
    return float(sol[0]), float(sol[1]), float(res.std())


class TestEffects:
    def test_gain_and_offset_recovered(self, scenes, only):
        p, (r1, r2), (c1, c2) = rendered(only, scenes, 8, GAIN_RANGE=(0.7, 1.3), OFFSET_RANGE=(-0.1, 0.1))
        for j in range(8):
            for v, (c, r) in enumerate(((c1, r1), (c2, r2))):
                gain, offset, res = _fit(c[j], r[j])
                assert gain == pytest.approx(float(p.realism.photometric[j, v, 0]), abs=0.01)
                assert offset == pytest.approx(float(p.realism.photometric[j, v, 1]), abs=0.005)
                assert res < 0.004  # 8 bits and JPEG at quality 100 only

    def test_gamma(self, scenes, only):
        p, (r1, _), (c1, _) = rendered(only, scenes, 6, GAMMA_RANGE=(0.8, 1.25))
        for j in range(6):
            g = float(p.realism.photometric[j, 0, 2])
            assert 0.8 <= g <= 1.25
            err = (r1[j] - c1[j].pow(g)).abs().mean()
            assert err < 0.003 and err < 0.2 * (r1[j] - c1[j]).abs().mean() + 1e-3

    def test_illumination_ramp_and_vignetting(self, scenes, only):
        p, (r1, r2), (c1, c2) = rendered(only, scenes, 8, ILLUMINATION=0.25)
        for v, (c, r) in enumerate(((c1, r1), (c2, r2))):
            light = illumination_field(p.realism.photometric[:, v], HS, WS)
            s = p.realism.photometric[:, v, 3].float()[:, None, None, None]
            assert bool((light >= 1 - s - 1e-6).all() and (light <= 1 + 1e-6).all())
            assert bool((light.amax((1, 2, 3)) - light.amin((1, 2, 3)) > 0.3 * s[:, 0, 0, 0]).all())  # not flat
            assert float((r - (light * c)).abs().amax()) < 0.01  # the render is the clean one times L
        views = (illumination_field(p.realism.photometric[:, v], HS, WS) for v in (0, 1))
        assert not torch.equal(*views)

    def test_noise_std(self, scenes, only):
        p, (r1, r2), (c1, c2) = rendered(only, scenes, 8, NOISE_RANGE=(0.005, 0.02))
        for j in range(8):
            d1, d2 = r1[j] - c1[j], r2[j] - c2[j]
            for v, d in enumerate((d1, d2)):
                sigma = float(p.realism.photometric[j, v, 6])
                assert 0.005 <= sigma <= 0.02
                assert float(d.std()) == pytest.approx(math.hypot(sigma, 0.0012), rel=0.1)
            assert abs(float(torch.corrcoef(torch.stack([d1.flatten(), d2.flatten()]))[0, 1])) < 0.1

    def test_jpeg_matches_libjpeg(self, scenes):
        cv2 = pytest.importorskip("cv2")
        import numpy as np

        img = scenes[0][..., 100 : 100 + HS, 100 : 100 + WS].contiguous()
        for q in (60, 80, 95):
            u8 = np.round(img[0, 0].numpy() * 255).astype(np.uint8)
            ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, q])
            ref = torch.from_numpy(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)).float() / 255
            ours = jpeg(img, q)[0, 0]
            # libjpeg's integer DCT rounds a few coefficients the other way: < 0.5 grey levels on average
            assert float((ours - ref).abs().mean()) * 255 < 0.5
            assert float((ours - ref).abs().mean()) < 0.3 * float((ref - img[0, 0]).abs().mean())

    def test_jpeg_blocks_and_levels(self):
        y, x = torch.meshgrid(torch.arange(HS, dtype=torch.float64), torch.arange(WS, dtype=torch.float64), indexing="ij")
        smooth = (0.5 + 0.3 * torch.sin(x / 9.0 + y / 13.0) + 0.1 * torch.cos(x / 5.0 - y / 7.0)).float()[None, None]

        def blockiness(img):
            dx = (img[0, 0, :, 1:] - img[0, 0, :, :-1]).abs()
            edge = torch.arange(WS - 1) % 8 == 7  # across a block boundary
            return float(dx[:, edge].mean() / dx[:, ~edge].mean())

        coded = {q: jpeg(smooth, q) for q in (60, 95)}
        assert blockiness(smooth) == pytest.approx(1.0, abs=0.05)
        # steps at the 8 x 8 block boundaries, in the image and more so in its error
        assert blockiness(coded[60]) > 1.15 and blockiness(coded[60] - smooth) > 1.5
        assert blockiness(coded[95]) < blockiness(coded[60])
        assert torch.equal(coded[60] * 255, (coded[60] * 255).round())  # 8-bit levels
        assert (coded[95] - smooth).abs().mean() < (coded[60] - smooth).abs().mean()
        odd = jpeg(smooth[..., :90, :125], 75)  # padded by the last row and column, cropped back
        assert odd.shape == (1, 1, 90, 125) and float((odd - smooth[..., :90, :125]).abs().mean()) < 0.02

    def test_jpeg_table(self):
        assert jpeg_table(50)[0, :4].tolist() == [16, 11, 10, 16]
        assert bool((jpeg_table(100) == 1).all()) and float(jpeg_table(1).max()) == 255
        for bad in (0, 101, 50.0, True):
            with pytest.raises(ValueError, match="quality"):
                jpeg_table(bad)

    def _displacement(self, monkeypatch, cfg, p):
        """(B, H, W, 2) px: how far the relief moved I2's samples, on a linear scene (bilinear exact)."""
        ramp = torch.arange(400, dtype=torch.float64) / 512
        scenes = [ramp.expand(400, 400).float()[None, None], ramp[:, None].expand(400, 400).float()[None, None]]
        assert synthesis.scene_zoom((400, 400), synthesis.footprint(cfg)) == 1.0
        monkeypatch.setattr(synthesis, "degrade", lambda a, b, real: (a, b))  # the geometry alone
        moved = []
        for s in (0, 1):  # x from the first scene, y from the second
            q = dataclasses.replace(p, scene=torch.full_like(p.scene, s))
            r1, r2 = render_pairs(scenes, q, cfg)
            c1, c2 = clean_of(scenes, q, cfg)
            assert torch.equal(r1, c1)  # I1 untouched
            moved.append((r2 - c2)[:, 0].double() * 512)
        return torch.stack(moved, -1)

    def test_relief_parallax_follows_the_translation(self, monkeypatch, only):
        """rho / (1 - rho) times camera 2's nadir, to first order: along the translation, in
        proportion to it and to the height; the measured size against that bound."""
        cfg = only(relief=0.03)
        p = draw_pairs(cfg, "train", range(12), 2)
        disp = self._displacement(monkeypatch, cfg, p)
        size = disp.norm(dim=-1).flatten(1).amax(1)
        t = torch.stack([p.motion[:, 1], p.motion[:, 0]], 1)  # camera 2's nadir is about (t_x, t_y)
        rho = p.realism.relief[:, 0]
        bound = rho / (1 - rho) * t.norm(dim=1)
        assert bool((size <= bound * 1.1 + 0.05).all()), (size, bound)  # + the altitude's radial term
        assert bool((size >= bound * 0.5 - 0.05).all()), (size, bound)  # the field reaches its peak somewhere
        big = disp.norm(dim=-1) > 0.2
        u = t / t.norm(dim=1, keepdim=True)
        cross = (disp[..., 0] * u[:, None, None, 1] - disp[..., 1] * u[:, None, None, 0]).abs()
        cross = cross / disp.norm(dim=-1).clamp_min(1e-9)  # sine of the angle to the motion
        assert float(cross[big].max()) < math.sin(math.radians(6))  # along it, up to M's 1 degree and scale

    def test_no_parallax_without_translation(self, monkeypatch, only):
        """A pure rotation (and scale 1) keeps camera 2's nadir and altitude: the relief moves nothing."""
        cfg = only(relief=0.03)
        p = draw_pairs(cfg, "train", range(6), 2)
        motion = torch.zeros_like(p.motion)
        motion[:, 2], motion[:, 3] = torch.linspace(-1, 1, 6, dtype=torch.float64), 1.0
        from lensdist_torch.data.synthesis import motion_matrix

        still = dataclasses.replace(p, motion=motion, M=motion_matrix(motion, HS, WS))
        disp = self._displacement(monkeypatch, cfg, still)
        assert float(disp.abs().max()) < 1e-3

    def test_height_field_peak(self, only):
        cfg = only(relief=0.03)
        p = draw_pairs(cfg, "train", range(10), 2)
        from lensdist_torch.data.relief import relief_fraction

        ys, xs = torch.meshgrid(torch.arange(HS, dtype=torch.float64) - (HS - 1) / 2,
                                torch.arange(WS, dtype=torch.float64) - (WS - 1) / 2, indexing="ij")
        for i in range(10):
            f = height_field(p.realism, i, HS, WS)
            peak = float(relief_fraction(f, xs, ys).abs().max())
            assert abs(peak - float(p.realism.relief[i, 0])) < 0.02 * float(p.realism.relief[i, 0])  # 64 x 64 grid
        assert height_field(draw_pairs(REAL, "train", [0], 2).realism, 0, HS, WS) is None

    def test_occluders(self, scenes, only):
        p, (r1, r2), (c1, c2) = rendered(only, scenes, 12, OCCLUDER_RATE=1.0)
        assert bool(p.realism.occluded.all())
        for j in range(12):
            patch = occluder_patch(p.realism, j)
            for v, (c, r) in enumerate(((c1, r1), (c2, r2))):
                x0, y0, w, h = p.realism.occluder[j, v].tolist()
                inside = torch.zeros(HS, WS, dtype=torch.bool)
                inside[y0 : y0 + h, x0 : x0 + w] = True
                if w:
                    assert float((r[j, 0][inside] - patch.flatten()).abs().mean()) < 0.004
                assert float((r[j, 0][~inside] - c[j, 0][~inside]).abs().mean()) < 0.004
        textured = p.realism.look[:, 0] == 1
        assert textured.any() and (~textured).any()
        for j in range(12):
            patch = occluder_patch(p.realism, j)
            assert (patch.std() > 0.02) == bool(textured[j])


# ---------------------------------------------------------------------------- determinism


class TestDeterminism:
    def test_same_pair_any_batch(self, scenes):
        """Draws and images are bit-identical alone, in a batch and twice; the registration, as in
        the clean protocol (tests/data/test_synthesis.py), agrees to 1e-5 across batches."""
        relief = config_from_dict({**BASE, "protocol": {**BASE["protocol"], "realistic": True, "relief": 0.03}})
        for cfg, set_name, i, idx in ((REAL, "train", 9, [7, 8, 9, 10, 11]), (relief, "test", 7, [4, 5, 6, 7, 8])):
            alone = make_pairs(scenes, config=cfg, set_name=set_name, indices=[i], keep_images=True)
            batch = make_pairs(scenes, config=cfg, set_name=set_name, indices=idx, keep_images=True)
            again = make_pairs(scenes, config=cfg, set_name=set_name, indices=[i], keep_images=True)
            k = idx.index(i)
            ra, rb, rc = (x.params.realism for x in (alone, batch, again))
            pairs = [(alone.img1, batch.img1[k : k + 1], again.img1), (alone.img2, batch.img2[k : k + 1], again.img2)]
            for f in ("photometric", "relief", "occluded", "occluder", "look", "seeds"):
                pairs.append((getattr(ra, f), getattr(rb, f)[k : k + 1], getattr(rc, f)))
            for a, b, c in pairs:
                assert torch.equal(a, b) and torch.equal(a, c)
            for f in ("H", "counts", "converged", "residual"):
                assert torch.equal(getattr(alone, f), getattr(again, f)), f
            torch.testing.assert_close(alone.H[0], batch.H[k], atol=1e-5, rtol=0)
            assert bool(alone.converged[0] == batch.converged[k])

    def test_degrade_is_pure(self, scenes):
        p = draw_pairs(REAL, "train", range(4), 2)
        c1, c2 = clean_of(scenes, p, REAL)
        a = degrade(c1, c2, p.realism)
        b = degrade(c1, c2, p.realism)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
        assert not torch.equal(a[0], c1)  # the inputs stay as they were
        assert torch.equal(c1, clean_of(scenes, p, REAL)[0])

    def test_realistic_pairs_generate(self, scenes):
        out = make_pairs(scenes, config=REAL, set_name="test", indices=[0, 1, 6, 8])
        assert out.params.realism.occluded.dtype == torch.bool and out.converged.dtype == torch.bool
        assert out.counts.shape == (4, 1, HS // 8, WS // 8)
        assert bool(out.params.perturbed[2:].all())


# ------------------------------------------------------------------------------ bad values


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "field, value",
    [
        ("realistic", 1),
        ("realistic", "yes"),
        ("relief", -0.01),
        ("relief", 0.5),
        ("relief", True),
    ],
)
def test_bad_realistic_values(field, value):
    with pytest.raises(ValueError) as exc:
        config_from_dict({"protocol": {field: value}})
    msg = str(exc.value)
    assert "\n" not in msg and f"protocol.{field} must be" in msg, msg


@pytest.mark.bad_input
def test_realistic_sequence_is_refused(scenes):
    with pytest.raises(ValueError) as exc:
        make_pairs(scenes, config=REAL, set_name="train", indices=[0], sequence=True)
    assert "\n" not in str(exc.value) and "protocol.realistic" in str(exc.value)


@pytest.mark.bad_input
def test_a_config_saved_with_the_retired_parallax():
    """Checkpoints saved before protocol.relief carry protocol.parallax_px: dropped where it had no
    effect (the clean protocol: the shipped checkpoints), refused where it shaped the data."""
    from lensdist_torch.config import retired_keys, stored_config

    clean = {"protocol": {"realistic": False, "parallax_px": 1.5}}
    assert retired_keys(clean) == ["protocol.parallax_px"]
    assert stored_config(clean) == config_from_dict({"protocol": {"realistic": False}})
    assert stored_config({"protocol": {"realistic": True, "parallax_px": 0.0}}).protocol.relief == 0.0
    with pytest.raises(ValueError, match=r"^saved under the realistic protocol's former fixed parallax .*1\.5.*protocol\.relief") as err:
        stored_config({"protocol": {"realistic": True, "parallax_px": 1.5}})
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['parallax_px'\] in config section \[protocol\]"):
        config_from_dict(clean)  # a user's file is not silently reinterpreted
    # the former relief threshold of the analysis (issue 20) never shaped a model or a data set: dropped
    old = {"analysis": {"relief_z": 4.0, "min_confidence": 0.6}}
    assert retired_keys(old) == ["analysis.relief_z"]
    assert stored_config(old) == config_from_dict({"analysis": {"min_confidence": 0.6}})
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['relief_z'\] in config section \[analysis\]"):
        config_from_dict(old)
