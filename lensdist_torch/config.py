"""Every number the library uses, as frozen dataclasses with the method's defaults.

The defaults are the project's conventions (``docs/method.md``); a TOML file in ``configs/``
may override any field. Sections of the TOML file map one to one onto the dataclasses below::

    [quality]       thresholds, temperatures, block size     (docs/method.md sections 2-5)
    [image]         analysis size                             (section 1)
    [distortion]    coefficient ranges                        (section 6, eq. 4)
    [protocol]      pair protocol and set sizes               (section 7)
    [registration]  homography registration                   (in the data fingerprint)
    [classifier]    eigen-space classifier                    (section 8)
    [selfcal]       self-calibration of (k2, k4) and H
    [regression]    Delta regression without classes
    [analysis]      the decision of ``analyze``: R threshold, overlap, confidence

Every threshold of a decision lives here, nowhere else.

Unknown sections or keys are an error (a typo must not silently fall back to a default), and
so is a value of the wrong type or out of range: a one-line ``ValueError`` names the section and
field (``protocol.ty_range must be (low, high) ...``); the checks are in ``config_checks.py``.
``configs/paper.toml`` writes every default out.
"""

from __future__ import annotations

import dataclasses
import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lensdist_torch.config_checks import choice, flag, integer, integers, names, one_line, pair, positive, real, show

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, as a package
    import tomli as tomllib

__all__ = [
    "QualityConfig", "ImageConfig", "DistortionConfig", "ProtocolConfig", "ClassifierConfig",
    "RegistrationConfig", "SelfCalConfig", "RegressionConfig", "AnalysisConfig", "LensdistConfig",
    "load_config", "config_to_dict", "config_from_dict",
]


@dataclass(frozen=True)
class QualityConfig:
    """Settings of the registration-quality metric (docs/method.md sections 2-5).

    Attributes:
        block_size: side of the square pooling blocks in pixels.
        theta_g: gradient-magnitude threshold of the risk map (normalised Sobel on [0, 1]).
        theta_e: edge-preservation threshold (in ]0, gamma[) below which a structured pixel errs.
        theta_d: intensity-difference threshold of the visual error.
        min_block_ratio: block error ratios below this are set to 0; in [0, 1].
        gamma, k, sigma: Xydeas-Petrovic constants of the edge-preservation sigmoid
            E = gamma / (1 + exp(k (A - sigma))): gamma in ]0, 1], k < 0, sigma in ]0, 1[.
        tau_g, tau_e, tau_d, tau_b: temperatures of the smooth path (gradient-magnitude,
            edge-preservation, intensity-difference and block-floor steps). Smaller is sharper.
        chunk_size: pairs processed at once inside a big batch, so that the intermediates of a
            chunk stay in the CPU cache. The result does not depend on it.
    """

    block_size: int = 8
    theta_g: float = 0.02
    theta_e: float = 0.5
    theta_d: float = 0.1
    min_block_ratio: float = 0.1
    gamma: float = 0.9879
    k: float = -22.0
    sigma: float = 0.8
    tau_g: float = 0.004
    tau_e: float = 0.05
    tau_d: float = 0.02
    tau_b: float = 0.02
    chunk_size: int = 2

    def __post_init__(self) -> None:
        integer(self, "block_size")
        integer(self, "chunk_size")
        for name in ("theta_g", "theta_d", "tau_g", "tau_e", "tau_d", "tau_b"):
            real(self, name, lo=0, lo_open=True)
        real(self, "gamma", lo=0, hi=1, lo_open=True)
        real(self, "theta_e", lo=0, hi=self.gamma, lo_open=True, hi_open=True, hi_name=f"gamma={self.gamma}")
        real(self, "min_block_ratio", lo=0, hi=1)
        real(self, "k", hi=0, hi_open=True, why="E grows with A")
        real(self, "sigma", lo=0, hi=1, lo_open=True, hi_open=True)

    def with_temperature_scale(self, factor: float) -> "QualityConfig":
        """A copy with every temperature multiplied by ``factor`` (for annealing)."""
        positive("factor", factor)
        t = {name: getattr(self, name) * factor for name in ("tau_g", "tau_e", "tau_d", "tau_b")}
        return dataclasses.replace(self, **t)


