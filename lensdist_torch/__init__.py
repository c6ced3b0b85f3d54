"""lensdist_torch: registration-quality maps and the analysis of lens distortions, in PyTorch.

Every public name is imported on first use (PEP 562), so ``import lensdist_torch`` and
``lensdist --help`` load nothing heavy, and the application layer (data sets, workflows) is
never loaded by code that only wants the metric or the loss. See ``docs/architecture.md``.

Example:
    >>> import lensdist_torch as ld
    >>> ld.LensdistConfig().image.size
    (320, 424)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.2.0"

#: Public name -> the module that defines it.
_LAZY: dict[str, str] = {
    **dict.fromkeys(["EigenSpaceClassifier"], "lensdist_torch.classify.eigenspace"),
    **dict.fromkeys(["DeltaRegressor"], "lensdist_torch.classify.regression"),
    **dict.fromkeys(
        [
            "AnalysisConfig",
            "ClassifierConfig",
            "DistortionConfig",
            "ImageConfig",
            "LensdistConfig",
            "ProtocolConfig",
            "QualityConfig",
            "RegistrationConfig",
            "RegressionConfig",
            "SelfCalConfig",
            "load_config",
        ],
        "lensdist_torch.config",
    ),
    **dict.fromkeys(["load_image", "load_scene", "scene_names", "to_grey"], "lensdist_torch.core.images"),
    **dict.fromkeys(
        [
            "CLASS_LABELS",
            "delta_avg",
            "delta_max",
            "distort_points",
            "distortion_class",
            "distortion_grid",
            "estimated_class",
            "pixel_offsets",
            "render_distorted",
            "undistort_points",
        ],
        "lensdist_torch.geometry.distortion",
    ),
    **dict.fromkeys(["corner_error", "perturb_homography"], "lensdist_torch.geometry.homography"),
    **dict.fromkeys(["estimate_homography", "warp_to_reference"], "lensdist_torch.geometry.registration"),
    **dict.fromkeys(["estimate_distortion"], "lensdist_torch.geometry.selfcal"),
    **dict.fromkeys(["ClassRMSE", "ConfusionMatrix"], "lensdist_torch.metric.classification"),
    **dict.fromkeys(["RegistrationQualityMetric"], "lensdist_torch.metric.stateful"),
    **dict.fromkeys(
        [
            "ErrorImages",
            "LocalCriteria",
            "QualityResult",
            "RegistrationQuality",
            "RegistrationQualityLoss",
            "block_counts",
            "block_pool",
            "counts_to_map",
            "erode_valid",
            "error_images",
            "local_criteria",
            "quality_map",
            "registration_error_counts",
            "registration_quality",
            "registration_quality_loss",
        ],
        "lensdist_torch.metric.quality",
    ),
    **dict.fromkeys(["analyze_pair"], "lensdist_torch.workflows.analyze"),
    **dict.fromkeys(["reproduce"], "lensdist_torch.workflows.reproduce"),
    **dict.fromkeys(["generate", "load_set"], "lensdist_torch.data.shards"),
}

if TYPE_CHECKING:  # for type checkers and IDEs: the same names, eagerly
    from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
    from lensdist_torch.classify.regression import DeltaRegressor
    from lensdist_torch.config import (
        AnalysisConfig,
        ClassifierConfig,
        DistortionConfig,
        ImageConfig,
        LensdistConfig,
        ProtocolConfig,
        QualityConfig,
        RegistrationConfig,
        RegressionConfig,
        SelfCalConfig,
        load_config,
    )
    from lensdist_torch.core.images import load_image, load_scene, scene_names, to_grey
    from lensdist_torch.data.shards import generate, load_set
    from lensdist_torch.geometry.distortion import (
        CLASS_LABELS,
        delta_avg,
        delta_max,
        distort_points,
        distortion_class,
        distortion_grid,
        estimated_class,
        pixel_offsets,
        render_distorted,
        undistort_points,
    )
    from lensdist_torch.geometry.homography import corner_error, perturb_homography
    from lensdist_torch.geometry.registration import estimate_homography, warp_to_reference
    from lensdist_torch.geometry.selfcal import estimate_distortion
    from lensdist_torch.metric.classification import ClassRMSE, ConfusionMatrix
    from lensdist_torch.metric.quality import (
        ErrorImages,
        LocalCriteria,
        QualityResult,
        RegistrationQuality,
        RegistrationQualityLoss,
        block_counts,
        block_pool,
        counts_to_map,
        erode_valid,
        error_images,
        local_criteria,
        quality_map,
        registration_error_counts,
        registration_quality,
        registration_quality_loss,
    )
    from lensdist_torch.metric.stateful import RegistrationQualityMetric
    from lensdist_torch.workflows.analyze import analyze_pair
    from lensdist_torch.workflows.reproduce import reproduce


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'lensdist_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "AnalysisConfig",
    "CLASS_LABELS",
    "ClassRMSE",
    "ClassifierConfig",
    "ConfusionMatrix",
    "DeltaRegressor",
    "DistortionConfig",
    "EigenSpaceClassifier",
    "ErrorImages",
    "ImageConfig",
    "LensdistConfig",
    "LocalCriteria",
    "ProtocolConfig",
    "QualityConfig",
    "QualityResult",
    "RegistrationConfig",
    "RegistrationQuality",
    "RegistrationQualityLoss",
    "RegistrationQualityMetric",
    "RegressionConfig",
    "SelfCalConfig",
    "analyze_pair",
    "block_counts",
    "block_pool",
    "corner_error",
    "counts_to_map",
    "delta_avg",
    "delta_max",
    "distort_points",
    "distortion_class",
    "distortion_grid",
    "erode_valid",
    "error_images",
    "estimate_distortion",
    "estimate_homography",
    "estimated_class",
    "generate",
    "load_config",
    "load_image",
    "load_scene",
    "load_set",
    "local_criteria",
    "perturb_homography",
    "pixel_offsets",
    "quality_map",
    "registration_error_counts",
    "registration_quality",
    "registration_quality_loss",
    "render_distorted",
    "reproduce",
    "scene_names",
    "to_grey",
    "undistort_points",
    "warp_to_reference",
]
