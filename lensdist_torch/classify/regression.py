"""Delta regression without classes: Delta_avg and Delta_max straight from the quality map.

Fitted on all training pairs at once (no per-class split). A map is described by its top
``n_components`` PCA coefficients (``torch.linalg.svd`` in float64 on the CPU) plus the norm of
its residual outside that subspace, so that nearly empty maps stay close to each other; the
prediction is the median Delta of the ``k`` nearest training pairs in that space. Classes follow
from the predicted value (``distortion_class``).

The defaults (384 components, 8 neighbours, median) were chosen on a validation split of the
training set (the last fifth held out), where they beat the eigen-space classifier's 4-NN in
every class; a ridge regression on degree-2 PCA features (the first version) lost to it in
classes 1 and 4.

Confidence: the spread of the neighbours' Delta_avg (1.4826 x their median absolute deviation)
is the std of the estimate; ``confidence = s0 / (s0 + std)`` with ``s0 =
CANNOT_TELL_FRACTION * Delta_top`` (0.125 of it), so confidence < 0.5 ("cannot tell")
where similar maps came from very different lenses, typically nearly empty maps (little
motion).

Everything fitted is a buffer (float16 for the basis and the training coefficients, to keep
the checkpoint small); checkpoints carry a format version and the config.
"""

from __future__ import annotations

import numbers
from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

from lensdist_torch.classify._checkpoint import (
    FEATURE_RANGE,
    check_deltas,
    check_extra,
    check_features_domain,
    check_state,
    in_range,
    load_payload,
    max_coefficient_norm,
    max_delta,
    orthonormal_rows,
    positive_int,
    row_norms_below,
    save_model,
)
from lensdist_torch.config import MAX_NEIGHBOURS, LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.storage import CheckpointError
from lensdist_torch.geometry.distortion import METRICS, delta_top, estimated_class

__all__ = ["DeltaRegressor", "RegressionResult", "CHECKPOINT_VERSION"]

#: 3: a content digest (core.storage.content_digest); version 2 files are refused (refit them).
CHECKPOINT_VERSION = 3
_KIND = "lensdist-delta-regression"
_MAD_TO_STD = 1.4826
#: The neighbours' Delta_avg spread, a share of the class range Delta_top, at which the confidence is 0.5.
CANNOT_TELL_FRACTION = 0.125
#: Below this confidence the regression's answer is "cannot tell".
CONFIDENCE_THRESHOLD = 0.5


class RegressionResult(NamedTuple):
    """The regressor's answer for a batch.

    Each (B,): delta_avg, delta_max (px), class_avg, class_max (0..3, or 4 = R below
    ``config.analysis.no_distortion_px``), std_avg, std_max
    (neighbour spread, px), confidence (0, 1] (from std_avg), confident (bool).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> reg = DeltaRegressor(12, n_components=3, k=4)  # every training pair: Delta 5 px (avg), 20 px (max)
        >>> res = reg.fit(torch.rand(50, 12, generator=g), torch.full((50,), 5.0), torch.full((50,), 20.0))(
        ...     torch.rand(2, 12, generator=g))
        >>> res.delta_avg.tolist(), res.std_avg.tolist(), res.confidence.tolist()
        ([5.0, 5.0], [0.0, 0.0], [1.0, 1.0])
        >>> from lensdist_torch.geometry.distortion import CLASS_LABELS
        >>> [CLASS_LABELS[i] for i in res.class_avg]  # 5 px of Delta_avg: class 2 (3.6 to 7.2 px)
        ['2', '2']
    """

    delta_avg: torch.Tensor
    delta_max: torch.Tensor
    class_avg: torch.Tensor
    class_max: torch.Tensor
    std_avg: torch.Tensor
    std_max: torch.Tensor
    confidence: torch.Tensor
    confident: torch.Tensor


