"""``[classifier]``, ``[regression]``: the eigen-space classifier and Delta regression (docs/method.md, section 8)."""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import choice, integer

__all__ = ["ClassifierConfig", "MAX_NEIGHBOURS", "RegressionConfig"]


@dataclass(frozen=True)
class ClassifierConfig:
    """The eigen-space classifier (docs/method.md section 8): its eigenvectors per class and its metric.

    Its constants (the reject quantile, the neighbours of the Delta interpolation) are named in
    :mod:`~lensdist_torch.classify.eigenspace` (``REJECT_QUANTILE``, ``N_NEIGHBOURS``).

    Example:
        >>> from dataclasses import replace
        >>> ClassifierConfig().metric, replace(ClassifierConfig(), metric="delta_max").metric
        ('delta_avg', 'delta_max')
    """

    n_eigenvectors: int = 10
    metric: str = "delta_avg"

    def __post_init__(self) -> None:
        integer(self, "n_eigenvectors")
        choice(self, "metric", ("delta_avg", "delta_max"))


#: The most neighbours of the Delta regression (``regression.k``; ``DeltaRegressor.load`` refuses a
#: checkpoint's k beyond it): a local median stays consistent while k / N shrinks; the usual
#: k ~ sqrt(N) is 110 at the protocol's 12000 training pairs (the validation chose 8).
MAX_NEIGHBOURS = 100


@dataclass(frozen=True)
class RegressionConfig:
    """Settings of :class:`~lensdist_torch.classify.regression.DeltaRegressor`.

    Attributes:
        n_components: PCA components kept (capped by the training set).
        k: neighbours whose median Delta is the prediction, at most ``MAX_NEIGHBOURS``.

    Its confidence's constants are named in :mod:`~lensdist_torch.classify.regression`
    (``CANNOT_TELL_FRACTION``, ``CONFIDENCE_THRESHOLD``).

    Example:
        >>> from dataclasses import replace
        >>> RegressionConfig().k, replace(RegressionConfig(), k=16).k
        (8, 16)
    """

    n_components: int = 384
    k: int = 8

    def __post_init__(self) -> None:
        integer(self, "n_components")
        integer(self, "k", hi=MAX_NEIGHBOURS, why="a local median; config.MAX_NEIGHBOURS")
