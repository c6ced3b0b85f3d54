"""Keys that became constants of the method: a file or a stored config naming one never silently changes meaning.

The one table is :data:`lensdist_torch.config.retired.RETIRED`; a key at its constant's value
loads (dropped), at any other value it is a one-line error naming the key, the file and the
constant.
"""

from __future__ import annotations

import pytest
from one_line import one_line_error

from lensdist_torch.config import LensdistConfig, config_from_dict, load_config, retired_keys, stored_config
from lensdist_torch.config.retired import RETIRED, Retired

FAKE = ("quality", "old_margin")  # a key of an earlier version, a constant now: the mechanism, whatever the table holds


@pytest.fixture
def fake_constant(monkeypatch):
    monkeypatch.setitem(RETIRED, FAKE, Retired(by="lensdist_torch.calibration.direct.OLD_MARGIN", value=(0.5, 2.0)))


def test_a_removed_key_at_the_constant_loads_and_is_dropped(fake_constant, tmp_path):
    path = tmp_path / "old.toml"
    path.write_text("[quality]\nold_margin = [0.5, 2]\nblock_size = 16\n[image]\nheight = 320\nwidth = 416\n")
    assert load_config(path).quality.block_size == 16
    assert stored_config({"quality": {"old_margin": [0.5, 2.0]}}) == LensdistConfig()  # a checkpoint's config
    assert retired_keys({"quality": {"old_margin": [0.5, 2.0]}}) == []  # loads as it is: a data set's too


@pytest.mark.bad_input
@pytest.mark.parametrize("value", ["[0.5, 3.0]", "[0.5]", "0.5", "true", "'0.5, 2'"])
def test_a_removed_key_at_another_value_is_one_line(fake_constant, tmp_path, value):
    path = tmp_path / "old.toml"
    path.write_text(f"[quality]\nold_margin = {value}\n")
    one_line_error(ValueError, lambda: load_config(path), "quality.old_margin", str(path),
                   "a constant of the method now: lensdist_torch.calibration.direct.OLD_MARGIN")
    one_line_error(ValueError, lambda: stored_config({"quality": {"old_margin": [1.0, 2.0]}}), "quality.old_margin")
    assert retired_keys({"quality": {"old_margin": [1.0, 2.0]}}) == ["quality.old_margin"]


def test_every_constant_of_the_table_is_the_modules():
    """The table's value of each key that became a constant is the constant's, in the module that names it."""
    import importlib

    for (section, key), r in RETIRED.items():
        if r.value is None:
            continue
        module, name = r.by.rsplit(".", 1)
        assert getattr(importlib.import_module(module), name) == r.value, (section, key)
        assert key not in config_from_dict({}).__getattribute__(section).__dataclass_fields__, (section, key)


def test_a_direct_path_key_of_an_earlier_version(tmp_path):
    """``[calibration] outlier_mads`` became ``pooling.OUTLIER_MADS``: at 4 it loads, at 5 it is refused."""
    from lensdist_torch.calibration.pooling import OUTLIER_MADS

    path = tmp_path / "old.toml"
    path.write_text(f"[calibration]\noutlier_mads = {OUTLIER_MADS}\nmotion_steps = [0.14, 0.22]\nparallax = 0\n")
    assert load_config(path).selfcal.parallax == 0  # moved: one relief model for a pair and a sequence
    path.write_text("[calibration]\noutlier_mads = 5.0\n")
    one_line_error(ValueError, lambda: load_config(path), "calibration.outlier_mads", str(path),
                   "a constant of the method now: lensdist_torch.calibration.pooling.OUTLIER_MADS")


