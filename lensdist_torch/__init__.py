"""lensdist_torch: registration-quality maps and the analysis of lens distortions, in PyTorch."""

from .config import (
    ClassifierConfig,
    DistortionConfig,
    ImageConfig,
    LensdistConfig,
    ProtocolConfig,
    QualityConfig,
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

__version__ = "0.1.0"
