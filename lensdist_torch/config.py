"""Every number the library uses, as frozen dataclasses with the SPEC defaults.

The defaults are the project's conventions (``docs/method.md``); a TOML file in ``configs/``
may override any field. Sections of the TOML file map one to one onto the dataclasses below::

    [quality]       thresholds, temperatures, block size     (method: the metric)
    [image]         analysis size                             (method: images)
    [distortion]    coefficient ranges                        (method: eq. 4)
    [protocol]      pair protocol and set sizes               (method: the protocol)
    [registration]  homography registration                   (in the data fingerprint)
    [classifier]    eigen-space classifier                    (method: eigen-spaces)
    [selfcal]       self-calibration of (k2, k4) and H
    [regression]    Delta regression without classes
    [analysis]      the decision of ``analyze``: R threshold, overlap, confidence

Every threshold of a decision lives here, nowhere else.

Unknown sections or keys are an error (a typo must not silently fall back to a default).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the same parser, as a package
    import tomli as tomllib

__all__ = [
    "QualityConfig",
    "ImageConfig",
    "DistortionConfig",
    "ProtocolConfig",
    "ClassifierConfig",
    "RegistrationConfig",
    "SelfCalConfig",
    "RegressionConfig",
    "AnalysisConfig",
    "LensdistConfig",
    "load_config",
    "config_to_dict",
    "config_from_dict",
]


@dataclass(frozen=True)
class QualityConfig:
    """Settings of the registration-quality metric (SPEC sections 2-5).

    Attributes:
        block_size: side of the square pooling blocks in pixels.
        theta_g: gradient-magnitude threshold of the risk map (normalised Sobel on [0, 1]).
        theta_e: edge-preservation threshold below which a structured pixel is an error.
        theta_d: intensity-difference threshold of the visual error.
        min_block_ratio: block error ratios below this are set to 0.
        gamma, k, sigma: Xydeas-Petrovic constants of the edge-preservation sigmoid.
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
        _check_positive_int("block_size", self.block_size)
        _check_positive_int("chunk_size", self.chunk_size)
        for name in ("theta_g", "theta_d", "tau_g", "tau_e", "tau_d", "tau_b", "gamma"):
            _check_positive_float(name, getattr(self, name))
        if not 0.0 < self.theta_e < self.gamma:
            raise ValueError(f"theta_e must lie in ]0, gamma={self.gamma}[, got {self.theta_e}")
        if not 0.0 <= self.min_block_ratio <= 1.0:
            raise ValueError(f"min_block_ratio must lie in [0, 1], got {self.min_block_ratio}")
        if self.k >= 0:
            raise ValueError(f"k must be negative (E grows with A), got {self.k}")

    def with_temperature_scale(self, factor: float) -> "QualityConfig":
        """A copy with every temperature multiplied by ``factor`` (for annealing)."""
        _check_positive_float("factor", factor)
        return dataclasses.replace(
            self,
            tau_g=self.tau_g * factor,
            tau_e=self.tau_e * factor,
            tau_d=self.tau_d * factor,
            tau_b=self.tau_b * factor,
        )


@dataclass(frozen=True)
class ImageConfig:
    """Analysis size (SPEC 1): 320 x 424 gives 40 x 53 blocks, feature vectors of 2120."""

    height: int = 320
    width: int = 424

    def __post_init__(self) -> None:
        _check_positive_int("height", self.height)
        _check_positive_int("width", self.width)

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return self.height, self.width


@dataclass(frozen=True)
class DistortionConfig:
    """Ranges of the radial coefficients (SPEC 6): k2 in ]0, k2_max], k4 in ]0, k4_max]."""

    k2_max: float = 2.5e-6
    k4_max: float = 2.5e-11
    n_classes: int = 4

    def __post_init__(self) -> None:
        _check_positive_float("k2_max", self.k2_max)
        _check_positive_float("k4_max", self.k4_max)
        _check_positive_int("n_classes", self.n_classes)


