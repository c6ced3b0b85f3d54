"""Keys an earlier version read that this one does not, and how a file or a stored config naming one loads.

One table, :data:`RETIRED`: (section, key) -> a :class:`Retired` saying what replaced the key.
A key that became a constant of the method (the value every config file and stored checkpoint
held) loads where it holds that constant's value, and is dropped: it means what the constant
does. Any other value is a one-line ``ValueError`` naming the key and the constant, never a
silent change of meaning. A key that moved to another section loads as that key (a one-line
``ValueError`` where both are given and differ). The other retired keys are refused in a user's file (an unknown key)
and dropped from a stored config where they had no effect (``stored_config``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lensdist_torch.config.checks import show

__all__ = ["INERT", "RETIRED", "Retired", "drop_constants", "moved_names", "retired_keys", "settle_moves",
           "without_key"]


@dataclass(frozen=True)
class Retired:
    """What replaced a key of an earlier version.

    Attributes:
        by: what replaced it: a key of this version (with why), or, for a key that became a
            constant of the method, the constant's dotted name (``lensdist_torch.calibration.X.NAME``,
            ``lensdist_torch.selfcal.X.NAME``, ``lensdist_torch.registration.X.NAME``,
            ``lensdist_torch.workflows.X.NAME``, ``lensdist_torch.data.X.NAME``,
            ``lensdist_torch.classify.X.NAME``, ``lensdist_torch.geometry.X.NAME``,
            ``lensdist_torch.config.X.NAME``).
        value: for a constant, its value: the key loads at this value (dropped) and is refused
            at any other; None for the others.
        inert: it never shaped a fitted model or a data set (a decision made at analysis time):
            dropped wherever a saved config is read.
        moved: the (section, key) it became, meaning the same: a file or stored config naming it
            loads it there.

    Example:
        >>> RETIRED[("analysis", "relief_z")].inert, RETIRED[("protocol", "parallax_px")].value
        (True, None)
    """

    by: str
    value: Any = None
    inert: bool = False
    moved: tuple[str, str] | None = None


def _constant(name: str, value: Any, package: str = "calibration") -> Retired:
    return Retired(by=f"lensdist_torch.{package}.{name}", value=value)


def _moved(section: str, key: str, why: str) -> Retired:
    return Retired(by=f"{section}.{key} ({why})", moved=(section, key))


#: Keys an earlier version wrote that this one no longer reads: (section, key) -> what replaced it.
#: Keys whose rule another replaced, a decision made at analysis time.
_BY_CLASS_RULE = Retired(by="the class rule every path of calibrate shares, a class where the whole interval lies in "
                            "one (lensdist_torch.calibration.sequence_class.interval_class)", inert=True)
_BY_EVIDENCE = Retired(by="the homography model's lens models weighed by how well each predicts held-out pairs "
                          "(lensdist_torch.calibration.planar_evidence)", inert=True)

RETIRED = {
    ("protocol", "parallax_px"): Retired(
        by="protocol.relief (a scene's relief; the parallax follows each pair's motion)"),
    ("analysis", "relief_z"): Retired(
        by="analysis.flat_prior (both models of the scene weighed in a pair's confidence; relief where their "
           "classes differ)", inert=True),
    # the direct path's constants (docs/method.md, section 10)
    ("calibration", "motion_steps"): _constant("direct.MOTION_STEPS", (0.14, 0.22)),
    ("calibration", "max_motion"): _constant("direct.MAX_MOTION", 0.35),
    ("calibration", "outlier_mads"): _constant("pooling.OUTLIER_MADS", 4.0),
    ("calibration", "outlier_range"): _constant("pooling.OUTLIER_RANGE", 2.0),
    ("calibration", "max_residual_ratio"): _constant("direct_fits.MAX_RESIDUAL_RATIO", 3.0),
    ("calibration", "jackknife_blocks"): _constant("pooling.JACKKNIFE_BLOCKS", 8),
    ("calibration", "systematic_rel"): _constant("direct.SYSTEMATIC_REL", 1e-3),
    ("calibration", "min_pairs"): _constant("sequence_class.MIN_PAIRS", 4),
    ("calibration", "max_class_halfwidth_px"): _BY_CLASS_RULE,
    ("calibration", "parallax_px"): _constant("direct_fits.PARALLAX_PX", 1.0),
    ("calibration", "max_misfit"): _constant("direct_fits.MAX_MISFIT", 0.4),
    ("calibration", "registered_start"): _constant("direct_fits.REGISTERED_START", True),
    ("calibration", "relief_rel"): _constant("direct.RELIEF_REL", 0.8),
    ("calibration", "relief_test"): _constant("direct.RELIEF_TEST", 2.0),
    ("calibration", "no_distortion_px"): _constant("sequence_class.NO_DISTORTION_PX", 0.25),
    ("calibration", "verify_pairs"): _constant("controllers.calibrate.VERIFY_PAIRS", 6),
    ("calibration", "batch_size"): _constant("direct_fits.BATCH_SIZE", 16),
    ("calibration", "parallax"): _moved("selfcal", "parallax", "one relief model's bumps, for a pair and a sequence"),
    ("multiview", "confidence"): _moved("calibration", "confidence", "one coverage for every path of calibrate"),
    # the multi-view path's and the homography model's constants (docs/method.md, sections 11-12)
    ("multiview", "exhaustive_below"): _constant("multiview.EXHAUSTIVE_BELOW", 30),
    ("multiview", "sequential_overlap"): _constant("multiview.SEQUENTIAL_OVERLAP", 12),
    ("multiview", "evidence_draws"): _constant("multiview.EVIDENCE_DRAWS", 1000),
    ("multiview", "extra_mappings"): _constant("multiview.EXTRA_MAPPINGS", 3),
    ("multiview", "min_registered"): _constant("controllers.multiview_path.MIN_REGISTERED", 0.5),
    ("multiview", "planar_max_relief_z"): _constant("controllers.multiview_path.PLANAR_MAX_RELIEF_Z", 2.0),
    ("multiview", "max_halfwidth_rel"): _BY_CLASS_RULE,
    ("multiview", "max_halfwidth_px"): _BY_CLASS_RULE,
    ("multiview", "bic_margin"): _BY_EVIDENCE,
    ("multiview", "rms_margin"): _BY_EVIDENCE,
    ("multiview", "planar_scan_range"): _constant("planar_features.PLANAR_SCAN_RANGE", (-0.3, 1.5)),
    ("multiview", "planar_scan_steps"): _constant("planar_features.PLANAR_SCAN_STEPS", 19),
    ("multiview", "planar_scan_pairs"): _constant("planar_features.PLANAR_SCAN_PAIRS", 60),
    ("multiview", "planar_ransac_px"): _constant("planar_features.PLANAR_RANSAC_PX", 2.0),
    ("multiview", "planar_inlier_px"): _constant("planar_features.PLANAR_INLIER_PX", 3.0),
    ("multiview", "planar_min_pairs"): _constant("planar_features.PLANAR_MIN_PAIRS", 4),
    ("multiview", "planar_iterations"): _constant("planar_features.PLANAR_ITERATIONS", 100),
    ("multiview", "planar_guided_ratio"): _constant("guided_matching.PLANAR_GUIDED_RATIO", 0.8),
    ("multiview", "planar_refine_px"): _constant("match_refinement.PLANAR_REFINE_PX", 7),
    ("multiview", "planar_refine_blur"): _constant("match_refinement.PLANAR_REFINE_BLUR", 1.0),
    ("multiview", "planar_refine_ncc"): _constant("match_refinement.PLANAR_REFINE_NCC", 0.9),
    ("multiview", "features_per_megapixel"): _constant("features.FEATURES_PER_MEGAPIXEL", 8192.0),
    ("multiview", "planar_min_matches"): _constant("matches.PLANAR_MIN_MATCHES", 15),
    ("multiview", "planar_pair_matches"): _constant("matches.PLANAR_PAIR_MATCHES", 60),
    ("multiview", "planar_min_inlier_share"): _constant("planar_features.PLANAR_MIN_INLIER_SHARE", 0.5),
    ("multiview", "planar_centre_max"): _constant("planar_features.PLANAR_CENTRE_MAX", 0.1),
    ("multiview", "planar_guided_px"): _constant("guided_matching.PLANAR_GUIDED_PX", 3.0),
    ("multiview", "planar_guided_below"): _constant("guided_matching.PLANAR_GUIDED_BELOW", 0.5),
    # one pair's self-calibration's constants (docs/method.md, section 10)
    ("selfcal", "newton"): _constant("model.NEWTON", 5, "selfcal"),
    ("selfcal", "margin"): _constant("model.MARGIN", 2.0, "selfcal"),
    ("selfcal", "noise_floor"): _constant("model.NOISE_FLOOR", 0.5 / 255, "selfcal"),
    ("selfcal", "huber_k"): _constant("model.HUBER_K", 1.345, "selfcal"),
    ("selfcal", "tukey_c"): _constant("model.TUKEY_C", 4.685, "selfcal"),
    ("selfcal", "gain_range"): _constant("model.GAIN_RANGE", (0.25, 4.0), "selfcal"),
    ("selfcal", "parallax_width"): _constant("model.PARALLAX_WIDTH", 0.3, "selfcal"),
    ("selfcal", "damping"): _constant("fit.DAMPING", 1e-3, "selfcal"),
    ("selfcal", "distortion_levels"): _constant("fit.DISTORTION_LEVELS", 2, "selfcal"),
    ("selfcal", "max_coefficient"): _constant("fit.MAX_COEFFICIENT", 2.0, "selfcal"),
    ("selfcal", "min_overlap"): _constant("fit.MIN_OVERLAP", 0.3, "selfcal"),
    ("selfcal", "cannot_tell_std_px"): _constant("fit.CANNOT_TELL_STD_PX", 0.5, "selfcal"),
    ("selfcal", "confidence_threshold"): _constant("fit.CONFIDENCE_THRESHOLD", 0.5, "selfcal"),
    ("selfcal", "parallax_iterations"): _constant("fit.PARALLAX_ITERATIONS", 6, "selfcal"),
    ("selfcal", "parallax_block"): _constant("fit.PARALLAX_BLOCK", 2, "selfcal"),
    ("selfcal", "ridge"): _constant("prior.RIDGE", 1e-6, "selfcal"),
    ("selfcal", "parallax_px_range"): _constant("prior.PARALLAX_PX_RANGE", (0.02, 2.0), "selfcal"),
    ("selfcal", "robust"): _constant("model.ROBUST_LOSS", "tukey", "selfcal"),
    ("selfcal", "photometric"): _constant("model.PHOTOMETRIC_MODEL", "gain_bias", "selfcal"),
    ("selfcal", "levels"): _constant("fit.LEVELS", 3, "selfcal"),
    ("selfcal", "iterations"): _constant("fit.ITERATIONS", (8, 4, 6), "selfcal"),
    ("selfcal", "sample_block"): _constant("fit.SAMPLE_BLOCK", (2, 4, 4), "selfcal"),
    ("selfcal", "interpolation"): _constant("fit.SAMPLING", "blend", "selfcal"),
    ("selfcal", "both_starts"): _constant("fit.BOTH_STARTS", True, "selfcal"),
    ("selfcal", "clusters"): _constant("fit.CLUSTERS", 6, "selfcal"),
    ("selfcal", "occluded_share"): _constant("fit.OCCLUDED_SHARE", 0.15, "selfcal"),
    ("selfcal", "small_motion_error"): _constant("fit.SMALL_MOTION_ERROR", 1.5e-5, "selfcal"),
    ("selfcal", "parallax_test"): _constant("fit.PARALLAX_TEST", 2.0, "selfcal"),
    ("selfcal", "parallax_score_level"): Retired(
        by="lensdist_torch.selfcal.fit.PARALLAX_SCORE_LEVEL (the relief stage fitted where the score test rejects a "
           "flat scene, one step from the planar answer elsewhere)", inert=True),
    # one pair's registration's constants (docs/method.md, section 7)
    ("registration", "levels"): _constant("direct.LEVELS", (2, 0), "registration"),
    ("registration", "iterations"): _constant("direct.ITERATIONS", (10, 6), "registration"),
    ("registration", "step_tol"): _constant("direct.STEP_TOL", 0.01, "registration"),
    ("registration", "coarse_tol"): _constant("direct.COARSE_TOL", 0.2, "registration"),
    ("registration", "phase_level"): _constant("direct.PHASE_LEVEL", 3, "registration"),
    ("registration", "damping"): _constant("direct.DAMPING", 1e-6, "registration"),
    ("registration", "min_texture"): _constant("direct.MIN_TEXTURE", 1e-8, "registration"),
    ("registration", "margin"): _constant("direct.MARGIN", 2.0, "registration"),
    ("registration", "max_step"): _constant("direct.MAX_STEP", 0.25, "registration"),
    ("registration", "fine_stride"): _constant("direct.FINE_STRIDE", 2, "registration"),
    ("registration", "presmooth"): _constant("direct.PRESMOOTH", True, "registration"),
    ("registration", "match_intensity"): _constant("direct.MATCH_INTENSITY", True, "registration"),
    ("registration", "max_keypoints"): _constant("wide_baseline.MAX_KEYPOINTS", 2000, "registration"),
    ("registration", "match_ratio"): _constant("wide_baseline.MATCH_RATIO", 0.9, "registration"),
    ("registration", "ransac_threshold"): _constant("wide_baseline.RANSAC_THRESHOLD", 2.0, "registration"),
    ("registration", "min_inliers"): _constant("wide_baseline.MIN_INLIERS", 15, "registration"),
    ("registration", "min_overlap"): _constant("direct.MIN_OVERLAP", 0.3, "registration"),
    ("registration", "max_residual"): _constant("direct.MAX_RESIDUAL", 0.5, "registration"),
    ("registration", "feature_fallback"): _constant("wide_baseline.FEATURE_FALLBACK", True, "registration"),
    # the decision of analyze's constants (docs/method.md, section 10)
    ("analysis", "min_overlap"): _constant("decision.MIN_OVERLAP", 0.5, "workflows"),
    ("analysis", "out_of_domain_factor"): _constant("analyze.OUT_OF_DOMAIN_FACTOR", 2.0, "workflows"),
    ("analysis", "selfcal_confidence_scale"): _constant("decision.SELFCAL_CONFIDENCE_SCALE", 1.0, "workflows"),
    ("analysis", "selfcal_confidence_shift"): _constant("decision.SELFCAL_CONFIDENCE_SHIFT", 0.0, "workflows"),
    ("analysis", "max_class_disagreement"): _constant("decision.MAX_CLASS_DISAGREEMENT", 1, "workflows"),
    ("analysis", "max_delta_disagreement"): _constant("decision.MAX_DELTA_DISAGREEMENT", 0.25, "workflows"),
    ("analysis", "texture_factor"): _constant("decision.TEXTURE_FACTOR", 2.0, "workflows"),
    ("analysis", "validation_seed_offset"): _constant("decision_fit.VALIDATION_SEED_OFFSET", 1, "workflows"),
    ("analysis", "interval_confidence"): _constant("class_mass.INTERVAL_CONFIDENCE", 0.95, "workflows"),
    ("analysis", "target_precision"): _constant("decision_fit.TARGET_PRECISION", 0.97, "workflows"),
    # the metric's constants (docs/method.md, sections 3 and 5; hashed by the data fingerprint as the keys were)
    ("quality", "gamma"): _constant("quality.GAMMA", 0.9879, "config"),
    ("quality", "k"): _constant("quality.K", -22.0, "config"),
    ("quality", "sigma"): _constant("quality.SIGMA", 0.8, "config"),
    ("quality", "tau_g"): _constant("quality.TAU_G", 0.004, "config"),
    ("quality", "tau_e"): _constant("quality.TAU_E", 0.05, "config"),
    ("quality", "tau_d"): _constant("quality.TAU_D", 0.02, "config"),
    ("quality", "tau_b"): _constant("quality.TAU_B", 0.02, "config"),
    # the pair protocol's constants (docs/method.md, section 7; hashed by the data fingerprint as the keys were)
    ("protocol", "perspective"): _constant("synthesis.PERSPECTIVE", 2e-5, "data"),
    ("protocol", "perturbation"): _constant("synthesis.PERTURBATION", 0.01, "data"),
    ("protocol", "occluder_area"): _constant("realism.OCCLUDER_AREA", (0.05, 0.15), "data"),
    ("protocol", "ty_range"): _constant("synthesis.TY_RANGE", (0.0, 40.0), "data"),
    ("protocol", "tx_range"): _constant("synthesis.TX_RANGE", (-4.0, 4.0), "data"),
    ("protocol", "rotation_deg"): _constant("synthesis.ROTATION_DEG", 1.0, "data"),
    ("protocol", "scale_range"): _constant("synthesis.SCALE_RANGE", (0.98, 1.02), "data"),
    ("protocol", "gain_range"): _constant("realism.GAIN_RANGE", (0.7, 1.3), "data"),
    ("protocol", "offset_range"): _constant("realism.OFFSET_RANGE", (-0.1, 0.1), "data"),
    ("protocol", "gamma_range"): _constant("realism.GAMMA_RANGE", (0.8, 1.25), "data"),
    ("protocol", "illumination"): _constant("realism.ILLUMINATION", 0.25, "data"),
    ("protocol", "noise_range"): _constant("realism.NOISE_RANGE", (0.0, 0.02), "data"),
    ("protocol", "jpeg_quality"): _constant("realism.JPEG_QUALITY", (60, 95), "data"),
    ("protocol", "occluder_rate"): _constant("realism.OCCLUDER_RATE", 0.2, "data"),
    ("distortion", "n_classes"): _constant("distortion.N_CLASSES", 4, "geometry"),
    # the classifiers' and the decision's fit's constants (docs/method.md, sections 8 and 10)
    ("classifier", "reject_quantile"): _constant("eigenspace.REJECT_QUANTILE", 0.95, "classify"),
    ("classifier", "n_neighbours"): _constant("eigenspace.N_NEIGHBOURS", 4, "classify"),
    ("regression", "cannot_tell_fraction"): _constant("regression.CANNOT_TELL_FRACTION", 0.125, "classify"),
    ("regression", "confidence_threshold"): _constant("regression.CONFIDENCE_THRESHOLD", 0.5, "classify"),
    ("analysis", "eigenspace_max_class_disagreement"): _constant("decision.EIGENSPACE_MAX_CLASS_DISAGREEMENT", 0,
                                                                 "workflows"),
    ("analysis", "max_cannot_tell"): _constant("decision_fit.MAX_CANNOT_TELL", 0.25, "workflows"),
}
#: Retired keys that never shaped a fitted model or a data set: dropped wherever a saved config is read.
INERT = {key for key, r in RETIRED.items() if r.inert}


def _same(value: Any, constant: Any) -> bool:
    """Whether a config's ``value`` (TOML: lists for tuples, ints for whole floats) is ``constant``."""
    if isinstance(constant, tuple):
        return isinstance(value, (list, tuple)) and len(value) == len(constant) and all(
            _same(v, c) for v, c in zip(value, constant))
    if isinstance(value, (bool, str)) or isinstance(constant, (bool, str)):
        return type(value) is type(constant) and value == constant
    return isinstance(value, (int, float)) and value == constant


