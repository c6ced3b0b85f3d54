"""lensdist_torch: registration-quality maps and the analysis of lens distortions, in PyTorch."""

from .config import (
    ClassifierConfig,
    DistortionConfig,
    ImageConfig,
    LensdistConfig,
    ProtocolConfig,
    QualityConfig,
    RegistrationConfig,
    load_config,
)
from .images import load_image, load_scene, scene_names, to_grey
from .quality import (
    ErrorImages,
    LocalCriteria,
    QualityResult,
    RegistrationQuality,
    RegistrationQualityLoss,
    block_counts,
    block_pool,
    erode_valid,
    error_images,
    local_criteria,
    quality_map,
    registration_error_counts,
    registration_quality,
    registration_quality_loss,
)

from .quality import counts_to_map
from .distortion import (
    CLASS_LABELS,
    delta_avg,
    delta_max,
    distort_points,
    distortion_class,
    distortion_grid,
    pixel_offsets,
    render_distorted,
    undistort_points,
)
from .registration import corner_error, estimate_homography, perturb_homography, warp_to_reference
from .eigenspace import EigenSpaceClassifier
from .selfcal import SelfCalConfig, estimate_distortion
from .regression import DeltaRegressor
from .analysis import analyze_pair

__version__ = "0.1.0"

__all__ = [
    "CLASS_LABELS",
    "ClassifierConfig",
    "DeltaRegressor",
    "DistortionConfig",
    "EigenSpaceClassifier",
    "ErrorImages",
    "ImageConfig",
    "LensdistConfig",
    "LocalCriteria",
    "ProtocolConfig",
    "QualityConfig",
    "RegistrationConfig",
    "QualityResult",
    "RegistrationQuality",
    "RegistrationQualityLoss",
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
    "load_config",
    "load_image",
    "load_scene",
    "local_criteria",
    "perturb_homography",
    "pixel_offsets",
    "quality_map",
    "registration_error_counts",
    "registration_quality",
    "registration_quality_loss",
    "render_distorted",
    "scene_names",
    "to_grey",
    "undistort_points",
    "warp_to_reference",
]
