"""``[classifier]``, ``[regression]``: the eigen-space classifier and Delta regression (docs/method.md, section 8)."""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import choice, integer, real

__all__ = ["ClassifierConfig", "MAX_NEIGHBOURS", "RegressionConfig"]


@dataclass(frozen=True)
class ClassifierConfig:
    """The eigen-space classifier (docs/method.md section 8).

    Example:
        >>> from dataclasses import replace
        >>> ClassifierConfig().metric, replace(ClassifierConfig(), metric="delta_max").metric
        ('delta_avg', 'delta_max')
    """

    n_eigenvectors: int = 10
    metric: str = "delta_avg"
    reject_quantile: float = 0.95
    n_neighbours: int = 4

    def __post_init__(self) -> None:
        integer(self, "n_eigenvectors")
        integer(self, "n_neighbours")
        choice(self, "metric", ("delta_avg", "delta_max"))
        real(self, "reject_quantile", lo=0, hi=1, lo_open=True)


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
        cannot_tell_fraction: neighbour spread of Delta_avg, as a fraction of the class range,
            at which confidence is 0.5, in ]0, 1].
        confidence_threshold: below this confidence the answer is "cannot tell".

    Example:
        >>> from dataclasses import replace
        >>> RegressionConfig().k, replace(RegressionConfig(), k=16).k
        (8, 16)
    """

    n_components: int = 384
    k: int = 8
    cannot_tell_fraction: float = 0.125
    confidence_threshold: float = 0.5

    def __post_init__(self) -> None:
        integer(self, "n_components")
        integer(self, "k", hi=MAX_NEIGHBOURS, why="a local median; config.MAX_NEIGHBOURS")
        real(self, "cannot_tell_fraction", lo=0, hi=1, lo_open=True, why="a share of the class range")
        real(self, "confidence_threshold", lo=0, hi=1)
