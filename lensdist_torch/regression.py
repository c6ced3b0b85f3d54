"""Delta regression without classes: Delta_avg and Delta_max straight from the quality map.

Fitted on all training pairs at once (no per-class split): PCA of the feature vectors
(row-major flattened quality maps, ``torch.linalg.svd`` in float64), the top ``n_components``
coefficients standardised, expanded with their pairwise products (degree 2), and a ridge
regression per metric whose penalty is picked by generalised cross-validation over a grid
(closed form through the SVD of the design matrix). Classes follow from the predicted value
(``distortion_class``).

Confidence: the spread of the training residuals among the ``k`` nearest training pairs in PCA
coefficients (local RMS of (prediction - truth), training pairs being their own neighbours
excluded) is the std of the estimate; ``confidence = s0 / (s0 + std)`` with
``s0 = CANNOT_TELL_FRACTION * Delta_top``, so confidence < 0.5 ("cannot tell") where
neighbouring pairs are predicted worse than s0 -- typically empty maps (little motion).

Everything fitted is a buffer; checkpoints carry a format version and the config, like
:class:`~lensdist_torch.eigenspace.EigenSpaceClassifier`.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch
from torch import nn

from .config import LensdistConfig, config_from_dict, config_to_dict
from .distortion import METRICS, delta_top, distortion_class
from .storage import check_compatible, load_versioned, save_versioned

__all__ = ["DeltaRegressor", "RegressionResult", "CHECKPOINT_VERSION", "CANNOT_TELL_FRACTION"]

CHECKPOINT_VERSION = 1
_KIND = "lensdist-delta-regression"
#: std of the Delta_avg estimate, as a fraction of Delta_top, at which confidence is 0.5.
CANNOT_TELL_FRACTION = 0.125
_LAMBDAS = torch.logspace(-4, 4, 17, dtype=torch.float64)


class RegressionResult(NamedTuple):
    """Each (B,): delta_avg, delta_max (px), class_avg, class_max (0..3), std_avg, std_max
    (neighbour residual spread, px), confidence (0, 1] (from std_avg), confident (bool)."""

    delta_avg: torch.Tensor
    delta_max: torch.Tensor
    class_avg: torch.Tensor
    class_max: torch.Tensor
    std_avg: torch.Tensor
    std_max: torch.Tensor
    confidence: torch.Tensor
    confident: torch.Tensor


class DeltaRegressor(nn.Module):
    """Ridge regression on (degree-2 expanded) PCA coefficients of the quality map.

    Args:
        n_features: feature-vector length ((H/8)(W/8)).
        config: the config it is fitted under (image size, block size, thresholds).
        n_components: PCA components kept. k: neighbours of the confidence.

    Example:
        >>> reg = DeltaRegressor(12, n_components=3, k=4).fit(torch.rand(50, 12), torch.rand(50) * 14, torch.rand(50) * 79)
        >>> reg(torch.rand(2, 12)).delta_avg.shape
        torch.Size([2])
    """

    def __init__(self, n_features: int, config: LensdistConfig | None = None, n_components: int = 16, k: int = 16) -> None:
        super().__init__()
        if n_features < 1 or n_components < 1 or k < 1:
            raise ValueError("n_features, n_components and k must be positive")
        self.n_features, self.n_components, self.k = int(n_features), int(n_components), int(k)
        self.config = config if config is not None else LensdistConfig()
        n_poly = n_components + n_components * (n_components + 1) // 2
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("components", torch.zeros(n_components, n_features))
        self.register_buffer("scale", torch.ones(n_components))
        self.register_buffer("poly_mean", torch.zeros(n_poly))
        self.register_buffer("poly_scale", torch.ones(n_poly))
        self.register_buffer("weights", torch.zeros(2, n_poly + 1))  # per metric, last = intercept
        self.register_buffer("lambdas", torch.zeros(2))
        self.register_buffer("train_coeffs", torch.zeros(0, n_components))
        self.register_buffer("train_residuals", torch.zeros(0, 2))
        self.register_buffer("fitted", torch.tensor(False))
        self.extra: dict = {}

    # ------------------------------------------------------------------ fitting
    def _poly(self, y: torch.Tensor) -> torch.Tensor:
        i, j = torch.triu_indices(y.shape[1], y.shape[1])
        return torch.cat([y, y[:, i] * y[:, j]], 1)

    def _design(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y = (x.double() - self.mean.double()) @ self.components.double().T / self.scale.double()
        p = (self._poly(y) - self.poly_mean.double()) / self.poly_scale.double()
        return y, torch.cat([p, torch.ones(len(p), 1, dtype=p.dtype, device=p.device)], 1)

    def fit(self, features: torch.Tensor, delta_avg: torch.Tensor, delta_max: torch.Tensor) -> "DeltaRegressor":
        """Fit on all training pairs at once. features (N, n_features); deltas (N,) in px."""
        x = torch.as_tensor(features).double()
        t = torch.stack([torch.as_tensor(delta_avg), torch.as_tensor(delta_max)], 1).double()
        if x.dim() != 2 or x.shape[1] != self.n_features or t.shape[0] != x.shape[0]:
            raise ValueError(f"features must be (N, {self.n_features}) with N deltas, got {tuple(x.shape)} and {tuple(t.shape)}")
        if x.shape[0] <= self.k or not (torch.isfinite(x).all() and torch.isfinite(t).all()):
            raise ValueError(f"need more than k={self.k} finite training pairs")
        mu = x.mean(0)
        _, s, vh = torch.linalg.svd(x - mu, full_matrices=False)
        nc = min(self.n_components, vh.shape[0])
        comps = torch.zeros(self.n_components, self.n_features, dtype=torch.float64)
        comps[:nc] = vh[:nc]
        y = (x - mu) @ comps.T
        scale = y.std(0).clamp_min(1e-9)
        self.mean.copy_(mu.float()), self.components.copy_(comps.float()), self.scale.copy_(scale.float())
        p = self._poly(y / scale)
        pm, ps = p.mean(0), p.std(0).clamp_min(1e-9)
        self.poly_mean.copy_(pm.float()), self.poly_scale.copy_(ps.float())
        _, d = self._design(x)
        u, sv, vt = torch.linalg.svd(d, full_matrices=False)
        ut = u.T @ t  # (P, 2)
        n = d.shape[0]
        best = [(float("inf"), None, None)] * 2
        for lam in _LAMBDAS * n:
            f = sv**2 / (sv**2 + lam)
            fit = u @ (f[:, None] * ut)
            gcv = ((t - fit) ** 2).mean(0) / (1 - f.sum() / n) ** 2
            for m in range(2):
                if gcv[m] < best[m][0]:
                    best[m] = (float(gcv[m]), lam, vt.T @ ((sv / (sv**2 + lam))[:, None] * ut[:, m : m + 1]))
        w = torch.stack([b[2][:, 0] for b in best])
        self.weights.copy_(w.float())
        self.lambdas.copy_(torch.tensor([b[1] / n for b in best]))
        # leave-one-out residuals of the ridge (hat-matrix diagonal), for the confidence
        hat = torch.stack([((u**2) * (sv**2 / (sv**2 + b[1]))).sum(1) for b in best], 1)
        loo = (d @ w.T - t) / (1 - hat).clamp_min(1e-3)
        self.train_coeffs = (y / scale).float()
        self.train_residuals = loo.float()
        self.fitted.fill_(True)
        return self

    # ------------------------------------------------------------------ prediction
    def forward(self, features: torch.Tensor) -> RegressionResult:
        if not bool(self.fitted):
            raise RuntimeError("DeltaRegressor is not fitted")
        x = torch.as_tensor(features)
        if x.dim() != 2 or x.shape[1] != self.n_features:
            raise ValueError(f"features must be (B, {self.n_features}), got {tuple(x.shape)}")
        y, d = self._design(x.to(self.mean.device))
        pred = (d @ self.weights.double().T).clamp_min(0)  # (B, 2); Delta is non-negative
        k = min(self.k, len(self.train_coeffs))
        dist = torch.cdist(y.float(), self.train_coeffs)
        nn_idx = dist.topk(k, largest=False).indices
        std = self.train_residuals[nn_idx].pow(2).mean(1).sqrt().double()  # (B, 2)
        cfg = self.config
        h, w = cfg.image.height, cfg.image.width
        tops = [delta_top(m, h, w, cfg.distortion) for m in METRICS]
        classes = [distortion_class(pred[:, i].clamp_min(1e-9), tops[i]) for i in range(2)]
        s0 = CANNOT_TELL_FRACTION * tops[0]
        conf = s0 / (s0 + std[:, 0])
        return RegressionResult(pred[:, 0], pred[:, 1], classes[0], classes[1], std[:, 0], std[:, 1], conf, conf >= 0.5)

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """Write atomically: kind, format version, config, sizes and the buffers."""
        save_versioned(path, _KIND, CHECKPOINT_VERSION, {
            "n_features": self.n_features,
            "n_components": self.n_components,
            "k": self.k,
            "config": config_to_dict(self.config),
            "state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()},
            "extra": extra or {},
        })

    @classmethod
    def load(cls, path: str | Path, expected: LensdistConfig | None = None, map_location="cpu") -> "DeltaRegressor":
        """Load a checkpoint (``torch.load(weights_only=True)``); CheckpointError if incompatible."""
        payload = load_versioned(path, _KIND, CHECKPOINT_VERSION, "Delta-regression", map_location)
        config = config_from_dict(payload["config"])
        if expected is not None:
            check_compatible(config, expected, path)
        sd = payload["state_dict"]
        model = cls(int(payload["n_features"]), config, int(payload["n_components"]), int(payload["k"]))
        for name in ("train_coeffs", "train_residuals"):
            setattr(model, name, torch.empty_like(sd[name]))
        model.load_state_dict(sd)
        model.extra = payload.get("extra", {})
        return model