@dataclass(frozen=True)
class ImageConfig:
    """Analysis size (docs/method.md section 1): 320 x 424 gives 40 x 53 blocks, feature vectors of 2120."""

    height: int = 320
    width: int = 424

    def __post_init__(self) -> None:
        integer(self, "height")
        integer(self, "width")

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return self.height, self.width


@dataclass(frozen=True)
class DistortionConfig:
    """Ranges of the radial coefficients (docs/method.md section 6).

    k2 lies in ]0, k2_max], k4 in ]0, k4_max]. ``n_classes`` is 4: the labels are the classes
    1-4 and R.
    """

    k2_max: float = 2.5e-6
    k4_max: float = 2.5e-11
    n_classes: int = 4

    def __post_init__(self) -> None:
        real(self, "k2_max", lo=0, lo_open=True)
        real(self, "k4_max", lo=0, lo_open=True)
        integer(self, "n_classes")
        if self.n_classes != 4:
            raise ValueError(
                f"distortion.n_classes must be 4 (the labels are the classes 1-4 and R), got {self.n_classes}"
            )


@dataclass(frozen=True)
class ProtocolConfig:
    """The pair protocol (docs/method.md section 7): motion ranges, set sizes, seed.

    ``seed`` is any int; ``scenes`` distinct embedded scene names; the ranges (low, high); the
    rotation and perspective half-widths >= 0; the class-R ``perturbation`` in [0, 1[.

    ``realistic`` (off by default) adds the effects of a photograph (docs/method.md section 7,
    the realistic protocol), each drawn per view or per pair: ``gain_range`` (> 0),
    ``offset_range`` (in [-1, 1]), ``gamma_range`` (> 0, log-uniform), ``illumination`` (the
    largest share, in [0, 1[, that a ramp / vignetting darkens), ``noise_range`` (Gaussian
    sigma, in [0, 1]), ``jpeg_quality`` (ints in [1, 100]), ``parallax_px`` (>= 0, the largest
    displacement of I2's samples along the motion), ``occluder_rate`` (share of pairs with a
    moving or occluding patch, in [0, 1]) and ``occluder_area`` (its share of the frame, in
    ]0, 1]).
    """

    seed: int = 0
    scenes: tuple[str, ...] = ("gravel", "grass")
    n_train: int = 12000
    n_test_distorted: int = 400
    n_test_undistorted: int = 100
    ty_range: tuple[float, float] = (0.0, 40.0)
    tx_range: tuple[float, float] = (-4.0, 4.0)
    rotation_deg: float = 1.0
    scale_range: tuple[float, float] = (0.98, 1.02)
    perspective: float = 2e-5
    perturbation: float = 0.01
    shard_size: int = 500
    realistic: bool = False
    gain_range: tuple[float, float] = (0.7, 1.3)
    offset_range: tuple[float, float] = (-0.1, 0.1)
    gamma_range: tuple[float, float] = (0.8, 1.25)
    illumination: float = 0.25
    noise_range: tuple[float, float] = (0.0, 0.02)
    jpeg_quality: tuple[int, int] = (60, 95)
    parallax_px: float = 1.5
    occluder_rate: float = 0.2
    occluder_area: tuple[float, float] = (0.05, 0.15)

    def __post_init__(self) -> None:
        integer(self, "seed", lo=None)
        names(self, "scenes")
        for name in ("n_train", "n_test_distorted", "n_test_undistorted"):
            integer(self, name, lo=0)
        pair(self, "ty_range")
        pair(self, "tx_range")
        pair(self, "scale_range", positive=True)
        real(self, "rotation_deg", lo=0)
        real(self, "perspective", lo=0)
        real(self, "perturbation", lo=0, hi=1, hi_open=True)
        integer(self, "shard_size")
        flag(self, "realistic")
        pair(self, "gain_range", positive=True)
        pair(self, "offset_range", within=(-1, 1))
        pair(self, "gamma_range", positive=True)
        real(self, "illumination", lo=0, hi=1, hi_open=True)
        pair(self, "noise_range", within=(0, 1))
        pair(self, "jpeg_quality", within=(1, 100), integral=True)
        real(self, "parallax_px", lo=0)
        real(self, "occluder_rate", lo=0, hi=1)
        pair(self, "occluder_area", positive=True, within=(0, 1))


