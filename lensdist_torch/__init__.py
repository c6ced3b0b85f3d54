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

from lensdist_torch._lazy import lazy_exports

__version__ = "0.2.0"

#: The public API, its one list: module -> the names taken from it. ``__all__``, ``dir()``, the
#: lazy loading and the stub ``__init__.pyi`` that type checkers and IDEs read are built from it
#: (after an edit: ``python tests/meta/test_public_names.py --write``; a test checks the stub).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.config": (
        "AnalysisConfig",
        "CalibrationConfig",
        "ClassifierConfig",
        "DistortionConfig",
        "ImageConfig",
        "LensdistConfig",
        "MultiViewConfig",
        "ProtocolConfig",
        "QualityConfig",
        "RegistrationConfig",
        "RegressionConfig",
        "SelfCalConfig",
        "load_config",
    ),
    "lensdist_torch.core.images": ("load_image", "load_scene", "scene_names", "to_grey"),
    # the metric: its function and module, the loss and its module, the stateful metric; the
    # paper's pieces (criteria, error images, pooling, counts, result types) in lensdist_torch.metric
    "lensdist_torch.metric.quality": (
        "RegistrationQuality",
        "RegistrationQualityLoss",
        "quality_map",
        "registration_quality",
        "registration_quality_loss",
    ),
    "lensdist_torch.metric.stateful": ("RegistrationQualityMetric",),
    "lensdist_torch.metric.classification": ("ClassRMSE", "ConfusionMatrix"),
    "lensdist_torch.geometry.distortion": (
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
    ),
    "lensdist_torch.geometry.homography": ("corner_error", "perturb_homography"),
    "lensdist_torch.geometry.undistort": ("Undistort", "undistort_image"),
    "lensdist_torch.registration.direct": ("estimate_homography", "warp_to_reference"),
    "lensdist_torch.selfcal.fit": ("estimate_distortion",),
    "lensdist_torch.calibration.direct": ("calibrate_sequence",),
    "lensdist_torch.classify.eigenspace": ("EigenSpaceClassifier",),
    "lensdist_torch.classify.regression": ("DeltaRegressor",),
    "lensdist_torch.data.shards": ("generate", "load_set"),
    "lensdist_torch.workflows.analyze": ("analyze_batch", "analyze_pair"),
    "lensdist_torch.workflows.pair_analysis": ("PairAnalysis",),
    "lensdist_torch.calibration.controllers.calibrate": ("synthetic_sequence",),
    "lensdist_torch.workflows.reproduce": ("reproduce",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
