"""The whole configuration: :class:`LensdistConfig`, one section per concern, and its TOML files.

A TOML file's sections map one to one onto the section dataclasses (the modules beside this
one); unknown sections or keys are an error (a typo must not silently fall back to a default),
and so is a value of the wrong type or out of range, with a one-line ``ValueError`` naming the
section and field. ``configs/paper.toml`` writes every default out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lensdist_torch.config.analysis import AnalysisConfig
from lensdist_torch.config.checks import show
from lensdist_torch.config.classify import ClassifierConfig, RegressionConfig
from lensdist_torch.config.protocol import DistortionConfig, ImageConfig, ProtocolConfig
from lensdist_torch.config.quality import QualityConfig
from lensdist_torch.config.registration import RegistrationConfig, SelfCalConfig
from lensdist_torch.config.retired import INERT, RETIRED, drop_constants, moved_names, settle_moves, without_key
from lensdist_torch.config.sequence import CalibrationConfig, MultiViewConfig
from lensdist_torch.config.toml import check_tables, read_toml

__all__ = [
    "FROM_CLASS_TOLERANCE",
    "LensdistConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
    "stored_config",
]


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
        ValueError: an unknown section or key, a section that is not a table, a bad value, or a
            key that became a constant of the method at another value than the constant's
            (:data:`~lensdist_torch.config.retired.RETIRED`); the message names the section and the field.

    Example:
        >>> config_from_dict({"quality": {"block_size": 16}, "image": {"height": 320, "width": 416}}).quality.block_size
        16
        >>> config_from_dict({"multiview": {"confidence": 1.5}})
        Traceback (most recent call last):
        ...
        ValueError: calibration.confidence must be a number in ]0, 1[, got 1.5 (written as multiview.confidence)
    """
    moved = moved_names(data)  # a user's old name of a key, for its message
    data = drop_constants(data)  # a key that became a constant of the method, at its value (config/retired.py)
    check_tables(data, {name: {f.name for f in dataclasses.fields(cls)} for name, cls in _SECTIONS.items()})
    try:
        return LensdistConfig(**{name: cls(**data.get(name, {})) for name, cls in _SECTIONS.items()})
    except ValueError as exc:
        named = next((old for new, old in moved.items() if str(exc).startswith(f"{new} ")), None)
        if named is None:
            raise
        raise ValueError(f"{exc} (written as {named})") from None


def stored_config(data: dict[str, Any]) -> LensdistConfig:
    """The config a checkpoint of an earlier version was saved with.

    A retired key is dropped where it had no effect (``protocol.parallax_px`` outside the
    realistic protocol, or 0; those of :data:`INERT` always: ``analysis.relief_z``); where it
    had one, the saved object was made under a protocol this version no longer has, and that
    is a one-line ValueError saying what replaced it. A moved key whose new place the saved
    config also names is dropped: an earlier version wrote every field, both places among them.

    Example:
        >>> stored_config({"calibration": {"parallax": 5}, "selfcal": {"parallax": 0}}).selfcal.parallax
        0
        >>> stored_config({"protocol": {"parallax_px": 1.5}}).protocol.relief
        0.0
        >>> stored_config({"analysis": {"relief_z": 4.0}}).analysis.flat_prior  # the default
        0.5
    """
    protocol = data.get("protocol")
    if isinstance(protocol, dict) and "parallax_px" in protocol:
        px = protocol["parallax_px"]
        if protocol.get("realistic") and px:
            raise ValueError(
                f"saved under the realistic protocol's former fixed parallax (protocol.parallax_px = {px!r}), "
                f"which this version replaced by {RETIRED[('protocol', 'parallax_px')].by}: fit it again"
            )
        data = without_key(data, "protocol", "parallax_px")
    data = settle_moves(data)  # an earlier version wrote both places of a moved key: the new one stands
    for section, key in INERT:
        data = without_key(data, section, key)
    return config_from_dict(data)


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
    data = read_toml(path)
    try:
        return config_from_dict(data)
    except ValueError as exc:
        raise ValueError(f"config file {path}: {exc}") from exc