def _named(data: Any, section: str, key: str) -> bool:
    return isinstance(data, dict) and isinstance(data.get(section), dict) and key in data[section]


def without_key(data: dict, section: str, key: str) -> dict:
    """A copy of a parsed config ``data`` without ``section.key`` (``data`` itself where it does not name it).

    Example:
        >>> without_key({"selfcal": {"parallax": 0, "chunk_size": 4}}, "selfcal", "parallax")
        {'selfcal': {'chunk_size': 4}}
    """
    if not _named(data, section, key):
        return data
    return {**data, section: {k: v for k, v in data[section].items() if k != key}}


def moved_names(data: Any) -> dict[str, str]:
    """The moved keys a parsed config names: their new ``section.key`` -> the old one it was written as.

    Example:
        >>> moved_names({"multiview": {"confidence": 0.9}})
        {'calibration.confidence': 'multiview.confidence'}
    """
    return {".".join(r.moved): f"{s}.{k}" for (s, k), r in RETIRED.items()
            if r.moved is not None and _named(data, s, k)}


def retired_keys(data: dict[str, Any]) -> list[str]:
    """The ``section.key`` names of :data:`RETIRED` in a saved config's dict that do not load as they are.

    A key that became a constant of the method, at the constant's value, loads (dropped): it is not one.

    Example:
        >>> retired_keys({"protocol": {"parallax_px": 1.5}}), retired_keys({"protocol": {}})
        (['protocol.parallax_px'], [])
        >>> retired_keys({"analysis": {"relief_z": 4.0}})
        ['analysis.relief_z']
    """
    return [f"{s}.{k}" for (s, k), r in RETIRED.items()
            if _named(data, s, k) and r.moved is None and (r.value is None or not _same(data[s][k], r.value))]


