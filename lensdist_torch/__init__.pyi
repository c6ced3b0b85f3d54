# Generated from _EXPORTS in __init__.py by `python tests/meta/test_public_names.py --write`:
# do not edit. Type checkers and IDEs read this file; the package loads each name on first use.

from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence as synthetic_sequence
from lensdist_torch.calibration.direct import calibrate_sequence as calibrate_sequence
from lensdist_torch.classify.eigenspace import EigenSpaceClassifier as EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor as DeltaRegressor
from lensdist_torch.config import AnalysisConfig as AnalysisConfig
from lensdist_torch.config import CalibrationConfig as CalibrationConfig
from lensdist_torch.config import ClassifierConfig as ClassifierConfig
from lensdist_torch.config import DistortionConfig as DistortionConfig
from lensdist_torch.config import ImageConfig as ImageConfig
from lensdist_torch.config import LensdistConfig as LensdistConfig
from lensdist_torch.config import MultiViewConfig as MultiViewConfig
from lensdist_torch.config import ProtocolConfig as ProtocolConfig
from lensdist_torch.config import QualityConfig as QualityConfig
from lensdist_torch.config import RegistrationConfig as RegistrationConfig
from lensdist_torch.config import RegressionConfig as RegressionConfig
from lensdist_torch.config import SelfCalConfig as SelfCalConfig
from lensdist_torch.config import load_config as load_config
from lensdist_torch.core.images import load_image as load_image
from lensdist_torch.core.images import load_scene as load_scene
from lensdist_torch.core.images import scene_names as scene_names
from lensdist_torch.core.images import to_grey as to_grey
from lensdist_torch.data.shards import generate as generate
from lensdist_torch.data.shards import load_set as load_set
from lensdist_torch.geometry.distortion import CLASS_LABELS as CLASS_LABELS
from lensdist_torch.geometry.distortion import delta_avg as delta_avg
from lensdist_torch.geometry.distortion import delta_max as delta_max
from lensdist_torch.geometry.distortion import distort_points as distort_points
from lensdist_torch.geometry.distortion import distortion_class as distortion_class
from lensdist_torch.geometry.distortion import distortion_grid as distortion_grid
from lensdist_torch.geometry.distortion import estimated_class as estimated_class
from lensdist_torch.geometry.distortion import pixel_offsets as pixel_offsets
from lensdist_torch.geometry.distortion import render_distorted as render_distorted
from lensdist_torch.geometry.distortion import undistort_points as undistort_points
from lensdist_torch.geometry.homography import corner_error as corner_error
from lensdist_torch.geometry.homography import perturb_homography as perturb_homography
from lensdist_torch.geometry.undistort import Undistort as Undistort
from lensdist_torch.geometry.undistort import undistort_image as undistort_image
from lensdist_torch.metric.classification import ClassRMSE as ClassRMSE
from lensdist_torch.metric.classification import ConfusionMatrix as ConfusionMatrix
from lensdist_torch.metric.quality import RegistrationQuality as RegistrationQuality
from lensdist_torch.metric.quality import RegistrationQualityLoss as RegistrationQualityLoss
from lensdist_torch.metric.quality import quality_map as quality_map
from lensdist_torch.metric.quality import registration_quality as registration_quality
from lensdist_torch.metric.quality import registration_quality_loss as registration_quality_loss
from lensdist_torch.metric.stateful import RegistrationQualityMetric as RegistrationQualityMetric
from lensdist_torch.registration.direct import estimate_homography as estimate_homography
from lensdist_torch.registration.direct import warp_to_reference as warp_to_reference
from lensdist_torch.selfcal.fit import estimate_distortion as estimate_distortion
from lensdist_torch.workflows.analyze import analyze_batch as analyze_batch
from lensdist_torch.workflows.analyze import analyze_pair as analyze_pair
from lensdist_torch.workflows.pair_analysis import PairAnalysis as PairAnalysis
from lensdist_torch.workflows.reproduce import reproduce as reproduce

__version__: str
__all__ = [
    "AnalysisConfig",
    "CLASS_LABELS",
    "CalibrationConfig",
    "ClassRMSE",
    "ClassifierConfig",
    "ConfusionMatrix",
    "DeltaRegressor",
    "DistortionConfig",
    "EigenSpaceClassifier",
    "ImageConfig",
    "LensdistConfig",
    "MultiViewConfig",
    "PairAnalysis",
    "ProtocolConfig",
    "QualityConfig",
    "RegistrationConfig",
    "RegistrationQuality",
    "RegistrationQualityLoss",
    "RegistrationQualityMetric",
    "RegressionConfig",
    "SelfCalConfig",
    "Undistort",
    "analyze_batch",
    "analyze_pair",
    "calibrate_sequence",
    "corner_error",
    "delta_avg",
    "delta_max",
    "distort_points",
    "distortion_class",
    "distortion_grid",
    "estimate_distortion",
    "estimate_homography",
    "estimated_class",
    "generate",
    "load_config",
    "load_image",
    "load_scene",
    "load_set",
    "perturb_homography",
    "pixel_offsets",
    "quality_map",
    "registration_quality",
    "registration_quality_loss",
    "render_distorted",
    "reproduce",
    "scene_names",
    "synthetic_sequence",
    "to_grey",
    "undistort_image",
    "undistort_points",
    "warp_to_reference",
]