@dataclass(frozen=True)
class ProtocolConfig:
    """The pair protocol (SPEC 7): motion ranges, set sizes, seed."""

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

    def __post_init__(self) -> None:
        for name in ("n_train", "n_test_distorted", "n_test_undistorted"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be a non-negative int, got {getattr(self, name)!r}")
        _check_positive_int("shard_size", self.shard_size)
        if len(self.scenes) == 0:
            raise ValueError("scenes must name at least one scene")
        for name in ("ty_range", "tx_range", "scale_range"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(lo, hi)}")


@dataclass(frozen=True)
class ClassifierConfig:
    """The eigen-space classifier (SPEC 8)."""

    n_eigenvectors: int = 10
    metric: str = "delta_avg"
    reject_quantile: float = 0.95
    n_neighbours: int = 4

    def __post_init__(self) -> None:
        _check_positive_int("n_eigenvectors", self.n_eigenvectors)
        _check_positive_int("n_neighbours", self.n_neighbours)
        if self.metric not in ("delta_avg", "delta_max"):
            raise ValueError(f"metric must be 'delta_avg' or 'delta_max', got {self.metric!r}")
        if not 0.0 < self.reject_quantile <= 1.0:
            raise ValueError(f"reject_quantile must lie in ]0, 1], got {self.reject_quantile}")


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
            (about 1 for unrelated images; ~0.02 registered, up to ~0.25 with SPEC 6's strongest
            distortion).
        margin: level px by which the pixels used must map inside img2.
        max_step: an update moving a corner by more than this fraction of the diagonal diverged.
        fine_stride: template pixel stride at full resolution.
        presmooth: binomial smoothing (sigma 1 px) of both images first.
        chunk_size: pairs registered together (cache locality); results do not depend on it.
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

    def __post_init__(self) -> None:
        lv, its = self.levels, self.iterations
        if not (isinstance(lv, tuple) and lv and all(type(i) is int for i in lv) and lv[-1] == 0
                and all(a > b for a, b in itertools.pairwise(lv))):
            raise ValueError(f"levels must be a decreasing tuple of ints ending with 0, got {lv!r}")
        if not (isinstance(its, tuple) and len(its) == len(lv) and all(type(i) is int and i > 0 for i in its)):
            raise ValueError(f"iterations must be a tuple of positive ints, one per level, got {its!r}")
        for name in ("phase_level", "fine_stride", "chunk_size"):
            if type(getattr(self, name)) is not int or getattr(self, name) < (0 if name == "phase_level" else 1):
                raise ValueError(f"{name} must be a {'non-negative' if name == 'phase_level' else 'positive'} int")
        for name in ("step_tol", "coarse_tol", "min_texture", "max_residual", "max_step"):
            if not (isinstance(getattr(self, name), (int, float)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a positive number, got {getattr(self, name)!r}")
        if not (self.damping >= 0 and self.margin >= 0 and 0 <= self.min_overlap <= 1):
            raise ValueError("damping and margin must be >= 0 and min_overlap in [0, 1]")


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

    def __post_init__(self) -> None:
        for name in ("levels", "newton", "chunk_size"):
            _check_positive_int(name, getattr(self, name))
        for name in ("iterations", "sample_block"):
            v = getattr(self, name)
            if not (isinstance(v, tuple) and len(v) == self.levels and all(type(i) is int and i > 0 for i in v)):
                raise ValueError(f"{name} must be a tuple of {self.levels} positive ints (one per level), got {v!r}")
        for name in ("damping", "max_coefficient", "cannot_tell_std_px", "noise_floor", "ridge"):
            _check_positive_float(name, getattr(self, name))
        _check_fraction("min_overlap", self.min_overlap)
        _check_fraction("confidence_threshold", self.confidence_threshold)
        if isinstance(self.margin, bool) or not isinstance(self.margin, (int, float)) or not self.margin >= 0:
            raise ValueError(f"margin must be a number >= 0, got {self.margin!r}")


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
        _check_positive_int("n_components", self.n_components)
        _check_positive_int("k", self.k)
        _check_positive_float("cannot_tell_fraction", self.cannot_tell_fraction)
        _check_fraction("confidence_threshold", self.confidence_threshold)


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
    """

    no_distortion_px: float = 0.25
    min_overlap: float = 0.5
    out_of_domain_factor: float = 2.0

    def __post_init__(self) -> None:
        _check_positive_float("no_distortion_px", self.no_distortion_px)
        _check_fraction("min_overlap", self.min_overlap)
        _check_positive_float("out_of_domain_factor", self.out_of_domain_factor)


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
        b = self.quality.block_size
        if self.image.height % b or self.image.width % b:
            raise ValueError(
                f"image size {self.image.height} x {self.image.width} must be a multiple of "
                f"quality.block_size={b}"
            )


_SECTIONS = {f.name: f.default_factory for f in dataclasses.fields(LensdistConfig)}


def config_from_dict(data: dict[str, Any]) -> LensdistConfig:
    """Build a :class:`LensdistConfig` from nested dicts; unknown sections or keys raise."""
    if not isinstance(data, dict):
        raise TypeError(f"config data must be a dict, got {type(data).__name__}")
    unknown = set(data) - set(_SECTIONS)
    if unknown:
        raise ValueError(f"unknown config section(s) {sorted(unknown)}; expected {sorted(_SECTIONS)}")
    parts = {}
    for name, cls in _SECTIONS.items():
        values = dict(data.get(name, {}))
        names = {f.name for f in dataclasses.fields(cls)}
        bad = set(values) - names
        if bad:
            raise ValueError(f"unknown key(s) {sorted(bad)} in config section [{name}]")
        for key, value in values.items():
            if isinstance(value, list):  # TOML arrays -> the tuples of the dataclasses
                values[key] = tuple(value)
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
    """Load a TOML config file; ``None`` gives the SPEC defaults.

    Example:
        >>> cfg = load_config(None)
        >>> cfg.quality.theta_e
        0.5
    """
    if path is None:
        return LensdistConfig()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"config file not found: {path}")
    with path.open("rb") as f:
        try:
            data = tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"config file {path} is not valid TOML: {exc}") from exc
    return config_from_dict(data)


def _check_positive_int(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"{name} must be a positive int, got {value!r}")


def _check_fraction(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must be a number in [0, 1], got {value!r}")


def _check_positive_float(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
        math.isfinite(value) and value > 0
    ):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
