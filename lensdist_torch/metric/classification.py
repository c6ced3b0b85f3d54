"""Stateful classification metrics for evaluation loops: a confusion matrix and RMSE per class.

In the manner of torchmetrics: ``update`` accumulates a batch, ``compute`` reports, ``reset``
starts again. Rows of the confusion matrix are the ground truth (1-4, R), columns predicted.
"""

from __future__ import annotations

import torch

from lensdist_torch.geometry.distortion import CLASS_LABELS

__all__ = ["ConfusionMatrix", "ClassRMSE"]


class ConfusionMatrix:
    """Accumulating (C, C) confusion matrix, rows ground truth, columns predicted.

    Args:
        num_classes: C, 5 by default (the distortion classes 1-4 and R).

    Example:
        >>> cm = ConfusionMatrix(3)
        >>> cm.update(torch.tensor([0, 1, 2, 2]), torch.tensor([0, 1, 1, 2]))
        >>> cm.compute().tolist()
        [[1, 0, 0], [0, 1, 1], [0, 0, 1]]
        >>> cm.rate()
        0.75
        >>> cm.reset()
        >>> int(cm.compute().sum())
        0
    """

    def __init__(self, num_classes: int = len(CLASS_LABELS)) -> None:
        self.num_classes = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.long)

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        """Add a batch of predictions.

        Args:
            pred: (N,) predicted class indices in 0..C-1 (any shape with N elements).
            target: (N,) ground-truth class indices in 0..C-1.

        Raises:
            ValueError: different lengths, or an index outside 0..C-1.
        """
        pred, target = pred.reshape(-1).long().cpu(), target.reshape(-1).long().cpu()
        if pred.shape != target.shape:
            raise ValueError(f"pred and target must have the same length, got {pred.numel()} and {target.numel()}")
        c = self.num_classes
        if bool(((pred < 0) | (pred >= c) | (target < 0) | (target >= c)).any()):
            raise ValueError(f"class indices must lie in 0..{c - 1}")
        self.matrix += torch.bincount(target * c + pred, minlength=c * c).view(c, c)

    def compute(self) -> torch.Tensor:
        """The (C, C) int64 counts (a copy): rows ground truth, columns predicted."""
        return self.matrix.clone()

    def rate(self) -> float:
        """The fraction of correct predictions (the trace over the total); NaN when empty."""
        total = int(self.matrix.sum())
        return float(self.matrix.diag().sum()) / total if total else float("nan")

    def reset(self) -> None:
        """Forget every prediction."""
        self.matrix.zero_()


class ClassRMSE:
    """RMSE and bias of a predicted Delta per ground-truth class (distorted classes only).

    Args:
        num_classes: classes kept (0..num_classes-1); pairs of higher classes (R) are skipped.

    Example:
        >>> m = ClassRMSE(2)
        >>> m.update(torch.tensor([1.0, 3.0, 5.0]), torch.tensor([0.0, 3.0, 4.0]), torch.tensor([0, 1, 1]))
        >>> out = m.compute()
        >>> [round(r, 4) for r in out["rmse"]], out["bias"], out["n"]
        ([1.0, 0.7071], [1.0, 0.5], [1, 2])
        >>> m.reset()
        >>> m.compute()["n"]
        [0, 0]
    """

    def __init__(self, num_classes: int = 4) -> None:
        self.num_classes = num_classes
        self.sq = torch.zeros(num_classes, dtype=torch.float64)
        self.err = torch.zeros(num_classes, dtype=torch.float64)
        self.n = torch.zeros(num_classes, dtype=torch.long)

    def update(self, pred: torch.Tensor, target: torch.Tensor, target_class: torch.Tensor) -> None:
        """Add a batch.

        Args:
            pred: (N,) predicted Delta.
            target: (N,) true Delta.
            target_class: (N,) ground-truth class of each pair (classes >= num_classes skipped).
        """
        pred, target, cls = (
            pred.reshape(-1).double().cpu(),
            target.reshape(-1).double().cpu(),
            target_class.reshape(-1).long().cpu(),
        )
        keep = cls < self.num_classes
        e = (pred - target)[keep]
        cls = cls[keep]
        self.sq += torch.bincount(cls, weights=e * e, minlength=self.num_classes)
        self.err += torch.bincount(cls, weights=e, minlength=self.num_classes)
        self.n += torch.bincount(cls, minlength=self.num_classes)

    def compute(self) -> dict:
        """Per class: ``rmse`` and ``bias`` (mean of pred - target; NaN for an empty class), ``n``.

        Returns:
            dict of three lists of length num_classes.
        """
        n = self.n.clamp_min(1).double()
        rmse = torch.where(self.n > 0, torch.sqrt(self.sq / n), torch.full_like(n, float("nan")))
        bias = torch.where(self.n > 0, self.err / n, torch.full_like(n, float("nan")))
        return {"rmse": rmse.tolist(), "bias": bias.tolist(), "n": self.n.tolist()}

    def reset(self) -> None:
        """Forget every pair."""
        self.sq.zero_()
        self.err.zero_()
        self.n.zero_()
