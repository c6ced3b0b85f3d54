"""Stateful registration-quality metrics for validation loops (torchmetrics' pattern).

``update`` adds a batch of registered pairs, ``compute`` reports, ``reset`` starts again:

* the mean quality index over all pairs seen (weighted by pairs, not by batches), the index
  of a pair being 1 - the mean of its hard registration map (docs/method.md, section 4);
* the mean registration-error map, the lens-distortion signature of a data set (a homography
  fitted to distorted images leaves errors that grow with the distance from the centre);
* the number of pairs.

The state is three sums (float64 for the sums, int64 for the count) kept as buffers, so
``.to(device)`` moves them and ``state_dict`` saves them. :class:`RegistrationQualityMetric`
needs nothing beyond PyTorch; where torchmetrics is installed, :class:`RegistrationQualityTorchMetric`
is the same metric as a ``torchmetrics.Metric`` (states summed across processes).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric._inputs import check_data_range, get_config
from lensdist_torch.metric.quality import quality_map

try:  # optional: only for RegistrationQualityTorchMetric
    import torchmetrics as _torchmetrics
except ImportError:  # pragma: no cover - depends on the environment
    _torchmetrics = None

__all__ = ["QualityMetricResult", "RegistrationQualityMetric"]


class QualityMetricResult(NamedTuple):
    """What the stateful metrics' ``compute`` returns.

    Attributes:
        quality_index: () float64, the mean over pairs of 1 - mean(registration map).
        registration_map: (1, h, w) float64, the mean hard registration map over pairs.
        num_pairs: () int64, the number of pairs.

    Example:
        >>> m = RegistrationQualityMetric()
        >>> m.update(torch.rand(2, 1, 16, 16), torch.rand(2, 1, 16, 16))
        >>> res = m.compute()
        >>> res.registration_map.shape, int(res.num_pairs)
        (torch.Size([1, 2, 2]), 2)
    """

    quality_index: torch.Tensor
    registration_map: torch.Tensor
    num_pairs: torch.Tensor


def _batch_state(img1, img2, valid, config, data_range, validate, pad):
    """(sum of the quality indices, sum of the maps (1, h, w), number of pairs) of a batch."""
    m = quality_map(img1, img2, valid, config, data_range, validate, pad)  # (B, 1, h, w)
    q = 1.0 - m.mean(dim=(1, 2, 3))  # as registration_quality's quality_index
    return q.double().sum(), m.double().sum(dim=0), m.shape[0]


def _add_map(current: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
    """Sum of ``current`` and ``batch``, ``current`` being the 0-dim initial zero or a map of the same shape."""
    if current.dim() and current.shape != batch.shape:
        raise ValueError(
            f"all pairs must give maps of one shape: the metric holds {tuple(current.shape)}, "
            f"this batch gives {tuple(batch.shape)} (call reset() between image sizes)"
        )
    return current + batch


def _result(quality_sum, map_sum, num_pairs) -> QualityMetricResult:
    n = int(num_pairs)
    if n == 0:
        raise RuntimeError("compute() needs at least one update() with a pair (or call it after reset + update)")
    return QualityMetricResult(quality_sum / n, map_sum / n, num_pairs.clone())


def _initial_map(map_shape: tuple[int, int] | None) -> torch.Tensor:
    """0-dim zero (shape taken from the first batch) or zeros (1, h, w)."""
    if map_shape is None:
        return torch.zeros((), dtype=torch.float64)
    if len(map_shape) != 2 or not all(isinstance(s, int) and s > 0 for s in map_shape):
        raise ValueError(f"map_shape must be (h, w) in blocks, two positive ints, got {map_shape!r}")
    return torch.zeros((1, *map_shape), dtype=torch.float64)


class RegistrationQualityMetric(nn.Module):
    """Accumulates the quality index and the registration map over a validation set.

    Args:
        config: thresholds and block size; the defaults when None.
        data_range: the value of white in float inputs.
        validate: check values in each ``update`` (one host sync); skipped while compiling.
        pad: pad images to whole blocks (else H, W must be multiples of the block size).
        map_shape: (h, w) of the maps in blocks, e.g. (40, 53) for 320 x 424 images; None
            takes it from the first batch.

    Shape:
        - img1, img2: (B, C, H, W); valid: (B, 1, H, W) or None.
        - compute(): QualityMetricResult with a () index, a (1, ceil(H/b), ceil(W/b)) map and
          the () pair count.

    Example:
        >>> metric = RegistrationQualityMetric()
        >>> x = torch.rand(3, 1, 32, 32)
        >>> metric.update(x, x)
        >>> metric.update(x[:1], torch.roll(x[:1], 1, dims=-1))
        >>> res = metric.compute()
        >>> int(res.num_pairs), bool(res.quality_index < 1)
        (4, True)
        >>> metric.reset()
        >>> int(metric.num_pairs)
        0
    """

    quality_sum: torch.Tensor
    map_sum: torch.Tensor
    num_pairs: torch.Tensor

    def __init__(
        self,
        config: QualityConfig | None = None,
        data_range: float = 1.0,
        validate: bool = True,
        pad: bool = True,
        map_shape: tuple[int, int] | None = None,
    ) -> None:
        super().__init__()
        check_data_range(data_range)
        self.config = get_config(config)
        self.data_range = data_range
        self.validate = validate
        self.pad = pad
        self.map_shape = map_shape
        self.register_buffer("quality_sum", torch.zeros((), dtype=torch.float64))
        self.register_buffer("map_sum", _initial_map(map_shape))
        self.register_buffer("num_pairs", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def update(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> None:
        """Add a batch of registered pairs (no host sync with ``validate=False``).

        Args:
            img1: (B, C, H, W) registered images, float in [0, data_range] or uint8.
            img2: (B, C, H, W) the other images.
            valid: (B, 1, H, W) validity masks or None.
        """
        self._add(img1, img2, valid)

    def _add(self, img1, img2, valid):
        q, m, n = _batch_state(img1, img2, valid, self.config, self.data_range, self.validate, self.pad)
        self.map_sum = _add_map(self.map_sum, m.to(self.map_sum.device))
        self.quality_sum += q.to(self.quality_sum.device)
        self.num_pairs += n
        return q, m, n

    def compute(self) -> QualityMetricResult:
        """The means over every pair since the last reset.

        Returns:
            QualityMetricResult (index, mean map, pair count).

        Raises:
            RuntimeError: no pair was added.
        """
        return _result(self.quality_sum, self.map_sum, self.num_pairs)

    def reset(self) -> None:
        """Forget every pair (the buffers stay on their device)."""
        device = self.num_pairs.device
        self.quality_sum = torch.zeros((), dtype=torch.float64, device=device)
        self.map_sum = _initial_map(self.map_shape).to(device)
        self.num_pairs = torch.zeros((), dtype=torch.long, device=device)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> QualityMetricResult:
        """Add the batch and return its own result (as ``torchmetrics.Metric.forward``)."""
        q, m, n = self._add(img1, img2, valid)
        return QualityMetricResult(q / n, m / n, torch.tensor(n, device=m.device))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "map_sum"
        if key in state_dict and state_dict[key].shape != self.map_sum.shape:  # a lazily shaped map
            self.map_sum = torch.zeros_like(state_dict[key], device=self.map_sum.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        """The block size and data range, shown in the module's repr."""
        return f"block_size={self.config.block_size}, data_range={self.data_range}"


