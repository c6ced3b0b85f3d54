"""Stateful classification metrics for evaluation loops: a confusion matrix and RMSE per class.

In the manner of torchmetrics: ``update`` accumulates a batch, ``compute`` reports, ``reset``
starts again. Rows of the confusion matrix are the ground truth (1-4, R), columns predicted.
"""

from __future__ import annotations

import torch

from lensdist_torch.geometry.distortion import CLASS_LABELS

__all__ = ["ConfusionMatrix", "ClassRMSE"]


class ConfusionMatrix:
    """Accumulating (C, C) confusion matrix, rows ground truth, columns predicted."""

    def __init__(self, num_classes: int = len(CLASS_LABELS)) -> None:
        self.num_classes = num_classes
        self.matrix = torch.zeros(num_classes, num_classes, dtype=torch.long)

    def update(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        pred, target = pred.reshape(-1).long().cpu(), target.reshape(-1).long().cpu()
        if pred.shape != target.shape:
            raise ValueError(f"pred and target must have the same length, got {pred.numel()} and {target.numel()}")
        c = self.num_classes
        if bool(((pred < 0) | (pred >= c) | (target < 0) | (target >= c)).any()):
            raise ValueError(f"class indices must lie in 0..{c - 1}")
        self.matrix += torch.bincount(target * c + pred, minlength=c * c).view(c, c)

    def compute(self) -> torch.Tensor:
        return self.matrix.clone()

    def rate(self) -> float:
        total = int(self.matrix.sum())
        return float(self.matrix.diag().sum()) / total if total else float("nan")


class ClassRMSE:
    """RMSE of a predicted Delta per ground-truth class (distorted classes only)."""

    def __init__(self, num_classes: int = 4) -> None:
        self.num_classes = num_classes
        self.sq = torch.zeros(num_classes, dtype=torch.float64)
        self.err = torch.zeros(num_classes, dtype=torch.float64)
        self.n = torch.zeros(num_classes, dtype=torch.long)

    def update(self, pred: torch.Tensor, target: torch.Tensor, target_class: torch.Tensor) -> None:
        pred, target, cls = pred.reshape(-1).double().cpu(), target.reshape(-1).double().cpu(), target_class.reshape(-1).long().cpu()
        keep = cls < self.num_classes
        e = (pred - target)[keep]
        cls = cls[keep]
        self.sq += torch.bincount(cls, weights=e * e, minlength=self.num_classes)
        self.err += torch.bincount(cls, weights=e, minlength=self.num_classes)
        self.n += torch.bincount(cls, minlength=self.num_classes)

    def compute(self) -> dict:
        n = self.n.clamp_min(1).double()
        rmse = torch.where(self.n > 0, torch.sqrt(self.sq / n), torch.full_like(n, float("nan")))
        bias = torch.where(self.n > 0, self.err / n, torch.full_like(n, float("nan")))
        return {"rmse": rmse.tolist(), "bias": bias.tolist(), "n": self.n.tolist()}