@pytest.mark.bad_input
def test_calibrate_refuses_a_changed_constant_with_one_line(tmp_path, capsys):
    from lensdist_torch.cli import main as cli_main

    (tmp_path / "frames").mkdir()
    path = tmp_path / "old.toml"
    path.write_text("[calibration]\nmax_motion = 0.5\n")
    assert cli_main(["calibrate", str(tmp_path / "frames"), "--config", str(path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "calibration.max_motion" in err and str(path) in err
    assert "a constant of the method now: lensdist_torch.calibration.direct.MAX_MOTION" in err


def test_a_self_calibration_key_of_an_earlier_version(tmp_path):
    """``[selfcal] noise_floor`` became ``selfcal.model.NOISE_FLOOR``: as paper.toml wrote it, it loads."""
    path = tmp_path / "old.toml"
    path.write_text("[selfcal]\nnoise_floor = 0.00196078431372549\ngain_range = [0.25, 4]\nnewton = 5\nparallax = 0\n")
    assert load_config(path).selfcal.parallax == 0
    path.write_text("[selfcal]\nhuber_k = 2.0\n")
    one_line_error(ValueError, lambda: load_config(path), "selfcal.huber_k", str(path),
                   "a constant of the method now: lensdist_torch.selfcal.model.HUBER_K")
    one_line_error(ValueError, lambda: stored_config({"selfcal": {"ridge": 1e-9}}), "selfcal.ridge",
                   "lensdist_torch.selfcal.prior.RIDGE")
    path.write_text("[selfcal]\nconfidence_threshold = 0.5\nchunk_size = 4\n")
    assert load_config(path) == config_from_dict({"selfcal": {"chunk_size": 4}})
    path.write_text("[selfcal]\nconfidence_threshold = 0.6\n")
    one_line_error(ValueError, lambda: load_config(path), "selfcal.confidence_threshold", str(path),
                   "a constant of the method now: lensdist_torch.selfcal.fit.CONFIDENCE_THRESHOLD")
    # the score test's level, a constant of issue 50 whose value changed since: inert, a decision made per pair
    assert stored_config({"selfcal": {"parallax_score_level": 1.0, "chunk_size": 4}}).selfcal.chunk_size == 4
    path.write_text("[selfcal]\nparallax_score_level = 1.0\n")
    one_line_error(ValueError, lambda: load_config(path), "parallax_score_level", str(path))


def test_a_moved_key_loads_in_its_new_place(tmp_path):
    """``[calibration] parallax`` is ``[selfcal] parallax``, ``[multiview] confidence`` ``[calibration] confidence``:
    a file or a stored config naming the old place loads there; both places at different values are refused."""
    path = tmp_path / "old.toml"
    path.write_text("[calibration]\nparallax = 0\nmax_pairs = 8\n[multiview]\nconfidence = 0.9\n")
    cfg = load_config(path)
    assert (cfg.selfcal.parallax, cfg.calibration.max_pairs, cfg.calibration.confidence) == (0, 8, 0.9)
    assert stored_config({"calibration": {"parallax": 3}}).selfcal.parallax == 3
    assert config_from_dict({"calibration": {"parallax": 5}, "selfcal": {"parallax": 5}}) == LensdistConfig()
    path.write_text("[calibration]\nparallax = 0\n[selfcal]\nparallax = 5\n")
    one_line_error(ValueError, lambda: load_config(path), "calibration.parallax", "selfcal.parallax", str(path))
    one_line_error(ValueError, lambda: config_from_dict({"multiview": {"confidence": 0.9},
                                                         "calibration": {"confidence": 0.95}}),
                   "multiview.confidence", "calibration.confidence")
    assert retired_keys({"calibration": {"parallax": 0}}) == []  # it loads: not a key that must be refitted
    path.write_text("[multiview]\nconfidence = 1.5\n")  # a bad value names the key the user wrote too
    one_line_error(ValueError, lambda: load_config(path), "calibration.confidence", "written as multiview.confidence",
                   str(path))
    # a stored config of an earlier version names both places (it wrote every field): the new one stands
    old = {"calibration": {"parallax": 5, "confidence": 0.9}, "multiview": {"confidence": 0.95},
           "selfcal": {"parallax": 0}}
    cfg = stored_config(old)
    assert (cfg.selfcal.parallax, cfg.calibration.confidence) == (0, 0.9)
    # the same value in both places keeps the new place's value as written
    assert config_from_dict({"calibration": {"parallax": 5.0}, "selfcal": {"parallax": 5}}).selfcal.parallax == 5


def test_calibrate_reads_one_coverage(tmp_path):
    """``calibrate_path``'s ``config`` is the ``[calibration]`` of every path; ``settings.calibration`` where None."""
    from lensdist_torch.calibration.controllers.calibrate import calibrate_path, synthetic_sequence
    from lensdist_torch.config import CalibrationConfig
    from lensdist_torch.core.png import encode_png, to_uint8

    for i, frame in enumerate(synthetic_sequence(6, 1e-5, 0.0, size=(120, 160))[0]):
        (tmp_path / f"frame_{i}.png").write_bytes(encode_png(to_uint8(frame)))
    ninety = CalibrationConfig(confidence=0.9)
    by_settings = calibrate_path(tmp_path, method="direct", settings=LensdistConfig(calibration=ninety), quiet=True)
    by_config = calibrate_path(tmp_path, method="direct", config=ninety, quiet=True)
    default = calibrate_path(tmp_path, method="direct", quiet=True)
    assert by_settings["confidence"] == by_config["confidence"] == 0.9 and default["confidence"] == 0.95
    assert by_settings["delta_avg_user_interval"] == by_config["delta_avg_user_interval"]
    lo, hi = by_settings["delta_avg_user_interval"]
    dlo, dhi = default["delta_avg_user_interval"]
    assert dlo < lo < hi < dhi  # a 90 % interval inside the 95 % one


def test_a_metric_key_of_an_earlier_version(tmp_path):
    """``[quality] tau_g`` became ``config.quality.TAU_G`` (scaled by ``temperature``): as written before, it loads."""
    path = tmp_path / "old.toml"
    path.write_text("[quality]\n" + "".join(f"{k} = {v}\n" for k, v in OLD_QUALITY.items()) + "theta_e = 0.4\n")
    assert load_config(path).quality == config_from_dict({"quality": {"theta_e": 0.4}}).quality
    path.write_text("[quality]\ntau_g = 0.001\n")
    one_line_error(ValueError, lambda: load_config(path), "quality.tau_g", str(path),
                   "a constant of the method now: lensdist_torch.config.quality.TAU_G")
    one_line_error(ValueError, lambda: stored_config({"quality": {"gamma": 0.9}}), "quality.gamma",
                   "lensdist_torch.config.quality.GAMMA")


def test_a_registration_key_of_an_earlier_version(tmp_path):
    """``[registration] levels`` became ``registration.direct.LEVELS``: as paper.toml wrote it, it loads."""
    path = tmp_path / "old.toml"
    path.write_text("[registration]\nlevels = [2, 0]\niterations = [10, 6]\ndamping = 1e-06\nmin_texture = 1e-08\n"
                    "margin = 2.0\npresmooth = true\nmatch_intensity = true\nmin_inliers = 15\nchunk_size = 4\n")
    assert load_config(path).registration.chunk_size == 4
    path.write_text("[registration]\nlevels = [3, 1, 0]\n")
    one_line_error(ValueError, lambda: load_config(path), "registration.levels", str(path),
                   "a constant of the method now: lensdist_torch.registration.direct.LEVELS")
    path.write_text("[registration]\nmatch_intensity = false\n")
    one_line_error(ValueError, lambda: load_config(path), "registration.match_intensity", str(path),
                   "lensdist_torch.registration.direct.MATCH_INTENSITY")
    one_line_error(ValueError, lambda: stored_config({"registration": {"min_inliers": 10}}),
                   "registration.min_inliers", "lensdist_torch.registration.wide_baseline.MIN_INLIERS")


#: ``[registration]`` of every data set generated before its constants left the config, as the config wrote it.
OLD_REGISTRATION = {
    "levels": [2, 0], "iterations": [10, 6], "step_tol": 0.01, "coarse_tol": 0.2, "phase_level": 3, "damping": 1e-6,
    "min_texture": 1e-8, "min_overlap": 0.3, "max_residual": 0.5, "margin": 2.0, "max_step": 0.25, "fine_stride": 2,
    "presmooth": True, "match_intensity": True, "chunk_size": 8, "feature_fallback": True, "max_keypoints": 2000,
    "match_ratio": 0.9, "ransac_threshold": 2.0, "min_inliers": 15,
}


#: ``[protocol]``'s keys that became constants of the method, as every data set generated before wrote them.
OLD_PROTOCOL = {"perspective": 2e-5, "perturbation": 0.01, "occluder_area": [0.05, 0.15], "ty_range": [0.0, 40.0],
                "tx_range": [-4.0, 4.0], "rotation_deg": 1.0, "scale_range": [0.98, 1.02], "gain_range": [0.7, 1.3],
                "offset_range": [-0.1, 0.1], "gamma_range": [0.8, 1.25], "illumination": 0.25,
                "noise_range": [0.0, 0.02], "jpeg_quality": [60, 95], "occluder_rate": 0.2}


#: ``[quality]``'s keys that became constants of the method (the temperatures: ``temperature`` 1), as written before.
OLD_QUALITY = {"gamma": 0.9879, "k": -22.0, "sigma": 0.8, "tau_g": 0.004, "tau_e": 0.05, "tau_d": 0.02, "tau_b": 0.02}


def test_the_data_fingerprint_hashes_the_retired_keys_as_before():
    """The retired keys are hashed at their constants' values: a data set generated before keeps its fingerprint."""
    from pathlib import Path

    from lensdist_torch.config import config_to_dict
    from lensdist_torch.data.manifest import _data_fields, config_fingerprint

    fields = _data_fields(LensdistConfig())
    old = {k: v for k, v in OLD_REGISTRATION.items()  # chunk_size and the fallback's were never hashed
           if k not in ("chunk_size", "feature_fallback", "max_keypoints", "match_ratio", "ransac_threshold",
                        "min_inliers")}
    assert fields["registration"] == old and len(old) == 14
    assert all(type(fields["registration"][k]) is type(v) for k, v in old.items())  # 2.0 stays a float, [2, 0] a list
    assert all(type(fields["protocol"][k]) is type(v) for k, v in OLD_PROTOCOL.items())
    assert all(type(x) is int for x in fields["protocol"]["jpeg_quality"])  # ints, as the config stored them
    others = {s: dict(config_to_dict(LensdistConfig())[s]) for s in ("quality", "image", "distortion", "protocol")}
    others["quality"].pop("chunk_size"), others["protocol"].pop("unseen_scenes")  # as before: not hashed
    assert others["quality"].pop("temperature") == 1.0  # hashed as the four temperatures it scales
    assert fields == {**others, "protocol": {**others["protocol"], **OLD_PROTOCOL}, "registration": old,
                      "distortion": {**others["distortion"], "n_classes": 4},
                      "quality": {**others["quality"], **OLD_QUALITY}}
    sharp = _data_fields(config_from_dict({"quality": {"temperature": 0.5}}))["quality"]
    assert (sharp["tau_g"], sharp["tau_b"]) == (0.002, 0.01) and "temperature" not in sharp
    assert type(fields["distortion"]["n_classes"]) is int
    # as the old code made them: the default protocol, with and without scenes, and the two realistic conditions
    assert config_fingerprint(LensdistConfig(), ["gravel", "grass"]) == "aa65403107c95ae1"
    assert config_fingerprint(LensdistConfig(), []) == "57d173dc8ee860f9"
    configs = Path(__file__).resolve().parents[2] / "configs"
    for name, fingerprint in (("realistic", "2afd8774946456f6"), ("realistic_relief", "7b3af95e40432cd4")):
        assert config_fingerprint(load_config(configs / f"{name}.toml"), ["gravel", "grass"]) == fingerprint, name


def test_a_manifest_of_an_earlier_version_still_reads(tmp_path):
    """A data set's manifest naming every old ``[registration]`` and ``[protocol]`` key reads as it is; at another
    value it is refused."""
    import json

    from lensdist_torch.config import config_to_dict
    from lensdist_torch.data.manifest import FORMAT_VERSION, ShardError, read_manifest

    default = config_to_dict(LensdistConfig())
    quality = {k: v for k, v in default["quality"].items() if k != "temperature"}
    config = {**default, "protocol": {**default["protocol"], **OLD_PROTOCOL}, "registration": OLD_REGISTRATION,
              "quality": {**quality, **OLD_QUALITY}}
    m = {"format_version": FORMAT_VERSION, "fingerprint": "aa65403107c95ae1", "config": config,
         "scenes": ["gravel", "grass"], "sets": {}}
    (tmp_path / "manifest.json").write_text(json.dumps(m, allow_nan=False))
    assert read_manifest(tmp_path)["fingerprint"] == "aa65403107c95ae1"
    for section, key, value in (("registration", "levels", [3, 1, 0]), ("protocol", "perspective", 1e-4)):
        m["config"] = {**config, section: {**config[section], key: value}}
        (tmp_path / "manifest.json").write_text(json.dumps(m, allow_nan=False))
        with pytest.raises(ShardError, match=rf"earlier version of the pair protocol \({section}\.{key}\)"):
            read_manifest(tmp_path)


def test_a_protocol_key_of_an_earlier_version(tmp_path):
    """``[protocol] occluder_area`` became ``data.realism.OCCLUDER_AREA``: as paper.toml wrote it, it loads."""
    path = tmp_path / "old.toml"
    path.write_text("[protocol]\nperspective = 2e-5\nperturbation = 0.01\noccluder_area = [0.05, 0.15]\n"
                    "relief = 0.02\n")
    assert load_config(path) == config_from_dict({"protocol": {"relief": 0.02}})
    path.write_text("[protocol]\noccluder_area = [0.05, 0.3]\n")
    one_line_error(ValueError, lambda: load_config(path), "protocol.occluder_area", str(path),
                   "a constant of the method now: lensdist_torch.data.realism.OCCLUDER_AREA")
    one_line_error(ValueError, lambda: stored_config({"protocol": {"perturbation": 0.02}}), "protocol.perturbation",
                   "lensdist_torch.data.synthesis.PERTURBATION")


#: The ``[analysis]`` keys that became constants of the method, as paper.toml and every stored config wrote them.
OLD_ANALYSIS = {
    "min_overlap": 0.5, "out_of_domain_factor": 2.0, "selfcal_confidence_scale": 1.0, "selfcal_confidence_shift": 0.0,
    "max_class_disagreement": 1, "max_delta_disagreement": 0.25, "texture_factor": 2.0,
    "validation_seed_offset": 1, "interval_confidence": 0.95, "target_precision": 0.97,
}


def test_an_analysis_key_of_an_earlier_version(tmp_path):
    """``[analysis] texture_factor`` became ``workflows.decision.TEXTURE_FACTOR``: as paper.toml wrote it, it loads."""
    import json

    path = tmp_path / "old.toml"
    old = "".join(f"{k} = {json.dumps(v)}\n" for k, v in OLD_ANALYSIS.items())
    path.write_text(f"[analysis]\n{old}min_confidence = 0.6\n")
    assert load_config(path) == config_from_dict({"analysis": {"min_confidence": 0.6}})
    path.write_text("[analysis]\nout_of_domain_factor = 3\n")
    one_line_error(ValueError, lambda: load_config(path), "analysis.out_of_domain_factor", str(path),
                   "a constant of the method now: lensdist_torch.workflows.analyze.OUT_OF_DOMAIN_FACTOR")
    path.write_text("[analysis]\ntexture_factor = 3.0\n")
    one_line_error(ValueError, lambda: load_config(path), "analysis.texture_factor", str(path),
                   "lensdist_torch.workflows.decision.TEXTURE_FACTOR")
    one_line_error(ValueError, lambda: stored_config({"analysis": {"interval_confidence": 0.9}}),
                   "analysis.interval_confidence", "lensdist_torch.workflows.class_mass.INTERVAL_CONFIDENCE")


@pytest.mark.parametrize("name", ["eigenspace_delta_avg_10ev.pt", "eigenspace_delta_max_10ev.pt", "regression.pt"])
def test_the_shipped_checkpoints_name_the_retired_keys_and_load(name):
    """Their stored configs hold retired keys at the constants' values: loaded, the config is as stored, less those."""
    from pathlib import Path

    import torch

    from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
    from lensdist_torch.classify.regression import DeltaRegressor
    from lensdist_torch.config import config_to_dict

    path = Path(__file__).resolve().parents[2] / "lensdist_torch" / "checkpoints" / name
    stored = torch.load(path, weights_only=True)["config"]
    constants = {key for key, r in RETIRED.items() if r.value is not None}
    named = {(s, k) for s, keys in stored.items() for k in keys if (s, k) in constants}
    assert {("analysis", k) for k in OLD_ANALYSIS} & named and ("registration", "levels") in named
    loaded = config_to_dict((DeltaRegressor if name == "regression.pt" else EigenSpaceClassifier).load(path).config)
    for section, values in loaded.items():  # every kept key as stored (a key the stored config lacks: its default)
        assert {k: v for k, v in values.items() if k in stored.get(section, {})} == {
            k: v for k, v in stored.get(section, {}).items() if k in values}, section


@pytest.mark.parametrize("name", ["calibration_default", "calibration_realistic", "calibration_realistic_relief"])
def test_the_fitted_decisions_in_the_results_load(name):
    """`lensdist reproduce` wrote these configs (docs/results/README.md): a user passes them with --config."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "docs" / "results" / f"{name}.toml"
    cfg = load_config(path)
    assert 0 < cfg.analysis.no_distortion_px < 1 and cfg.analysis != LensdistConfig().analysis  # its fitted decision


#: Keys that became constants of the method in issue 50's pass over the config, as paper.toml and every stored
#: config wrote them (section -> key -> the old default).
OLD_ISSUE_50 = {
    "distortion": {"n_classes": 4},
    "classifier": {"reject_quantile": 0.95, "n_neighbours": 4},
    "regression": {"cannot_tell_fraction": 0.125, "confidence_threshold": 0.5},
    "analysis": {"eigenspace_max_class_disagreement": 0, "max_cannot_tell": 0.25},
    "registration": {"min_overlap": 0.3, "max_residual": 0.5, "feature_fallback": True},
    "protocol": {k: v for k, v in OLD_PROTOCOL.items() if k not in ("perspective", "perturbation", "occluder_area")},
    "selfcal": {"robust": "tukey", "photometric": "gain_bias", "levels": 3, "iterations": [8, 4, 6],
                "sample_block": [2, 4, 4], "interpolation": "blend", "both_starts": True, "clusters": 6,
                "occluded_share": 0.15, "small_motion_error": 1.5e-5, "parallax_test": 2.0},
    "calibration": {"max_misfit": 0.4, "relief_rel": 0.8, "relief_test": 2.0, "no_distortion_px": 0.25,
                    "verify_pairs": 6, "registered_start": True},
}


def test_the_keys_of_issue_50_load_at_their_old_defaults(tmp_path):
    """Each loads at its old default (dropped) and is refused at another value, one line naming its constant."""
    import json

    path = tmp_path / "old.toml"
    path.write_text("".join(f"[{s}]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in keys.items())
                            for s, keys in OLD_ISSUE_50.items()))
    assert load_config(path) == LensdistConfig()
    assert stored_config(OLD_ISSUE_50) == LensdistConfig() and retired_keys(OLD_ISSUE_50) == []
    for section, keys in OLD_ISSUE_50.items():
        for key, value in keys.items():
            other = (not value) if isinstance(value, bool) else [v + 1 for v in value] if isinstance(value, list) \
                else value + "x" if isinstance(value, str) else value + 1
            path.write_text(f"[{section}]\n{key} = {json.dumps(other)}\n")
            one_line_error(ValueError, lambda: load_config(path), f"{section}.{key}", str(path),
                           f"a constant of the method now: {RETIRED[(section, key)].by}")