@dataclass(frozen=True)
class ClassifierConfig:
    """The eigen-space classifier (docs/method.md section 8)."""

    n_eigenvectors: int = 10
    metric: str = "delta_avg"
    reject_quantile: float = 0.95
    n_neighbours: int = 4

    def __post_init__(self) -> None:
        integer(self, "n_eigenvectors")
        integer(self, "n_neighbours")
        choice(self, "metric", ("delta_avg", "delta_max"))
        real(self, "reject_quantile", lo=0, hi=1, lo_open=True)


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`estimate_homography`.

    Attributes:
        levels: pyramid levels to run, coarsest first, ending with 0 (level l is 1 / 2**l of the
            size); levels whose smaller side would be under 16 px are dropped.
        iterations: maximum IC iterations for each entry of ``levels``.
        step_tol: full resolution is done when an update moves no corner by more than this (px).
        coarse_tol: the same for the coarser levels (full-resolution px).
        phase_level: pyramid level of the phase correlation (lowered for small images).
        damping: Hessian damping, a fraction of its mean diagonal.
        min_texture: smallest admissible eigenvalue of the per-pixel Gauss-Newton Hessian
            (gradients in level px, coordinates in half-diagonals).
        min_overlap: fraction of img1 that must map inside img2.
        max_residual: largest RMS residual, relative to sqrt(2) x img1's standard deviation
            (about 1 for unrelated images; ~0.02 registered, up to ~0.25 with the strongest
            distortion of docs/method.md section 6).
        margin: level px by which the pixels used must map inside img2.
        max_step: an update moving a corner by more than this fraction of the diagonal diverged.
        fine_stride: template pixel stride at full resolution.
        presmooth: binomial smoothing (sigma 1 px) of both images first.
        chunk_size: pairs registered together (cache locality); results do not depend on it.
        feature_fallback: :func:`~lensdist_torch.geometry.wide_baseline.estimate_homography_robust`
            retries the pairs that did not converge from SIFT matches (docs/method.md, section 10).
        max_keypoints: SIFT keypoints kept per image by the fallback.
        match_ratio: second-nearest-neighbour ratio of the fallback's mutual matches, in ]0, 1].
        ransac_threshold: px, one-way transfer error of a RANSAC inlier in the fallback.
        min_inliers: fewest RANSAC inliers for a feature homography.
    """

    levels: tuple[int, ...] = (2, 0)
    iterations: tuple[int, ...] = (10, 6)
    step_tol: float = 0.01
    coarse_tol: float = 0.2
    phase_level: int = 3
    damping: float = 1e-6
    min_texture: float = 1e-8
    min_overlap: float = 0.3
    max_residual: float = 0.5
    margin: float = 2.0
    max_step: float = 0.25
    fine_stride: int = 2
    presmooth: bool = True
    chunk_size: int = 8
    feature_fallback: bool = True
    max_keypoints: int = 2000
    match_ratio: float = 0.9
    ransac_threshold: float = 2.0
    min_inliers: int = 15

    def __post_init__(self) -> None:
        integers(self, "levels", lo=0)
        lv = self.levels
        if lv[-1] != 0 or not all(a > b for a, b in itertools.pairwise(lv)):
            raise ValueError(f"registration.levels must be a decreasing tuple of ints ending with 0, got {lv!r}")
        integers(self, "iterations", n=len(lv), per="level")
        for name in ("step_tol", "coarse_tol", "min_texture", "max_residual", "max_step"):
            real(self, name, lo=0, lo_open=True)
        integer(self, "phase_level", lo=0)
        real(self, "damping", lo=0)
        real(self, "margin", lo=0)
        real(self, "min_overlap", lo=0, hi=1)
        integer(self, "fine_stride")
        flag(self, "presmooth")
        integer(self, "chunk_size")
        flag(self, "feature_fallback")
        integer(self, "max_keypoints", lo=4)
        real(self, "match_ratio", lo=0, hi=1, lo_open=True)
        real(self, "ransac_threshold", lo=0, lo_open=True)
        integer(self, "min_inliers", lo=4)


@dataclass(frozen=True)
class SelfCalConfig:
    """Settings of :func:`~lensdist_torch.geometry.selfcal.estimate_distortion`.

    Attributes:
        levels: pyramid levels (2 x 2 means), coarsest first in ``iterations``.
        iterations: Levenberg-Marquardt iterations per level, coarsest first.
        newton: Newton steps of the inverse of eq. 4.
        damping: initial LM lambda, relative to diag(J^T J).
        margin: level pixels kept inside img2.
        max_coefficient: bound on |a|, |b| (normalised units) beyond which a fit diverged.
        min_overlap: share of img1's sampled pixels that must map inside img2.
        sample_block: per level (coarsest first), the residual uses the strongest-gradient
            pixel of every block x block cell (1: every pixel).
        chunk_size: pairs fitted together; results do not depend on it.
        cannot_tell_std_px: posterior std of Delta_avg (px) at which confidence is 0.5.
        confidence_threshold: pairs below this confidence are "cannot tell from this pair".
        noise_floor: intensity std floor of the covariance (8-bit quantisation), so that a
            textureless or identical pair cannot claim certainty.
        ridge: absolute ridge on J^T J in the covariance.
        robust: the M-estimator of the photometric residual: "tukey" (biweight), "huber" or
            "none" (least squares); IRLS with sigma = 1.4826 MAD re-estimated every iteration.
        huber_k: Huber's constant, in sigmas (1.345: 95 % efficiency for Gaussian noise).
        tukey_c: Tukey's biweight constant, in sigmas (4.685: 95 % efficiency).
        photometric: "gain_bias" (img2 times a fitted gain plus a bias), "normalized"
            (zero-mean, unit-variance samples per pair) or "none".
        gain_range: (low, high) plausible gain of ``gain_bias``; the start is clamped to it, a
            fit that leaves it is flagged.
        both_starts: with an ``init`` homography, also fit from phase correlation in the same
            batch and keep, per pair, the start with the lower final robust cost.
    """

    levels: int = 3
    iterations: tuple[int, ...] = (12, 6, 3)
    newton: int = 5
    damping: float = 1e-3
    margin: float = 2.0
    max_coefficient: float = 2.0
    min_overlap: float = 0.3
    sample_block: tuple[int, ...] = (2, 4, 4)
    chunk_size: int = 16
    cannot_tell_std_px: float = 0.5
    confidence_threshold: float = 0.5
    noise_floor: float = 0.5 / 255
    ridge: float = 1e-6
    robust: str = "tukey"
    huber_k: float = 1.345
    tukey_c: float = 4.685
    photometric: str = "gain_bias"
    gain_range: tuple[float, float] = (0.25, 4.0)
    both_starts: bool = True

    def __post_init__(self) -> None:
        choice(self, "robust", ("none", "huber", "tukey"))
        choice(self, "photometric", ("none", "gain_bias", "normalized"))
        real(self, "huber_k", lo=0, lo_open=True)
        real(self, "tukey_c", lo=0, lo_open=True)
        pair(self, "gain_range", positive=True)
        flag(self, "both_starts")
        for name in ("levels", "newton", "chunk_size"):
            integer(self, name)
        for name in ("iterations", "sample_block"):
            integers(self, name, n=self.levels, per="level")
        for name in ("damping", "max_coefficient", "cannot_tell_std_px", "noise_floor", "ridge"):
            real(self, name, lo=0, lo_open=True)
        real(self, "margin", lo=0)
        real(self, "min_overlap", lo=0, hi=1)
        real(self, "confidence_threshold", lo=0, hi=1)


@dataclass(frozen=True)
class RegressionConfig:
    """Settings of :class:`~lensdist_torch.classify.regression.DeltaRegressor`.

    Attributes:
        n_components: PCA components kept (capped by the training set).
        k: neighbours whose median Delta is the prediction.
        cannot_tell_fraction: neighbour spread of Delta_avg, as a fraction of the class range,
            at which confidence is 0.5.
        confidence_threshold: below this confidence the answer is "cannot tell".
    """

    n_components: int = 384
    k: int = 8
    cannot_tell_fraction: float = 0.125
    confidence_threshold: float = 0.5

    def __post_init__(self) -> None:
        integer(self, "n_components")
        integer(self, "k")
        real(self, "cannot_tell_fraction", lo=0, lo_open=True)
        real(self, "confidence_threshold", lo=0, hi=1)


@dataclass(frozen=True)
class AnalysisConfig:
    """The decision of ``analyze`` and of the evaluation of the estimators.

    Attributes:
        no_distortion_px: an estimated Delta_avg (analysis px) below this is class R, "no
            visible distortion" (class 1 spans ]0, 3.6] px at 320 x 424; a true Delta_avg below
            0.25 px occurs in well under 1 % of the protocol's pairs).
        min_overlap: below this share of valid pixels the map is too small to judge.
        out_of_domain_factor: an eigen-space map whose smallest class distance exceeds this
            multiple of the reject threshold is unlike every training map.
        min_confidence: below this calibrated confidence (an estimate of P(class right)) the
            answer is "cannot tell" (self-calibration and regression).
        selfcal_confidence_scale, selfcal_confidence_shift: the Platt map of the
            self-calibration's confidence c: sigmoid(scale * logit(c) + shift); 1 and 0 leave
            it as it is. Fitted on a validation split by ``calibrate_confidence``.
        regression_confidence_scale, regression_confidence_shift: the same for the regression.
        cross_check: the learned methods (regression, eigen-space) also run the
            self-calibration and are out of domain where the two disagree.
        max_class_disagreement: out of domain where the classes differ by more than this
            (R counts as class 0).
        max_delta_disagreement: out of domain where the Delta_avg estimates differ by more than
            this share of the Delta_avg range.
        texture_factor: out of domain where the images' gradient-magnitude histogram is farther
            from every training scene than this multiple of the largest distance of a
            training view (stored in the checkpoint).
        validation_seed_offset: the validation split used to fit the decision is the test set
            of the protocol seed plus this offset (never the test set itself).
    """

    no_distortion_px: float = 0.25
    min_overlap: float = 0.5
    out_of_domain_factor: float = 2.0
    min_confidence: float = 0.5
    selfcal_confidence_scale: float = 1.0
    selfcal_confidence_shift: float = 0.0
    regression_confidence_scale: float = 1.0
    regression_confidence_shift: float = 0.0
    cross_check: bool = True
    max_class_disagreement: int = 1
    max_delta_disagreement: float = 0.25
    texture_factor: float = 2.0
    validation_seed_offset: int = 1

    def __post_init__(self) -> None:
        real(self, "no_distortion_px", lo=0, lo_open=True)
        real(self, "min_overlap", lo=0, hi=1)
        real(self, "out_of_domain_factor", lo=0, lo_open=True)
        real(self, "min_confidence", lo=0, hi=1)
        for name in ("selfcal_confidence_scale", "regression_confidence_scale", "max_delta_disagreement", "texture_factor"):
            real(self, name, lo=0, lo_open=True)
        real(self, "selfcal_confidence_shift")
        real(self, "regression_confidence_shift")
        flag(self, "cross_check")
        integer(self, "max_class_disagreement", lo=0)
        integer(self, "validation_seed_offset")


@dataclass(frozen=True)
class LensdistConfig:
    """All settings, one section per concern."""

    quality: QualityConfig = field(default_factory=QualityConfig)
    image: ImageConfig = field(default_factory=ImageConfig)
    distortion: DistortionConfig = field(default_factory=DistortionConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    selfcal: SelfCalConfig = field(default_factory=SelfCalConfig)
    regression: RegressionConfig = field(default_factory=RegressionConfig)
    analysis: AnalysisConfig = field(default_factory=AnalysisConfig)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            cls, value = f.default_factory, getattr(self, f.name)
            if not isinstance(value, cls):  # type: ignore[arg-type]
                raise ValueError(f"{f.name} must be a {cls.__name__}, got {show(value)}")  # type: ignore[union-attr]
        b = self.quality.block_size
        if self.image.height % b or self.image.width % b:
            raise ValueError(
                f"image size {self.image.height} x {self.image.width} must be a multiple of "
                f"quality.block_size={b}"
            )


_SECTIONS = {f.name: f.default_factory for f in dataclasses.fields(LensdistConfig)}


def config_from_dict(data: dict[str, Any]) -> LensdistConfig:
    """Build a :class:`LensdistConfig` from nested dicts (a parsed TOML file).

    Raises:
        TypeError: ``data`` is not a dict.
        ValueError: an unknown section or key, a section that is not a table, or a bad value;
            the message names the section and the field.
    """
    if not isinstance(data, dict):
        raise TypeError(f"config data must be a dict, got {type(data).__name__}")
    for name, values in data.items():
        if name not in _SECTIONS and not isinstance(values, dict):
            raise ValueError(f"config key {name!r} is outside any section; the sections are {list(_SECTIONS)}")
    unknown = sorted(set(data) - set(_SECTIONS))
    if unknown:
        raise ValueError(f"unknown config section(s) {unknown}; expected {sorted(_SECTIONS)}")
    parts = {}
    for name, cls in _SECTIONS.items():
        values = data.get(name, {})
        if not isinstance(values, dict):
            raise ValueError(f"config section [{name}] must be a table of key = value pairs, got {show(values)}")
        values = dict(values)
        bad = set(values) - {f.name for f in dataclasses.fields(cls)}
        if bad:
            raise ValueError(f"unknown key(s) {sorted(bad)} in config section [{name}]")
        parts[name] = cls(**values)
    return LensdistConfig(**parts)


def config_to_dict(config: LensdistConfig) -> dict[str, Any]:
    """Nested plain dicts (lists for tuples), suitable for JSON and for checkpoints."""

    def plain(value: Any) -> Any:
        return list(value) if isinstance(value, tuple) else value

    return {
        name: {k: plain(v) for k, v in dataclasses.asdict(getattr(config, name)).items()}
        for name in _SECTIONS
    }


def load_config(path: str | Path | None = None) -> LensdistConfig:
    """Load a TOML config file; ``None`` gives the defaults (the values of ``configs/paper.toml``).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not a readable UTF-8 TOML file, or an invalid config; the one-line message
            names the file and the section and field.

    Example:
        >>> cfg = load_config(None)
        >>> cfg.quality.theta_e
        0.5
    """
    if path is None:
        return LensdistConfig()
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"config file not found: {path}")
    if not path.is_file():
        raise ValueError(f"config path {path} is not a file")
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path} is not valid TOML: {one_line(exc)}") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"config file {path} is not UTF-8 text: {one_line(exc)}") from exc
    except OSError as exc:
        raise ValueError(f"cannot read config file {path}: {exc.strerror or one_line(exc)}") from exc
    try:
        return config_from_dict(data)
    except ValueError as exc:
        raise ValueError(f"config file {path}: {exc}") from exc
