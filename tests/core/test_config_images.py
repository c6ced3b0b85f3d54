"""Tests of lensdist_torch/config.py (the defaults of docs/method.md, TOML loading) and images.py
(docs/method.md section 1). Bad inputs: test_bad_config.py and test_bad_images.py."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from kornia.color import rgb_to_grayscale

from lensdist_torch import quality_map
from lensdist_torch.classify.eigenspace import N_NEIGHBOURS, REJECT_QUANTILE
from lensdist_torch.config import (
    ClassifierConfig,
    DistortionConfig,
    ImageConfig,
    LensdistConfig,
    ProtocolConfig,
    QualityConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from lensdist_torch.core.images import (
    as_batch,
    check_image,
    check_image_pair,
    load_image,
    load_scene,
    resize_to,
    scene_names,
    to_grey,
)
from lensdist_torch.data.synthesis import PERSPECTIVE, PERTURBATION, ROTATION_DEG, SCALE_RANGE, TX_RANGE, TY_RANGE
from lensdist_torch.geometry.distortion import N_CLASSES

# ----------------------------------------------------------------------------- config


class TestDefaults:
    def test_quality_defaults_are_the_method(self):
        q = QualityConfig()
        # docs/method.md sections 2-4
        assert (q.theta_g, q.theta_e, q.theta_d) == (0.02, 0.5, 0.1)
        assert (q.gamma, q.k, q.sigma) == (0.9879, -22.0, 0.8)
        assert q.block_size == 8
        assert q.min_block_ratio == 0.1
        assert all(t > 0 for t in (q.tau_g, q.tau_e, q.tau_d, q.tau_b))

    def test_other_sections_are_the_method(self):
        img = ImageConfig()
        assert (img.height, img.width) == (320, 424)
        assert (img.height // 8) * (img.width // 8) == 2120  # section 1: feature length
        d = DistortionConfig()
        assert (d.k2_max, d.k4_max, N_CLASSES) == (2.5e-6, 2.5e-11, 4)  # the last a constant now
        p = ProtocolConfig()
        assert (p.n_train, p.n_test_distorted, p.n_test_undistorted) == (12000, 400, 100)
        assert (TY_RANGE, TX_RANGE, SCALE_RANGE) == ((0.0, 40.0), (-4.0, 4.0), (0.98, 1.02))  # constants now
        assert ROTATION_DEG == 1.0 and (PERSPECTIVE, PERTURBATION) == (2e-5, 0.01)
        c = ClassifierConfig()
        assert c.n_eigenvectors in (5, 10) and (REJECT_QUANTILE, N_NEIGHBOURS) == (0.95, 4)  # constants now
        assert load_config(None) == LensdistConfig()

    def test_frozen(self):
        with pytest.raises(dataclasses.FrozenInstanceError):
            QualityConfig().theta_g = 0.1  # type: ignore[misc]

    def test_temperature_scale(self):
        q = QualityConfig()
        s = q.with_temperature_scale(0.5)
        for name in ("tau_g", "tau_e", "tau_d", "tau_b"):
            assert getattr(s, name) == getattr(q, name) * 0.5
        assert s.temperature == 0.5 and s.with_temperature_scale(4.0).tau_g == q.tau_g * 2.0
        for name in ("theta_g", "theta_e", "theta_d", "gamma", "k", "sigma", "block_size", "min_block_ratio"):
            assert getattr(s, name) == getattr(q, name)
        for bad in (0, -1.0, math.inf, math.nan):
            with pytest.raises(ValueError, match="factor"):
                q.with_temperature_scale(bad)

    @pytest.mark.parametrize(
        "kwargs,word",
        [
            ({"block_size": 0}, "block_size"),
            ({"block_size": 2.5}, "block_size"),
            ({"block_size": True}, "block_size"),
            ({"chunk_size": -1}, "chunk_size"),
            ({"theta_g": 0.0}, "theta_g"),
            ({"theta_g": math.nan}, "theta_g"),
            ({"theta_d": -0.1}, "theta_d"),
            ({"temperature": 0.0}, "temperature"),
            ({"temperature": math.inf}, "temperature"),
            ({"theta_e": 0.0}, "theta_e"),
            ({"theta_e": 0.9879}, "theta_e"),  # theta_e must stay below gamma
            ({"min_block_ratio": 1.5}, "min_block_ratio"),
            ({"temperature": True}, "temperature"),
        ],
    )
    def test_invalid_quality_values(self, kwargs, word):
        with pytest.raises(ValueError, match=word):
            QualityConfig(**kwargs)

    def test_invalid_other_values(self):
        with pytest.raises(ValueError, match="height"):
            ImageConfig(height=0)
        with pytest.raises(ValueError, match="metric"):
            ClassifierConfig(metric="delta_median")
        with pytest.raises(ValueError, match="relief"):
            ProtocolConfig(relief=-0.1)
        with pytest.raises(ValueError, match="scenes"):
            ProtocolConfig(scenes=())

    def test_image_size_must_fit_the_blocks(self):
        with pytest.raises(ValueError, match="block_size"):
            LensdistConfig(image=ImageConfig(height=321, width=424))
        with pytest.raises(ValueError, match="block_size"):
            LensdistConfig(quality=QualityConfig(block_size=10))  # 424 = 42.4 x 10
        cfg = LensdistConfig(quality=QualityConfig(block_size=16), image=ImageConfig(height=320, width=432))
        assert cfg.image.width % cfg.quality.block_size == 0


class TestLoadConfig:
    def test_overrides(self, tmp_path):
        path = tmp_path / "cfg.toml"
        path.write_text(
            "[quality]\n"
            "block_size = 4\n"
            "theta_e = 0.4\n"
            "temperature = 0.25\n"
            "[image]\n"
            "height = 64\n"
            "width = 96\n"
            "[protocol]\n"
            'scenes = ["grass"]\n'
            "n_train = 100\n"
        )
        cfg = load_config(path)
        assert cfg.quality == QualityConfig(block_size=4, theta_e=0.4, temperature=0.25)
        assert cfg.quality.theta_g == 0.02  # left out: the default
        assert (cfg.image.height, cfg.image.width) == (64, 96)
        assert cfg.protocol.scenes == ("grass",) and cfg.protocol.n_train == 100
        assert cfg.distortion == DistortionConfig() and cfg.classifier == ClassifierConfig()
        assert load_config(str(path)) == cfg
        # the loaded settings drive the metric
        x = torch.rand(1, 1, cfg.image.height, cfg.image.width)
        assert quality_map(x, x.flip(-1), config=cfg.quality).shape == (1, 1, 16, 24)

    def test_empty_file_gives_defaults(self, tmp_path):
        path = tmp_path / "empty.toml"
        path.write_text("# nothing\n")
        assert load_config(path) == LensdistConfig()

    @pytest.mark.parametrize(
        "text,words",
        [
            ("[qualty]\ntheta_g = 0.1\n", ["qualty"]),
            ("[quality]\ntheta_gg = 0.1\n", ["theta_gg", "quality"]),
            ("[image]\nheight = 320\ndepth = 3\n", ["depth", "image"]),
            ("theta_g = 0.1\n", ["theta_g"]),  # a key outside any section
        ],
    )
    def test_unknown_keys_and_sections(self, tmp_path, text, words):
        path = tmp_path / "bad.toml"
        path.write_text(text)
        with pytest.raises(ValueError) as info:
            load_config(path)
        for w in words:
            assert w in str(info.value)

    def test_bad_values_and_files(self, tmp_path):
        path = tmp_path / "bad.toml"
        path.write_text("[quality]\nblock_size = 10\n")  # 424 is not a multiple of 10
        with pytest.raises(ValueError, match="block_size"):
            load_config(path)
        path.write_text("[quality]\ntheta_e = 2.0\n")
        with pytest.raises(ValueError, match="theta_e"):
            load_config(path)
        path.write_text("[quality\ntheta_g = \n")
        with pytest.raises(ValueError, match="TOML"):
            load_config(path)
        with pytest.raises(FileNotFoundError):
            load_config(tmp_path / "missing.toml")

    def test_dict_round_trip(self):
        cfg = LensdistConfig(quality=QualityConfig(theta_g=0.03), protocol=ProtocolConfig(scenes=("gravel",)))
        data = config_to_dict(cfg)
        assert data["quality"]["theta_g"] == 0.03
        assert data["protocol"]["scenes"] == ["gravel"]  # tuples become lists (JSON, TOML)
        assert config_from_dict(data) == cfg
        with pytest.raises(TypeError):
            config_from_dict([("quality", {})])  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- images


class TestChecks:
    def test_check_image_names_the_argument(self):
        with pytest.raises(ValueError, match="warped"):
            check_image(torch.rand(3, 8, 8), "warped")
        with pytest.raises(TypeError, match="warped.*int32"):
            check_image(torch.zeros(1, 1, 8, 8, dtype=torch.int32), "warped")
        with pytest.raises(ValueError, match="warped.*empty"):
            check_image(torch.rand(1, 1, 0, 8), "warped")
        x = torch.rand(1, 1, 8, 8)
        assert check_image(x) is x
        nan = x.clone()
        nan[0, 0, 0, 0] = math.nan
        assert check_image(nan, finite=False) is nan
        with pytest.raises(ValueError, match="NaN"):
            check_image(nan)

    def test_check_image_pair(self):
        check_image_pair(torch.rand(1, 1, 12, 12), torch.rand(1, 1, 12, 12))  # no block size
        with pytest.raises(ValueError, match="block_size=8"):
            check_image_pair(torch.rand(1, 1, 12, 12), torch.rand(1, 1, 12, 12), 8)
        with pytest.raises(ValueError, match="same shape"):
            check_image_pair(torch.rand(1, 1, 8, 8), torch.rand(2, 1, 8, 8))


class TestGrey:
    def test_uint8_is_divided_by_255(self):
        u = torch.arange(256, dtype=torch.uint8).view(1, 1, 16, 16)
        g = to_grey(u)
        assert g.dtype == torch.float32
        assert float(g[0, 0, 0, 0]) == 0.0 and float(g[0, 0, -1, -1]) == 1.0
        assert torch.equal(g, u.float() / 255)

    def test_rgb_uses_itu_r_601_luma(self):
        rgb = torch.zeros(1, 3, 1, 4, dtype=torch.float64)
        rgb[0, 0, 0, 0] = 1  # red
        rgb[0, 1, 0, 1] = 1  # green
        rgb[0, 2, 0, 2] = 1  # blue
        rgb[0, :, 0, 3] = 1  # white
        g = to_grey(rgb)
        assert g.shape == (1, 1, 1, 4)
        luma = torch.tensor([0.299, 0.587, 0.114, 1.0], dtype=torch.float64)  # R, G, B, white
        torch.testing.assert_close(g.flatten(), luma, atol=1e-6, rtol=0)
        x = torch.rand(2, 3, 8, 8)
        assert torch.equal(to_grey(x), rgb_to_grayscale(x))
        u = (x * 255).to(torch.uint8)
        assert torch.equal(to_grey(u), rgb_to_grayscale(u.float() / 255))

    def test_grey_float_unchanged(self):
        x = torch.rand(1, 1, 8, 8, dtype=torch.float64)
        assert torch.equal(to_grey(x), x) and to_grey(x).dtype == torch.float64

    def test_as_batch(self):
        assert as_batch(torch.rand(8, 12)).shape == (1, 1, 8, 12)
        assert as_batch(torch.rand(3, 8, 12)).shape == (1, 3, 8, 12)
        assert as_batch(torch.rand(1, 1, 8, 12)).shape == (1, 1, 8, 12)
        with pytest.raises(ValueError, match="photo"):
            as_batch(torch.rand(2, 1, 8, 12), name="photo")
        with pytest.raises(TypeError, match="photo"):
            as_batch([[0.0]], name="photo")


class TestScenesAndFiles:
    def test_embedded_scenes(self):
        assert {"gravel", "grass"} <= set(scene_names())
        for name in ("gravel", "grass"):
            s = load_scene(name)
            assert s.shape == (1, 1, 512, 512) and s.dtype == torch.float32
            assert float(s.min()) >= 0 and float(s.max()) <= 1
            assert float(s.std()) > 0.05  # textured
            # 8-bit source: every value is k / 255
            torch.testing.assert_close(s * 255, (s * 255).round(), atol=1e-4, rtol=0)
        with pytest.raises(ValueError, match="gravel"):
            load_scene("marble")

    def test_load_image(self, tmp_path):
        from kornia.io import write_image

        g = torch.Generator().manual_seed(0)
        rgb = (torch.rand(3, 8, 16, generator=g) * 255).to(torch.uint8)
        path = tmp_path / "rgb.png"
        write_image(path, rgb)
        colour = load_image(path, grey=False)
        assert colour.shape == (1, 3, 8, 16) and colour.dtype == torch.float32
        assert torch.equal(colour, rgb.float()[None] / 255)
        assert torch.equal(load_image(path), rgb_to_grayscale(rgb.float()[None] / 255))
        grey = (torch.rand(1, 8, 16, generator=g) * 255).to(torch.uint8)
        write_image(tmp_path / "grey.png", grey)
        assert torch.equal(load_image(tmp_path / "grey.png"), grey.float()[None] / 255)
        with pytest.raises(FileNotFoundError):
            load_image(tmp_path / "missing.png")
        bad = tmp_path / "not_an_image.png"
        bad.write_bytes(b"this is not a png")
        with pytest.raises(ValueError, match="not_an_image"):
            load_image(bad)

    def test_resize_to(self):
        s = load_scene("gravel")
        r = resize_to(s, 320, 424)
        assert r.shape == (1, 1, 320, 424)
        assert float(r.min()) >= -1e-6 and float(r.max()) <= 1 + 1e-6
        # already the right size: unchanged
        assert torch.equal(resize_to(r, 320, 424), r)
        # a centre crop to the aspect ratio, then resampling: a constant image stays constant
        # and a left/right split stays centred
        wide = torch.zeros(1, 1, 100, 400)
        wide[..., 200:] = 1
        out = resize_to(wide, 40, 53)
        assert out.shape == (1, 1, 40, 53)
        torch.testing.assert_close(out[..., :26].max(), torch.tensor(0.0), atol=0.05, rtol=0)
        torch.testing.assert_close(out[..., 27:].min(), torch.tensor(1.0), atol=0.05, rtol=0)
        tall = torch.full((2, 3, 400, 100), 0.25)
        torch.testing.assert_close(resize_to(tall, 32, 24), torch.full((2, 3, 32, 24), 0.25))
