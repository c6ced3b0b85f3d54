"""Every number the library uses, as frozen dataclasses with the method's defaults.

The defaults are the project's conventions (``docs/method.md``); a TOML file in ``configs/``
may override any field. Its sections map one to one onto the dataclasses, one module per concept::

    [quality]       thresholds, temperature, block size      quality.py       (docs/method.md 2-5)
    [image]         analysis size                             protocol.py      (section 1)
    [distortion]    coefficient ranges                        protocol.py      (section 6, eq. 4)
    [protocol]      pair protocol and set sizes               protocol.py      (section 7)
    [registration]  homography registration                   registration.py  (in the data fingerprint)
    [selfcal]       self-calibration of (k2, k4) and H        registration.py
    [classifier]    eigen-space classifier                    classify.py      (section 8)
    [regression]    Delta regression without classes          classify.py
    [analysis]      the decision of ``analyze``               analysis.py
    [calibration]   a sequence: coverage, the direct path     sequence.py      (``lensdist calibrate``)
    [multiview]     the same by COLMAP's bundle adjustment    sequence.py

:class:`LensdistConfig` holds one of each, and ``lensdist.py`` reads and writes it (TOML, dicts).
Every setting a user may change lives in this package; the method's constants (thresholds,
counts, margins nobody sets) are named constants in the modules that use them (docs/method.md).
Three kinds of field: the choices a user makes; the ``chunk_size`` of ``[quality]``,
``[registration]`` and ``[selfcal]`` (speed only, the results do not depend on them); and six
``[analysis]`` fields that ``fit_confidence`` writes from a validation split
(``min_confidence``, ``regression_confidence_scale`` and ``_shift``, ``selfcal_std_scale``,
``interval_std_scale``, ``flat_prior``).
The field checks, with their ``section.field`` messages, and the one "this config or its
defaults" helper are in
:mod:`~lensdist_torch.config.checks`; the training scripts (``train/``) read their TOML files and
``--set`` overrides with the same reader (:mod:`~lensdist_torch.config.toml`). A key an earlier
version read, a constant of the method now among them, loads by the one table of
:mod:`~lensdist_torch.config.retired`.

Example:
    >>> from lensdist_torch.config import LensdistConfig, config_to_dict
    >>> config_to_dict(LensdistConfig())["quality"]["block_size"]
    8
"""

from lensdist_torch.config.analysis import AnalysisConfig
from lensdist_torch.config.classify import MAX_NEIGHBOURS, ClassifierConfig, RegressionConfig
from lensdist_torch.config.lensdist import (
    FROM_CLASS_TOLERANCE,
    LensdistConfig,
    config_from_dict,
    config_to_dict,
    load_config,
    stored_config,
)
from lensdist_torch.config.protocol import DistortionConfig, ImageConfig, ProtocolConfig
from lensdist_torch.config.quality import QualityConfig
from lensdist_torch.config.registration import RegistrationConfig, SelfCalConfig
from lensdist_torch.config.retired import INERT, RETIRED, retired_keys
from lensdist_torch.config.sequence import MULTIVIEW_MODELS, CalibrationConfig, MultiViewConfig
from lensdist_torch.config.toml import (
    apply_overrides,
    check_tables,
    layered_tables,
    merge_tables,
    parse_overrides,
    read_toml,
)

__all__ = [
    "AnalysisConfig",
    "CalibrationConfig",
    "ClassifierConfig",
    "DistortionConfig",
    "FROM_CLASS_TOLERANCE",
    "ImageConfig",
    "LensdistConfig",
    "MAX_NEIGHBOURS",
    "MULTIVIEW_MODELS",
    "MultiViewConfig",
    "INERT",
    "RETIRED",
    "ProtocolConfig",
    "QualityConfig",
    "RegistrationConfig",
    "RegressionConfig",
    "SelfCalConfig",
    "config_from_dict",
    "config_to_dict",
    "apply_overrides",
    "check_tables",
    "layered_tables",
    "load_config",
    "merge_tables",
    "parse_overrides",
    "read_toml",
    "retired_keys",
    "stored_config",
]