def settle_moves(data: Any) -> Any:
    """``data`` without the moved keys whose new place it also names (a stored config of an earlier version).

    Example:
        >>> settle_moves({"calibration": {"parallax": 5, "max_pairs": 8}, "selfcal": {"parallax": 0}})
        {'calibration': {'max_pairs': 8}, 'selfcal': {'parallax': 0}}
    """
    for (section, key), r in RETIRED.items():
        if r.moved is not None and _named(data, *r.moved):
            data = without_key(data, section, key)
    return data


def drop_constants(data: Any) -> Any:
    """``data`` (a parsed config): its retired keys at a constant's value dropped, its moved keys in their new place.

    Raises:
        ValueError: such a key at another value, or a moved key given in both places at different values; one
            line naming the key and what replaced it.

    Example:
        >>> drop_constants({"quality": {"block_size": 16}})
        {'quality': {'block_size': 16}}
        >>> drop_constants({"calibration": {"parallax": 0}})
        {'calibration': {}, 'selfcal': {'parallax': 0}}
    """
    for (section, key), r in RETIRED.items():
        if r.moved is not None and _named(data, section, key):
            value, (to_section, to_key) = data[section][key], r.moved
            if _named(data, to_section, to_key) and not _same(data[to_section][to_key], value):
                raise ValueError(f"{section}.{key} = {show(value)} moved to {r.by}, which is "
                                 f"{show(data[to_section][to_key])} here: give one")
            data = without_key(data, section, key)
            target = data.get(to_section, {})
            if isinstance(target, dict) and to_key not in target:
                data = {**data, to_section: {**target, to_key: value}}
            continue
        if r.value is None or not _named(data, section, key):
            continue
        value = data[section][key]
        if not _same(value, r.value):
            raise ValueError(f"{section}.{key} = {show(value)} cannot be set: a constant of the method now: "
                             f"{r.by} = {r.value!r}")
        data = without_key(data, section, key)
    return data
