"""Bad configs end in a one-line ValueError naming the section and the field, never in a wrong
result (lensdist_torch/config.py); and the shipped config is the defaults, exactly."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from one_line import one_line_error

from lensdist_torch.config import (
    LensdistConfig,
    ProtocolConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)

PAPER = Path(__file__).resolve().parents[2] / "configs" / "paper.toml"




# ----------------------------------------------------------------------------- the good ones


class TestShippedConfig:
    def test_defaults_construct_and_every_section_too(self):
        cfg = LensdistConfig()
        for f in dataclasses.fields(cfg):
            section = getattr(cfg, f.name)
            assert type(section)() == section  # each section's defaults pass its own checks

    def test_paper_toml_is_the_defaults_exactly(self):
        assert load_config(PAPER) == LensdistConfig()
        assert load_config(str(PAPER)) == load_config(None)

    def test_paper_toml_writes_every_field(self):
        import tomllib

        with PAPER.open("rb") as f:
            data = tomllib.load(f)
        # every section, every key, same values; no key that became a constant of the method (config/retired.py)
        assert data == config_to_dict(LensdistConfig())

    def test_default_toml_is_gone(self):
        assert not (PAPER.parent / "default.toml").exists()

    def test_numbers_and_sequences_are_stored_canonically(self, tmp_path):
        path = tmp_path / "ints.toml"
        path.write_text('[protocol]\nrelief = 0\nscenes = ["grass"]\n[analysis]\nmin_motion_px = 2\n')
        cfg = load_config(path)
        assert cfg.protocol.relief == 0.0 and type(cfg.protocol.relief) is float
        assert cfg.analysis.min_motion_px == 2.0 and type(cfg.analysis.min_motion_px) is float
        assert cfg.protocol.scenes == ("grass",)
        # lists become tuples in direct construction as well (hashable, equal to the TOML form)
        q = ProtocolConfig(scenes=["grass"], unseen_scenes=[])  # type: ignore[arg-type]
        assert q.scenes == ("grass",) and q.unseen_scenes == ()
        hash(q)

    def test_round_trip_after_normalisation(self):
        cfg = LensdistConfig(protocol=ProtocolConfig(relief=0, scenes=["grass"]))  # type: ignore[arg-type]
        assert config_from_dict(config_to_dict(cfg)) == cfg


# ----------------------------------------------------------------------------- bad values in a TOML file

# (section, key, TOML value): each a distinct defect of one field
BAD_VALUES = [
    ("quality", "sigma", "0"),
    ("quality", "sigma", "-1"),
    ("quality", "sigma", "1.0"),
    ("quality", "k", "nan"),
    ("quality", "k", "0.0"),
    ("quality", "gamma", "1.5"),
    ("quality", "gamma", '"0.9879"'),
    ("quality", "block_size", "8.0"),
    ("quality", "block_size", "true"),
    ("quality", "theta_g", "inf"),
    ("quality", "theta_d", "-0.1"),
    ("quality", "min_block_ratio", "-0.1"),
    ("quality", "tau_d", "0.0"),  # a constant of the method now, refused at another value
    ("quality", "temperature", "0.0"),
    ("quality", "temperature", "true"),
    ("quality", "chunk_size", "0"),
    ("image", "height", '"320"'),
    ("image", "width", "-424"),
    ("distortion", "k2_max", "0.0"),
    ("distortion", "k4_max", "nan"),
    ("distortion", "n_classes", "5"),
    ("protocol", "seed", "1.5"),
    ("protocol", "seed", "1979-05-27"),
    ("protocol", "scenes", '"gravel"'),
    ("protocol", "scenes", "[]"),
    ("protocol", "scenes", '["gravel", 3]'),
    ("protocol", "scenes", '["gravel", "gravel"]'),
    ("protocol", "scenes", '["gravel", ""]'),
    ("protocol", "n_train", "-1"),
    ("protocol", "n_test_distorted", "1.5"),
    ("protocol", "ty_range", "[0.0]"),
    ("protocol", "ty_range", "[0.0, 40.0, 80.0]"),
    ("protocol", "ty_range", "40.0"),
    ("protocol", "tx_range", "[4.0, -4.0]"),
    ("protocol", "tx_range", "[0.0, nan]"),
    ("protocol", "tx_range", '["-4", "4"]'),
    ("protocol", "scale_range", "[0.0, 1.02]"),
    ("protocol", "scale_range", "[-1.0, 1.0]"),
    ("protocol", "rotation_deg", "-1.0"),
    ("protocol", "rotation_deg", "inf"),
    ("protocol", "perspective", "-2e-5"),  # constants of the method now: refused at another value, named
    ("protocol", "perspective", "nan"),
    ("protocol", "perturbation", "1.0"),
    ("protocol", "perturbation", "-0.01"),
    ("protocol", "relief", "0.5"),
    ("protocol", "occluder_rate", "-0.1"),
    ("protocol", "shard_size", "0"),
    ("registration", "levels", "[0, 2]"),
    ("registration", "levels", "[2, 1]"),
    ("registration", "levels", "[]"),
    ("registration", "iterations", "[10]"),
    ("registration", "iterations", "[10, 0]"),
    ("registration", "presmooth", "1"),
    ("registration", "step_tol", "0.0"),
    ("registration", "damping", "-1e-6"),
    ("registration", "margin", "nan"),
    ("registration", "min_overlap", "1.5"),
    ("registration", "phase_level", "-1"),
    ("registration", "fine_stride", "0"),
    ("registration", "chunk_size", "2.0"),
    ("registration", "max_residual", "0.0"),
    ("registration", "feature_fallback", "1"),
    ("classifier", "metric", '"delta_median"'),
    ("classifier", "metric", "1"),
    ("classifier", "reject_quantile", "0.0"),
    ("classifier", "n_eigenvectors", "0"),
    ("classifier", "n_neighbours", "false"),
    ("selfcal", "levels", "0"),
    ("selfcal", "iterations", "[12, 6]"),
    ("selfcal", "sample_block", "[2, 4, 0]"),
    ("selfcal", "newton", "-5"),
    ("selfcal", "noise_floor", "0.0"),
    ("selfcal", "ridge", "inf"),
    ("selfcal", "confidence_threshold", "2.0"),  # a constant of the method now: refused at another value, named
    ("selfcal", "occluded_share", "1.0"),  # a share of the frame's rectangles left out, below 1
    ("selfcal", "min_overlap", "nan"),
    ("selfcal", "margin", "-1.0"),
    ("regression", "k", "0"),
    ("regression", "k", "11000"),
    ("regression", "n_components", "3.5"),
    ("regression", "cannot_tell_fraction", "-0.1"),
    ("regression", "cannot_tell_fraction", "1000.0"),  # a share of the class range: 1000 read as confident
    ("analysis", "max_delta_disagreement", "1.5"),  # a constant of the method now: refused at another value, named
    ("analysis", "max_cannot_tell", "1.5"),
    ("registration", "max_step", "2.0"),
    ("regression", "confidence_threshold", "nan"),
    ("analysis", "no_distortion_px", "0.0"),
    ("analysis", "min_overlap", "-0.5"),  # constants of the method now: refused at another value, named
    ("analysis", "out_of_domain_factor", "inf"),
    ("analysis", "min_confidence", "-0.5"),
    ("analysis", "relief_mass", "inf"),
    ("analysis", "eigenspace_max_class_disagreement", "-1"),
    ("analysis", "min_motion_px", "0.0"),  # every method would answer on the same image twice
    ("analysis", "min_motion_px", "-1.0"),
    ("analysis", "flat_prior", "1.5"),  # a weight of the planar model, in [0, 1]
    ("analysis", "flat_prior", "-0.1"),
]


@pytest.mark.bad_input
@pytest.mark.parametrize("section,key,value", BAD_VALUES, ids=[f"{s}.{k}={v}" for s, k, v in BAD_VALUES])
def test_bad_value_in_toml(tmp_path, section, key, value):
    path = tmp_path / "bad.toml"
    path.write_text(f"[{section}]\n{key} = {value}\n")
    one_line_error(ValueError, lambda: load_config(path), f"{section}.{key}", str(path))


# (section, field, value) in Python: the section's class built with the one bad field
BAD_PYTHON_VALUES = [
    ("quality", "temperature", 0.0),
    ("quality", "temperature", math.nan),
    ("quality", "theta_e", 0.99),  # above gamma
    ("image", "height", 320.0),
    ("distortion", "k2_max", -1.0),
    ("protocol", "scenes", "grass"),  # not iterated as characters
    ("protocol", "relief", 0.5),
    ("protocol", "unseen_scenes", ("gravel",)),  # a training scene
    ("protocol", "seed", True),
    ("protocol", "scenes", ("grass", None)),
    ("registration", "chunk_size", 1.5),
    ("classifier", "metric", None),
    ("selfcal", "parallax", 2.5),
    ("regression", "k", True),
    ("analysis", "min_confidence", "0.5"),
]


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "section,key,value", BAD_PYTHON_VALUES, ids=[f"{s}.{k}={v!r}" for s, k, v in BAD_PYTHON_VALUES]
)
def test_bad_value_in_python(section, key, value):
    cls = type(getattr(LensdistConfig(), section))  # QualityConfig for "quality", ...
    one_line_error(ValueError, lambda: cls(**{key: value}), f"{section}.{key}")


# ----------------------------------------------------------------------------- bad structure


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "text,words",
    [
        ("quality = 5\n", ["quality", "table"]),  # a section that is not a table
        ('protocol = ["gravel"]\n', ["protocol", "table"]),
        ("sigma = 0.8\n", ["sigma", "outside any section"]),  # a key before any [section]
        ("[quality.sub]\nsigma = 0.8\n", ["sub", "[quality]"]),  # a sub-table is an unknown key
        ("[protocol]\nscenes = [[\"gravel\"]]\n", ["protocol.scenes"]),  # nested array
    ],
)
def test_bad_structure_in_toml(tmp_path, text, words):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    one_line_error(ValueError, lambda: load_config(path), str(path), *words)


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "data,words",
    [
        ({"quality": "sigma=0.8"}, ["[quality]", "table"]),
        ({"image": [320, 424]}, ["[image]", "table"]),
        ({"quality": {"sigma": "0.8"}}, ["quality.sigma"]),
        ({"protocol": {"ty_range": {"low": 0, "high": 40}}}, ["protocol.ty_range"]),
    ],
)
def test_bad_structure_in_dict(data, words):
    one_line_error(ValueError, lambda: config_from_dict(data), *words)


@pytest.mark.bad_input
def test_section_of_the_wrong_type():
    one_line_error(
        ValueError, lambda: LensdistConfig(quality={"sigma": 0.8}), "quality", "QualityConfig"  # type: ignore[arg-type]
    )


@pytest.mark.bad_input
def test_config_file_not_utf8(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes("# caf\xe9\n[quality]\nsigma = 0.8\n".encode("latin-1"))
    one_line_error(ValueError, lambda: load_config(path), str(path), "UTF-8")


@pytest.mark.bad_input
def test_config_file_with_a_utf8_byte_order_mark(tmp_path):
    """A Windows editor's UTF-8 BOM is skipped: the file loads as without it (was refused as
    "not valid TOML" at line 1, column 1, without saying why)."""
    text = "[quality]\ntheta_e = 0.75\n"
    plain, bom = tmp_path / "plain.toml", tmp_path / "bom.toml"
    plain.write_text(text)
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert load_config(bom) == load_config(plain) != LensdistConfig()
    assert load_config(bom).quality.theta_e == 0.75


@pytest.mark.bad_input
@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-be"])
def test_config_file_utf16_says_byte_order_mark(tmp_path, encoding):
    path = tmp_path / "c.toml"
    data = "[quality]\ntheta_e = 0.75\n".encode(encoding)
    path.write_bytes(data if encoding == "utf-16" else b"\xfe\xff" + data)
    one_line_error(ValueError, lambda: load_config(path), str(path), "UTF-16 byte-order mark", "UTF-8")


@pytest.mark.bad_input
def test_config_path_is_a_directory(tmp_path):
    one_line_error(ValueError, lambda: load_config(tmp_path), str(tmp_path), "not a file")


@pytest.mark.bad_input
def test_cli_refuses_a_bad_config_before_writing_anything(tmp_path, capsys):
    """The audit's case: sigma = 0 used to write a data set of all-zero maps and exit 0."""
    from lensdist_torch.cli import main as cli_main

    path = tmp_path / "sigma0.toml"
    path.write_text("[quality]\nsigma = 0\n")
    out = tmp_path / "data"
    code = cli_main(["generate", "--config", str(path), "--out", str(out), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "quality.sigma" in err and err.count("\n") == 1
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.bad_input
def test_unseen_scenes_must_not_be_training_scenes():
    with pytest.raises(ValueError, match=r"^protocol.unseen_scenes must share no scene with protocol.scenes.*'gravel'"):
        ProtocolConfig(scenes=("gravel", "grass"), unseen_scenes=("gravel",))
    assert ProtocolConfig(unseen_scenes=()).unseen_scenes == ()  # empty: no unseen test


def test_unseen_scenes_are_not_in_the_data_fingerprint():
    from lensdist_torch.data.manifest import config_fingerprint

    a, b = LensdistConfig(), LensdistConfig(protocol=ProtocolConfig(unseen_scenes=()))
    c = LensdistConfig(protocol=ProtocolConfig(seed=1))
    assert config_fingerprint(a, ["x"]) == config_fingerprint(b, ["x"]) != config_fingerprint(c, ["x"])
