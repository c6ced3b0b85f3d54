"""The registration-quality metric, its loss and stateful metrics (docs/method.md, sections 2-5).

The top level (``lensdist_torch``) exports what most users need: :func:`quality_map`,
:func:`registration_quality` and :class:`RegistrationQuality`, the loss
:func:`registration_quality_loss` and :class:`RegistrationQualityLoss`, the stateful
:class:`RegistrationQualityMetric` (a ``torchmetrics.Metric`` where torchmetrics is installed).
The paper's pieces, for those who build on them, are exported here: the per-pixel criteria
(:func:`local_criteria`), the error images (:func:`error_images`, :func:`erode_valid`), block
pooling (:func:`block_pool`, :func:`block_counts`, :func:`floor_ratio`), the compact counts
(:func:`registration_error_counts`, :func:`counts_to_map`) and the result types; the metric's
settings are :class:`QualityConfig`; the evaluation metrics :class:`ConfusionMatrix` and
:class:`ClassRMSE`.

Modules: :mod:`~lensdist_torch.metric.quality` (maps and modules), :mod:`~lensdist_torch.metric.loss`,
:mod:`~lensdist_torch.metric.criteria` (per-pixel criteria and error images),
:mod:`~lensdist_torch.metric.pooling` (blocks and floor), :mod:`~lensdist_torch.metric.stateful`
(accumulating over a data set) and :mod:`~lensdist_torch.metric.classification`.

Example:
    >>> import torch
    >>> from lensdist_torch.metric import block_pool, local_criteria
    >>> x = torch.rand(1, 1, 16, 16)
    >>> float(local_criteria(x, x).a.min()), tuple(block_pool(torch.ones(1, 1, 16, 16)).shape)
    (1.0, (1, 1, 2, 2))
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it (imported on first use, PEP 562:
#: the stateful metrics' torchmetrics loads only where they are used).
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.config": ("QualityConfig",),
    "lensdist_torch.metric.classification": ("ClassRMSE", "ConfusionMatrix"),
    "lensdist_torch.metric.quality": (
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
        "floor_ratio",
        "local_criteria",
        "quality_map",
        "registration_error_counts",
        "registration_quality",
        "registration_quality_loss",
    ),
    "lensdist_torch.metric.stateful": ("QualityMetricResult", "RegistrationQualityMetric"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
