"""The per-class eigen-space classifier (paper 4.2, docs/method.md section 8).

It sees feature vectors (row-major flattened quality maps), never images.

Per class c: the mean mu_c and the top n eigenvectors U_c (rows) of the centred training
vectors, from ``torch.linalg.svd`` on the CPU in float64. A vector x is assigned to the class
whose eigen-space it lies closest to, eps_c(x) = ||(x - mu_c) - U_c^T U_c (x - mu_c)||, and to
the reject class R where even the smallest distance exceeds tau_R, the ``REJECT_QUANTILE`` (0.95)
quantile of the training pairs' own smallest distances. Delta is interpolated from the
``N_NEIGHBOURS`` (4) nearest training pairs of the winning class, by distance between
eigen-space coefficients y = U_c (x - mu_c), with weights 1 / (d + 1e-6). A pair classed R
still gets the Delta of its nearest class (its best guess).

Everything fitted is a buffer, so ``state_dict`` carries it and ``.to("cuda")`` moves it.

References:
    B. Möller, S. Posch, "Automatic Analysis of Lens Distortions in Image Registration", Institute
    of Computer Science, Martin Luther University Halle-Wittenberg (venue and year not in the text
    the project worked from; docs/method.md): the per-class eigen-spaces, section 4.2.
"""

from __future__ import annotations

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
from lensdist_torch.config import ClassifierConfig, LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.storage import CheckpointError
from lensdist_torch.geometry.distortion import N_CLASSES, REJECT

__all__ = ["EigenSpaceClassifier", "ClassifierResult", "CheckpointError", "CHECKPOINT_VERSION"]

#: 2: a content digest (core.storage.content_digest); version 1 files are refused (refit them).
CHECKPOINT_VERSION = 2
_KIND = "lensdist-eigenspace"
#: The reject threshold tau_R: this quantile of the training pairs' own smallest class distances.
REJECT_QUANTILE = 0.95
#: Training pairs of the winning class whose Delta is interpolated (nearest in eigen-space coefficients).
N_NEIGHBOURS = 4


class ClassifierResult(NamedTuple):
    """The classifier's answer for a batch.

    label: (B,) class index 0..3, or 4 for R. delta: (B,) interpolated Delta (px).
    distances: (B, C) distance to every class space. nearest: (B,) argmin class.
    neighbours: (B, k) training-pair indices used. neighbour_distances: (B, k).

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> x, cls = torch.rand(40, 12, generator=g), torch.arange(40) % 4
        >>> clf = EigenSpaceClassifier(12, LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=2)))
        >>> res = clf.fit(x, cls, torch.rand(40, generator=g))(x[:3])
        >>> tuple(res.distances.shape), bool((res.nearest == res.distances.argmin(1)).all())
        ((3, 4), True)
        >>> res.neighbours[:, 0].tolist()  # each training vector is its own nearest neighbour
        [0, 1, 2]
    """

    label: torch.Tensor
    delta: torch.Tensor
    distances: torch.Tensor
    nearest: torch.Tensor
    neighbours: torch.Tensor
    neighbour_distances: torch.Tensor


