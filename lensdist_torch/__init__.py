"""lensdist_torch: registration-quality maps and the analysis of lens distortions, in PyTorch.

The library (the metric, the distortion model, registration, self-calibration, the
classifiers) is imported eagerly; the application layer (data sets, workflows) only when one
of its names is first used, so ``import lensdist_torch`` loads neither tqdm nor matplotlib.
See ``docs/architecture.md`` for the layers.
"""

from __future__ import annotations

import importlib
from typing import Any

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

__version__ = "0.2.0"

#: Names of the application layer, imported on first use: name -> module.
_LAZY = {
    "analyze_pair": "lensdist_torch.workflows.analyze",
    "reproduce": "lensdist_torch.workflows.reproduce",
    "generate": "lensdist_torch.data.shards",
    "load_set": "lensdist_torch.data.shards",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'lensdist_torch' has no attribute {name!r}")


__all__ = [
    "CLASS_LABELS",
    "AnalysisConfig",
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