class DeltaRegressor(nn.Module):
    """Nearest-neighbour Delta regression in PCA coefficients of the quality map.

    Args:
        n_features: feature-vector length ((H/8)(W/8)).
        config: the config it is fitted under (image size, block size, thresholds).
        n_components: PCA components kept (capped by the training set); default
            ``config.regression.n_components``.
        k: neighbours; default ``config.regression.k``; at most ``config.MAX_NEIGHBOURS``.

    Example:
        >>> reg = DeltaRegressor(12, n_components=3, k=4).fit(torch.rand(50, 12), torch.rand(50) * 14,
        ...                                                   torch.rand(50) * 79)
        >>> reg(torch.rand(2, 12)).delta_avg.shape
        torch.Size([2])
    """

    def __init__(
        self,
        n_features: int,
        config: LensdistConfig | None = None,
        n_components: int | None = None,
        k: int | None = None,
    ) -> None:
        super().__init__()
        self.config = or_defaults(config, LensdistConfig)
        n_components = self.config.regression.n_components if n_components is None else n_components
        k = self.config.regression.k if k is None else k
        for name, value in (("n_features", n_features), ("n_components", n_components), ("k", k)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if k > MAX_NEIGHBOURS:
            raise ValueError(f"k must be at most {MAX_NEIGHBOURS} neighbours (a local median), got {k}")
        self.n_features, self.n_components, self.k = int(n_features), int(n_components), int(k)
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("components", torch.zeros(0, n_features, dtype=torch.float16))
        self.register_buffer("train_coeffs", torch.zeros(0, 1, dtype=torch.float16))
        self.register_buffer("train_delta", torch.zeros(0, 2))
        self.register_buffer("fitted", torch.tensor(False))
        self.extra: dict = {}  # saved with the checkpoint: the scenes fitted on, their texture

    # ------------------------------------------------------------------ fitting
    def _describe(self, x: torch.Tensor) -> torch.Tensor:
        """(B, D) features -> (B, n + 1): PCA coefficients and the residual norm, float32."""
        basis = self.components.float()
        xc = x.float() - self.mean
        y = xc @ basis.T
        resid = (xc - y @ basis).norm(dim=1, keepdim=True)
        return torch.cat([y, resid], 1)

    def fit(self, features: torch.Tensor, delta_avg: torch.Tensor, delta_max: torch.Tensor) -> "DeltaRegressor":
        """Fit on all training pairs at once. features (N, n_features); deltas (N,) in px."""
        x = torch.as_tensor(features)
        n = x.shape[0] if x.dim() == 2 else 0
        if x.dim() != 2 or x.shape[1] != self.n_features:
            raise ValueError(f"features must be (N, {self.n_features}), got {tuple(x.shape)}")
        da, dm = torch.as_tensor(delta_avg).reshape(-1), torch.as_tensor(delta_max).reshape(-1)
        if da.shape != (n,) or dm.shape != (n,):
            raise ValueError(f"delta_avg and delta_max must have shape ({n},)")
        if n < self.k + 1:
            raise ValueError(f"need more than k={self.k} training pairs, got {n}")
        if not (torch.isfinite(x).all() and torch.isfinite(da).all() and torch.isfinite(dm).all()):
            raise ValueError("features and deltas must be finite")
        check_features_domain(x)
        check_deltas(torch.cat([da, dm]), self.config)
        x64 = x.detach().cpu().double()
        mu = x64.mean(0)
        _, _, vh = torch.linalg.svd(x64 - mu, full_matrices=False)
        nc = min(self.n_components, vh.shape[0])
        self.mean = mu.float()
        self.components = vh[:nc].to(torch.float16)  # rounded first: the coefficients use the stored basis
        self.train_coeffs = self._describe(x64).to(torch.float16)
        self.train_delta = torch.stack([da, dm], 1).float().cpu()
        self.fitted.fill_(True)
        return self

    # ------------------------------------------------------------------ prediction
    def forward(self, features: torch.Tensor) -> RegressionResult:
        """Predict both Deltas, their classes and a confidence for (B, n_features) feature vectors."""
        if not bool(self.fitted):
            raise RuntimeError("DeltaRegressor is not fitted")
        x = torch.as_tensor(features)
        if x.dim() != 2 or x.shape[1] != self.n_features:
            raise ValueError(f"features must be (B, {self.n_features}), got {tuple(x.shape)}")
        q = self._describe(x.to(self.mean.device))
        k = min(self.k, self.train_coeffs.shape[0])
        idx = torch.cdist(q, self.train_coeffs.float()).topk(k, largest=False).indices
        nd = self.train_delta[idx]  # (B, k, 2)
        pred = nd.median(dim=1).values  # (B, 2)
        std = _MAD_TO_STD * (nd - pred[:, None, :]).abs().median(dim=1).values
        cfg = self.config
        classes = [estimated_class(pred[:, i], pred[:, 0], metric=m, config=cfg) for i, m in enumerate(METRICS)]
        s0 = CANNOT_TELL_FRACTION * delta_top("delta_avg", cfg)
        conf = s0 / (s0 + std[:, 0])
        confident = conf >= CONFIDENCE_THRESHOLD
        return RegressionResult(
            delta_avg=pred[:, 0], delta_max=pred[:, 1], class_avg=classes[0], class_max=classes[1], std_avg=std[:, 0],
            std_max=std[:, 1], confidence=conf, confident=confident)

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """Write atomically: kind, format version, config, sizes and the buffers.

        ``extra`` (a dict of plain values: names, numbers, lists) is stored beside them; by
        default ``self.extra`` (e.g. the scenes it was fitted on and their texture statistics).
        An existing file at ``path`` is replaced only if it is a checkpoint of this kind
        (FileExistsError otherwise: never an image, a data shard or another file).
        """
        sizes = {"n_features": self.n_features, "n_components": self.n_components, "k": self.k}
        save_model(
            self,
            path,
            kind=_KIND,
            version=CHECKPOINT_VERSION,
            sizes=sizes,
            extra=self.extra if extra is None else extra,
        )

    @classmethod
    def load(cls, path: str | Path, expected: LensdistConfig | None = None, map_location="cpu") -> "DeltaRegressor":
        """Load a checkpoint (``torch.load(weights_only=True)``).

        The content digest is verified, then the payload is validated before anything is
        allocated: the sizes against the stored tensors, every buffer's shape and dtype, finite
        values, values a fit can produce (``classify/_checkpoint.py``), the ``extra`` entries
        read by the analysis.

        Args:
            path: the checkpoint file.
            expected: if given, the image size, block size and quality thresholds must match it.
            map_location: ``torch.load``'s map_location.

        Raises:
            FileNotFoundError: no such file.
            CheckpointError: another kind, format version or (with ``expected``) config; a
                content that does not match its digest; missing entries, wrong shapes or
                dtypes, non-finite or implausible values (the message names the field).
        """
        sizes = ("n_features", "n_components", "k")
        payload, config = load_payload(path, kind=_KIND, version=CHECKPOINT_VERSION, what="Delta-regression",
                                       map_location=map_location, sizes=sizes, expected=expected)
        d, nc, k = (positive_int(payload, key, path) for key in ("n_features", "n_components", "k"))
        spec = {
            "mean": (torch.float32, ("D",)),
            "components": (torch.float16, ("C", "D")),
            "train_coeffs": (torch.float16, ("N", "C+1")),
            "train_delta": (torch.float32, ("N", 2)),
            "fitted": (torch.bool, ()),
        }
        sd = payload["state_dict"]
        dims = check_state(sd, spec, {"D": d}, path)
        if not 1 <= dims["C"] <= nc or dims["C+1"] != dims["C"] + 1 or dims["N"] < 1:
            raise CheckpointError(
                f"checkpoint {path}: components {tuple(sd['components'].shape)} and train_coeffs "
                f"{tuple(sd['train_coeffs'].shape)} do not fit n_components={nc}"
            )
        if dims["C"] != min(nc, dims["N"], d):
            raise CheckpointError(
                f"checkpoint {path}: components has {dims['C']} rows; a fit of n_components={nc} on {dims['N']} "
                f"pairs of {d} features keeps {min(nc, dims['N'], d)}"
            )
        if k >= dims["N"]:
            raise CheckpointError(
                f"checkpoint {path}: k={k} neighbours needs more than k training pairs, it holds {dims['N']}"
            )
        if k > MAX_NEIGHBOURS:  # the bound of regression.k: the median must stay local
            raise CheckpointError(
                f"checkpoint {path}: k={k} neighbours of {dims['N']} training pairs, expected at most {MAX_NEIGHBOURS} "
                "(a local median, as for regression.k)"
            )
        in_range(sd, "mean", lo=FEATURE_RANGE[0], hi=FEATURE_RANGE[1], path=path, why="a mean of quality maps")
        orthonormal_rows(sd, "components", 2e-2, path)
        row_norms_below(sd, "train_coeffs", max_coefficient_norm(d), path)
        in_range(
            sd, "train_delta", lo=0.0, hi=max_delta(config), path=path, why="a Delta in px, at most the image diagonal"
        )
        if bool((sd["train_coeffs"][:, -1] < 0).any()):
            raise CheckpointError(f"checkpoint {path}: train_coeffs holds a negative residual norm (its last column)")
        extra = check_extra(payload, path)
        model = cls(d, config, nc, k)
        for name in ("components", "train_coeffs", "train_delta"):
            setattr(model, name, torch.empty_like(sd[name]))
        model.load_state_dict(sd)
        model.extra = extra
        return model