if _torchmetrics is not None:
    __all__.append("RegistrationQualityTorchMetric")

    class RegistrationQualityTorchMetric(_torchmetrics.Metric):
        """:class:`RegistrationQualityMetric` as a ``torchmetrics.Metric``.

        Defined only when torchmetrics is installed; the states are summed across processes.

        Args:
            config: thresholds and block size; the defaults when None.
            data_range: the value of white in float inputs.
            validate: check values in each ``update`` (one host sync).
            pad: pad images to whole blocks.
            map_shape: (h, w) of the maps in blocks; pass it for distributed runs in which a
                process may see no batch (the lazily shaped map cannot be summed with an
                empty one).
            **kwargs: passed to ``torchmetrics.Metric``.

        Example:
            >>> metric = RegistrationQualityTorchMetric()
            >>> x = torch.rand(2, 1, 16, 16)
            >>> metric.update(x, x)
            >>> float(metric.compute().quality_index)
            1.0
        """

        is_differentiable = False
        higher_is_better = True
        full_state_update = False

        def __init__(
            self,
            config: QualityConfig | None = None,
            data_range: float = 1.0,
            validate: bool = True,
            pad: bool = True,
            map_shape: tuple[int, int] | None = None,
            **kwargs,
        ) -> None:
            super().__init__(**kwargs)
            check_data_range(data_range)
            self.quality_config = get_config(config)
            self.data_range = data_range
            self.validate = validate
            self.pad = pad
            self.add_state("quality_sum", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
            self.add_state("map_sum", default=_initial_map(map_shape), dist_reduce_fx="sum")
            self.add_state("num_pairs", default=torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")

        def update(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> None:
            """Add a batch of registered pairs: img1, img2 (B, C, H, W), valid (B, 1, H, W)."""
            q, m, n = _batch_state(
                img1, img2, valid, self.quality_config, self.data_range, self.validate, self.pad
            )
            self.map_sum = _add_map(self.map_sum, m)
            self.quality_sum += q
            self.num_pairs += n

        def compute(self) -> QualityMetricResult:
            """The means over every pair (of every process) since the last reset."""
            return _result(self.quality_sum, self.map_sum, self.num_pairs)