class EigenSpaceClassifier(nn.Module):
    """Per-class PCA eigen-spaces with rejection and nearest-neighbour Delta regression.

    Args:
        n_features: length of the feature vectors ((H/8) * (W/8), 2120 at the default size).
        config: the full config it is fitted under (image size, block size, metric, n, ...).

    Example:
        >>> clf = EigenSpaceClassifier(n_features=12, config=LensdistConfig(
        ...     classifier=ClassifierConfig(n_eigenvectors=2)))
        >>> x = torch.rand(40, 12); cls = torch.arange(40) % 4; d = torch.rand(40)
        >>> _ = clf.fit(x, cls, d)
        >>> clf(x[:3]).label.shape
        torch.Size([3])
    """

    def __init__(self, n_features: int, config: LensdistConfig | None = None) -> None:
        super().__init__()
        self.config = or_defaults(config, LensdistConfig)
        c = self.config.classifier
        k = N_CLASSES
        n = c.n_eigenvectors
        if not (isinstance(n_features, int) and n_features > n):
            raise ValueError(f"n_features must be an int larger than n_eigenvectors={n}, got {n_features!r}")
        self.n_features = n_features
        self.register_buffer("means", torch.zeros(k, n_features))
        self.register_buffer("bases", torch.zeros(k, n, n_features))
        self.register_buffer("explained", torch.zeros(k))
        self.register_buffer("train_coeffs", torch.zeros(0, n))
        self.register_buffer("train_class", torch.zeros(0, dtype=torch.long))
        self.register_buffer("train_delta", torch.zeros(0))
        self.register_buffer("reject_threshold", torch.tensor(float("inf")))
        self.register_buffer("fitted", torch.tensor(False))
        self.extra: dict = {}  # saved with the checkpoint: the scenes fitted on, their texture

    @property
    def settings(self) -> ClassifierConfig:
        """The classifier section of the config it was fitted with."""
        return self.config.classifier

    # ------------------------------------------------------------------ fitting
    def fit(self, features: torch.Tensor, classes: torch.Tensor, deltas: torch.Tensor) -> "EigenSpaceClassifier":
        """Fit on training vectors (N, D), class indices (N,) in 0..C-1 and Delta values (N,)."""
        features, classes, deltas = self._check_fit(features, classes, deltas)
        k, n = self.means.shape[0], self.settings.n_eigenvectors
        x = features.detach().cpu().double()
        means = torch.zeros(k, self.n_features, dtype=torch.float64)
        bases = torch.zeros(k, n, self.n_features, dtype=torch.float64)
        explained = torch.zeros(k, dtype=torch.float64)
        coeffs = torch.zeros(x.shape[0], n, dtype=torch.float64)
        for c in range(k):
            sel = classes == c
            xc = x[sel]
            if xc.shape[0] <= n:
                raise ValueError(
                    f"class {c + 1} has {xc.shape[0]} training vectors; fitting {n} eigenvectors needs more than {n}"
                )
            mu = xc.mean(0)
            _, s, vh = torch.linalg.svd(xc - mu, full_matrices=False)
            means[c], bases[c] = mu, vh[:n]
            explained[c] = (s[:n] ** 2).sum() / (s**2).sum().clamp_min(1e-300)
            coeffs[sel] = (xc - mu) @ vh[:n].T
        self.means.copy_(means.float())
        self.bases.copy_(bases.float())
        self.explained.copy_(explained.float())
        self.train_coeffs = coeffs.float()
        self.train_class = classes.cpu().long()
        self.train_delta = deltas.detach().cpu().float()
        self.fitted.fill_(True)
        own = self.distances(features).min(1).values
        self.reject_threshold.fill_(float(torch.quantile(own.double(), REJECT_QUANTILE)))
        return self

    def _check_fit(self, features, classes, deltas):
        if not isinstance(features, torch.Tensor) or features.dim() != 2 or features.shape[1] != self.n_features:
            raise ValueError(
                f"features must be (N, {self.n_features}), got {getattr(features, 'shape', type(features))}"
            )
        n = features.shape[0]
        if not isinstance(classes, torch.Tensor) or classes.shape != (n,) or classes.is_floating_point():
            raise ValueError(f"classes must be an integer tensor of shape ({n},)")
        k = self.means.shape[0]
        if bool(((classes < 0) | (classes >= k)).any()):
            raise ValueError(f"classes must lie in 0..{k - 1} (class R is never fitted)")
        if not isinstance(deltas, torch.Tensor) or deltas.shape != (n,):
            raise ValueError(f"deltas must be a tensor of shape ({n},)")
        if not bool(torch.isfinite(features).all()) or not bool(torch.isfinite(deltas).all()):
            raise ValueError("features and deltas must be finite")
        check_features_domain(features)
        check_deltas(deltas, self.config)
        return features, classes, deltas

    # ------------------------------------------------------------------ inference
    def _check_features(self, features: torch.Tensor) -> torch.Tensor:
        if not bool(self.fitted):
            raise RuntimeError("EigenSpaceClassifier is not fitted: call fit() or load a checkpoint")
        if not isinstance(features, torch.Tensor) or features.dim() != 2 or features.shape[1] != self.n_features:
            raise ValueError(
                f"features must be (B, {self.n_features}), got {getattr(features, 'shape', type(features))}"
            )
        return features.to(self.means.device, self.means.dtype)

    def _project(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Coefficients y = U_c (x - mu_c), (B, C, n), and distances eps_c(x), (B, C)."""
        x = self._check_features(features)
        xc = x[:, None, :] - self.means[None]  # (B, C, D)
        y = torch.einsum("bcd,cnd->bcn", xc, self.bases)
        return y, (xc - torch.einsum("bcn,cnd->bcd", y, self.bases)).norm(dim=-1)

    def coefficients(self, features: torch.Tensor) -> torch.Tensor:
        """Eigen-space coefficients of every vector in every class space: (B, C, n)."""
        return self._project(features)[0]

    def distances(self, features: torch.Tensor) -> torch.Tensor:
        """eps_c(x), the distance of each vector from each class space: (B, C)."""
        return self._project(features)[1]

    def forward(self, features: torch.Tensor) -> ClassifierResult:
        """Classify (B, D) feature vectors; see :class:`ClassifierResult`."""
        y, dist = self._project(features)
        nearest = dist.argmin(1)
        label = torch.where(dist.min(1).values > self.reject_threshold, torch.full_like(nearest, REJECT), nearest)
        kn = N_NEIGHBOURS
        b, dev = y.shape[0], y.device
        neigh = torch.zeros(b, kn, dtype=torch.long, device=dev)
        ndist = torch.zeros(b, kn, device=dev)
        delta = torch.zeros(b, device=dev)
        for c in range(self.means.shape[0]):
            rows = (nearest == c).nonzero().flatten()
            if rows.numel() == 0:
                continue
            members = (self.train_class == c).nonzero().flatten().to(dev)
            d = torch.cdist(y[rows, c], self.train_coeffs[members])
            k = min(kn, members.numel())
            dk, ik = d.topk(k, dim=1, largest=False)
            w = 1.0 / (dk + 1e-6)
            w = w / w.sum(1, keepdim=True)
            delta[rows] = (w * self.train_delta[members][ik]).sum(1)
            neigh[rows, :k] = members[ik]
            ndist[rows, :k] = dk
        return ClassifierResult(
            label=label, delta=delta, distances=dist, nearest=nearest, neighbours=neigh, neighbour_distances=ndist)

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: str | Path, extra: dict | None = None) -> None:
        """Write atomically: format version, the config it was fitted with, and the buffers.

        ``extra`` (a dict of plain values: names, numbers, lists) is stored beside them; by
        default ``self.extra`` (e.g. the scenes it was fitted on and their texture statistics).
        An existing file at ``path`` is replaced only if it is a checkpoint of this kind
        (FileExistsError otherwise: never an image, a data shard or another file).
        """
        save_model(self, path, kind=_KIND, version=CHECKPOINT_VERSION, sizes={"n_features": self.n_features},
                   extra=self.extra if extra is None else extra)

    @classmethod
    def load(
        cls, path: str | Path, expected: LensdistConfig | None = None, map_location="cpu"
    ) -> "EigenSpaceClassifier":
        """Load a checkpoint (``torch.load(weights_only=True)``).

        The content digest is verified, then the payload is validated before anything is
        allocated: the sizes against the stored tensors, every buffer's shape and dtype, finite
        values, class indices in range, values a fit can produce (``classify/_checkpoint.py``),
        the ``extra`` entries read by the analysis.

        Args:
            path: the checkpoint file.
            expected: if given, the image size, block size and quality thresholds must match it.
            map_location: ``torch.load``'s map_location.

        Raises:
            FileNotFoundError: no such file.
            CheckpointError: another kind or format version, image size, block size or
                thresholds; a content that does not match its digest; missing entries, wrong
                shapes or dtypes, non-finite or implausible values (the message names the field).
        """
        payload, config = load_payload(path, kind=_KIND, version=CHECKPOINT_VERSION, what="eigen-space",
                                       map_location=map_location, sizes=("n_features",), expected=expected)
        d = positive_int(payload, "n_features", path)
        k, n = N_CLASSES, config.classifier.n_eigenvectors
        if d <= n:
            raise CheckpointError(f"checkpoint {path}: n_features={d} must exceed n_eigenvectors={n}")
        f32 = torch.float32
        spec = {
            "means": (f32, ("k", "D")),
            "bases": (f32, ("k", "n", "D")),
            "explained": (f32, ("k",)),
            "train_coeffs": (f32, ("N", "n")),
            "train_class": (torch.int64, ("N",)),
            "train_delta": (f32, ("N",)),
            "reject_threshold": (f32, ()),
            "fitted": (torch.bool, ()),
        }
        sd = payload["state_dict"]
        check_state(sd, spec, {"k": k, "n": n, "D": d}, path)
        counts = torch.bincount(sd["train_class"].clamp(0, k), minlength=k + 1)
        if bool((sd["train_class"] < 0).any()) or int(counts[k]) or bool((counts[:k] <= n).any()):
            raise CheckpointError(
                f"checkpoint {path}: train_class must hold every class 0..{k - 1} more than n_eigenvectors={n} "
                "times (what a fit needs) and nothing else"
            )
        _check_plausible(sd, config, d, path)
        extra = check_extra(payload, path)
        model = cls(d, config)
        # fitted sizes vary with the training set: resize the buffers before loading
        for name in ("train_coeffs", "train_class", "train_delta"):
            setattr(model, name, torch.empty_like(sd[name]))
        model.load_state_dict(sd)
        model.extra = extra
        return model


def _check_plausible(sd: dict, config: LensdistConfig, d: int, path) -> None:
    """The fitted values are ones a fit on quality maps can produce (bounds: classify/_checkpoint.py)."""
    in_range(sd, "means", lo=FEATURE_RANGE[0], hi=FEATURE_RANGE[1], path=path, why="a mean of quality maps")
    orthonormal_rows(sd, "bases", 1e-3, path)
    in_range(sd, "explained", lo=0.0, hi=1.0 + 1e-5, path=path, why="a share of the variance")
    top = max_coefficient_norm(d)
    row_norms_below(sd, "train_coeffs", top, path)
    in_range(sd, "reject_threshold", lo=0.0, hi=top, path=path, why="a distance between quality maps")
    in_range(
        sd, "train_delta", lo=0.0, hi=max_delta(config), path=path, why="a Delta in px, at most the image diagonal"
    )
