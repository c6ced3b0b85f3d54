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
    [calibration]   a camera's distortion from a sequence (``lensdist calibrate``), the direct path
    [multiview]     the same by bundle adjustment on COLMAP's tracks (``lensdist calibrate``)

The estimators' sections are defined in ``config_estimators.py`` and ``config_sequence.py`` (for
length) and exported here.

Every threshold of a decision lives here, nowhere else.

Unknown sections or keys are an error (a typo must not silently fall back to a default), and
so is a value of the wrong type or out of range: a one-line ``ValueError`` names the section and
field (``protocol.ty_range must be (low, high) ...``); the checks are in ``config_checks.py``.
``configs/paper.toml`` writes every default out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomllib  # Python >= 3.11 (pyproject.toml says why)

from lensdist_torch.config_checks import choice, flag, integer, names, one_line, pair, positive, real, show
from lensdist_torch.config_estimators import AnalysisConfig, RegistrationConfig, RegressionConfig, SelfCalConfig
from lensdist_torch.config_sequence import CalibrationConfig, MultiViewConfig

__all__ = [
    "QualityConfig", "ImageConfig", "DistortionConfig", "ProtocolConfig", "ClassifierConfig",
    "RegistrationConfig", "SelfCalConfig", "RegressionConfig", "AnalysisConfig", "CalibrationConfig", "MultiViewConfig",
    "LensdistConfig",
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

    Example:
        >>> from dataclasses import replace
        >>> QualityConfig().theta_e, replace(QualityConfig(), theta_e=0.6).theta_e
        (0.5, 0.6)
        >>> QualityConfig(theta_e=0.99)
        Traceback (most recent call last):
        ...
        ValueError: quality.theta_e must be a number in ]0, gamma=0.9879[, got 0.99
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
    """Analysis size (docs/method.md section 1): 320 x 424 gives 40 x 53 blocks, feature vectors of 2120.

    Example:
        >>> from dataclasses import replace
        >>> ImageConfig().size, replace(ImageConfig(), width=512).size
        ((320, 424), (320, 512))
    """

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

    Example:
        >>> from dataclasses import replace
        >>> DistortionConfig().k2_max, replace(DistortionConfig(), k2_max=1e-6).k2_max
        (2.5e-06, 1e-06)
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
    ``unseen_scenes``: embedded scenes none of ``scenes``, on which ``lensdist reproduce`` also
    tests every method (a scene unlike the training ones; empty: no such test; not in the data
    fingerprint: the training and test pairs do not depend on it).

    ``realistic`` (off by default) adds the effects of a photograph (docs/method.md section 7,
    the realistic protocol), each drawn per view or per pair: ``gain_range`` (> 0),
    ``offset_range`` (in [-1, 1]), ``gamma_range`` (> 0, log-uniform), ``illumination`` (the
    largest share, in [0, 1[, that a ramp / vignetting darkens), ``noise_range`` (Gaussian
    sigma, in [0, 1]), ``jpeg_quality`` (ints in [1, 100]), ``parallax_px`` (>= 0, the largest
    displacement of I2's samples along the motion), ``occluder_rate`` (share of pairs with a
    moving or occluding patch, in [0, 1]) and ``occluder_area`` (its share of the frame, in
    ]0, 1]).

    Example:
        >>> from dataclasses import replace
        >>> ProtocolConfig().n_train, replace(ProtocolConfig(), n_train=100).n_train
        (12000, 100)
        >>> ProtocolConfig(ty_range=(40, 0))
        Traceback (most recent call last):
        ...
        ValueError: protocol.ty_range must be (low, high): two finite numbers with low <= high, got (40, 0) (tuple)
    """

    seed: int = 0
    scenes: tuple[str, ...] = ("gravel", "grass")
    unseen_scenes: tuple[str, ...] = ("brick",)
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
        names(self, "unseen_scenes", empty=True)
        if set(self.unseen_scenes) & set(self.scenes):
            raise ValueError(f"protocol.unseen_scenes must share no scene with protocol.scenes, both hold "
                             f"{sorted(set(self.unseen_scenes) & set(self.scenes))}")
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
    """The eigen-space classifier (docs/method.md section 8).

    Example:
        >>> from dataclasses import replace
        >>> ClassifierConfig().metric, replace(ClassifierConfig(), metric="delta_max").metric
        ('delta_avg', 'delta_max')
    """

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
class LensdistConfig:
    """All settings, one section per concern.

    Example:
        >>> from dataclasses import replace
        >>> cfg = LensdistConfig()
        >>> cfg.quality.block_size, replace(cfg, image=ImageConfig(96, 128)).image.size
        (8, (96, 128))
        >>> LensdistConfig(image=ImageConfig(321, 424))
        Traceback (most recent call last):
        ...
        ValueError: image size 321 x 424 must be a multiple of quality.block_size=8
    """

    quality: QualityConfig = field(default_factory=QualityConfig)
    image: ImageConfig = field(default_factory=ImageConfig)
    distortion: DistortionConfig = field(default_factory=DistortionConfig)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    selfcal: SelfCalConfig = field(default_factory=SelfCalConfig)
    regression: RegressionConfig = field(default_factory=RegressionConfig)
    analysis: AnalysisConfig = field(default_factory=AnalysisConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    multiview: MultiViewConfig = field(default_factory=MultiViewConfig)

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

#: ``lensdist undistort --from``: a file's class must be the one its coefficients give, Delta_avg at
#: the paper's frame within this share of the class's bounds (the analysis sizes' rounding moves
#: it by less than 0.5 %; the audit's class-R file, Delta_avg 12.6 px, is 50 times the R bound).
FROM_CLASS_TOLERANCE = 0.02


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
        ValueError: not a readable UTF-8 TOML file (a UTF-8 byte-order mark is skipped), or an
            invalid config; the one-line message names the file and the section and field.

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
        raw = path.read_bytes()
        if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
            raise ValueError(f"config file {path} starts with a UTF-16 byte-order mark: save it as UTF-8")
        # a UTF-8 byte-order mark (Windows editors) is not TOML: skipped, as Python's utf-8-sig does
        data = tomllib.loads(raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
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
