"""Estimators that learn from quality maps: the eigen-space classifier and the Delta regression.

Modules:

* :mod:`~lensdist_torch.classify.eigenspace`: the per-class eigen-space classifier (paper 4.2).
* :mod:`~lensdist_torch.classify.regression`: Delta_avg and Delta_max regressed from a map, no classes.
* ``_checkpoint.py``: the checks of a checkpoint's payload before anything is built from it.

The estimators and their result types are exported here and imported on first use (PEP 562).

Example:
    >>> import torch
    >>> from lensdist_torch.classify import DeltaRegressor
    >>> reg = DeltaRegressor(12, n_components=3, k=4).fit(torch.rand(50, 12), torch.rand(50) * 14, torch.rand(50) * 79)
    >>> tuple(reg(torch.rand(3, 12)).delta_avg.shape)
    (3,)
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.classify.eigenspace": ("ClassifierResult", "EigenSpaceClassifier"),
    "lensdist_torch.classify.regression": ("DeltaRegressor", "RegressionResult"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
