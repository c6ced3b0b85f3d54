"""Stateful registration-quality metrics for validation loops (torchmetrics' pattern).

``update`` adds a batch of registered pairs, ``compute`` returns the mean quality index as a
0-dim tensor (what ``MetricCollection``, ``self.log`` and ``log_dict`` expect),
``compute_details`` returns everything, ``reset`` starts again:

* the mean quality index over all pairs seen (weighted by pairs, not by batches), the index
  of a pair being 1 - the mean of its hard registration map (docs/method.md, section 4);
* the mean registration-error map, the lens-distortion signature of a data set (a homography
  fitted to distorted images leaves errors that grow with the distance from the centre);
* the number of pairs, and the number of pairs skipped because they had nothing to measure (no
  pixel of the mask valid after its 3 x 3 erosion, or every valid pixel in the risk map: an
  index there would read 1.0, perfect, although nothing was compared). Such pairs are never averaged, with or without ``validate``.

The state is four sums (float64 for the sums, int64 for the counts) kept as buffers, so
``.to(device)`` moves them and ``state_dict`` saves them. The sums stay float64 whatever
``.half()``, ``.float()``, ``.bfloat16()`` or ``.to(dtype)`` ask (float16 sums stop growing after
a few thousand pairs); device moves apply. ``load_state_dict`` checks what it loads: counts
non-negative integers, sums finite and consistent with the count, the map of the metric's shape. :class:`RegistrationQualityMetric`
needs nothing beyond PyTorch; where torchmetrics is installed, :class:`RegistrationQualityTorchMetric`
is the same metric as a ``torchmetrics.Metric`` (states summed across processes).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric._inputs import check_data_range, get_config, measured
from lensdist_torch.metric._state import STATE, check_state, loaded_state
from lensdist_torch.metric.quality import measured_map

try:  # optional: only for RegistrationQualityTorchMetric
    import torchmetrics as _torchmetrics
except ImportError:  # pragma: no cover - depends on the environment
    _torchmetrics = None

__all__ = ["QualityMetricResult", "RegistrationQualityMetric"]


class QualityMetricResult(NamedTuple):
    """What the stateful metrics' ``compute_details`` returns (``compute`` is its quality_index).

    Attributes:
        quality_index: () float64, the mean over pairs of 1 - mean(registration map).
        registration_map: (1, h, w) float64, the mean hard registration map over pairs.
        num_pairs: () int64, the number of pairs averaged.
        num_skipped: () int64, the pairs left out because they had nothing to measure (no
            pixel of the mask valid after its 3 x 3 erosion, or every valid pixel at risk).

    Example:
        >>> m = RegistrationQualityMetric()
        >>> m.update(torch.rand(2, 1, 16, 16), torch.rand(2, 1, 16, 16))
        >>> res = m.compute_details()
        >>> res.registration_map.shape, int(res.num_pairs)
        (torch.Size([1, 2, 2]), 2)
    """

    quality_index: torch.Tensor
    registration_map: torch.Tensor
    num_pairs: torch.Tensor
    num_skipped: torch.Tensor


def _batch_state(img1, img2, valid, config, data_range, validate, pad):
    """(sum of the quality indices, sum of the maps (1, h, w), pairs counted, pairs skipped).

    Pairs with nothing to measure are left out of the sums and counted as skipped. The counts
    are ints when every pair counts, else int64 tensors on the maps' device: no host sync.
    """
    m, flags = measured_map(img1, img2, valid, config, data_range, validate, pad)  # (B, 1, h, w)
    m = m.double()
    q = 1.0 - m.mean(dim=(1, 2, 3))  # as registration_quality's quality_index
    keep = measured(flags).double()
    n = keep.sum().long()
    return (q * keep).sum(), (m * keep[:, None, None, None]).sum(dim=0), n, m.shape[0] - n


def _to_device(count: int | torch.Tensor, device: torch.device) -> int | torch.Tensor:
    return count.to(device) if isinstance(count, torch.Tensor) else count


def _add_map(current: torch.Tensor, batch: torch.Tensor) -> torch.Tensor:
    """Sum of ``current`` and ``batch``, ``current`` being the 0-dim initial zero or a map of the same shape."""
    if current.dim() and current.shape != batch.shape:
        raise ValueError(
            f"all pairs must give maps of one shape: the metric holds {tuple(current.shape)}, "
            f"this batch gives {tuple(batch.shape)} (call reset() between image sizes)"
        )
    return current + batch


def _result(quality_sum, map_sum, num_pairs, num_skipped) -> QualityMetricResult:
    n = int(num_pairs)
    if n == 0:
        skipped = int(num_skipped)
        if skipped:
            raise RuntimeError(
                f"compute() has no pair to average: the {skipped} pair(s) added had nothing to measure "
                "(no pixel of the mask valid after its 3 x 3 erosion, or flat images: every valid pixel in the risk map)"
            )
        raise RuntimeError("compute() needs at least one update() with a pair (or call it after reset + update)")
    return QualityMetricResult(quality_sum / n, map_sum / n, num_pairs.clone(), num_skipped.clone())


def _keeping_dtypes(fn):
    """``fn`` for ``nn.Module._apply`` that moves the accumulators but never changes their dtype."""

    def apply(t: torch.Tensor) -> torch.Tensor:
        out = fn(t)
        return out if out.dtype == t.dtype else t.to(device=out.device)

    return apply


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
        - compute(): () float64, the mean quality index (1 = no registration error).
        - compute_details(): QualityMetricResult with that index, the (1, ceil(H/b), ceil(W/b))
          mean map and the () counts of pairs averaged and skipped.

    A pair with nothing to measure (no pixel of its mask valid after the 3 x 3 erosion, or
    every valid pixel in the risk map) is
    never averaged, with or without ``validate``: ``update`` leaves it out of the sums and
    counts it in ``num_skipped`` (``compute_details`` reports it). The accumulators stay float64/int64
    under ``.half()``, ``.float()``, ``.bfloat16()`` and ``.to(dtype)`` (device moves apply), and
    ``load_state_dict`` refuses a state no sequence of updates can give (a negative count, a
    NaN sum, sums that do not match the count) with a one-line ValueError naming the field.

    Example:
        >>> metric = RegistrationQualityMetric()
        >>> x = torch.rand(3, 1, 32, 32)
        >>> metric.update(x, x)
        >>> metric.update(x[:1], torch.roll(x[:1], 1, dims=-1))
        >>> metric.compute().shape, bool(metric.compute() < 1)
        (torch.Size([]), True)
        >>> res = metric.compute_details()
        >>> int(res.num_pairs), res.registration_map.shape
        (4, torch.Size([1, 4, 4]))
        >>> metric.reset()
        >>> int(metric.num_pairs)
        0
    """

    quality_sum: torch.Tensor
    map_sum: torch.Tensor
    num_pairs: torch.Tensor
    num_skipped: torch.Tensor

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
        self.register_buffer("num_skipped", torch.zeros((), dtype=torch.long))

    @torch.no_grad()
    def update(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> None:
        """Add a batch of registered pairs (no host sync with ``validate=False``).

        Pairs with nothing to measure are counted in ``num_skipped``, not averaged.

        Args:
            img1: (B, C, H, W) registered images, float in [0, data_range] or uint8.
            img2: (B, C, H, W) the other images, on img1's device.
            valid: (B, 1, H, W) validity masks on img1's device, or None.
        """
        self._add(img1, img2, valid)

    def _add(self, img1, img2, valid):
        q, m, n, skipped = _batch_state(img1, img2, valid, self.config, self.data_range, self.validate, self.pad)
        device = self.quality_sum.device
        self.map_sum = _add_map(self.map_sum, m.to(device))
        self.quality_sum += q.to(device)
        self.num_pairs += _to_device(n, device)
        self.num_skipped += _to_device(skipped, device)
        return q, m, n, skipped

    def compute(self) -> torch.Tensor:
        """The mean quality index over every pair since the last reset: a () float64 tensor.

        Raises:
            RuntimeError: no pair was added.
        """
        return self.compute_details().quality_index

    def compute_details(self) -> QualityMetricResult:
        """The mean index, the mean registration map and the counts of pairs averaged and skipped.

        Raises:
            RuntimeError: no pair was added.
        """
        return _result(self.quality_sum, self.map_sum, self.num_pairs, self.num_skipped)

    def reset(self) -> None:
        """Forget every pair (the buffers stay on their device)."""
        device = self.num_pairs.device
        self.quality_sum = torch.zeros((), dtype=torch.float64, device=device)
        self.map_sum = _initial_map(self.map_shape).to(device)
        self.num_pairs = torch.zeros((), dtype=torch.long, device=device)
        self.num_skipped = torch.zeros((), dtype=torch.long, device=device)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Add the batch and return its own mean index (as ``torchmetrics.Metric.forward``).

        NaN when none of the batch's pairs has anything to measure.
        """
        q, _, n, _ = self._add(img1, img2, valid)
        return q / torch.as_tensor(n, device=q.device)

    def _apply(self, fn, *args, **kwargs):
        """Device moves apply to the accumulators; dtype changes do not (they stay float64/int64)."""
        return super()._apply(_keeping_dtypes(fn), *args, **kwargs)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        check_state(loaded_state(self, state_dict, prefix), self.map_shape)
        key = prefix + "map_sum"
        if key in state_dict and state_dict[key].shape != self.map_sum.shape:  # a lazily shaped map
            self.map_sum = torch.zeros(state_dict[key].shape, dtype=torch.float64, device=self.map_sum.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        """The block size and data range, shown in the module's repr."""
        return f"block_size={self.config.block_size}, data_range={self.data_range}"


if _torchmetrics is not None:
    __all__.append("RegistrationQualityTorchMetric")

    class RegistrationQualityTorchMetric(_torchmetrics.Metric):
        """:class:`RegistrationQualityMetric` as a ``torchmetrics.Metric``.

        Defined only when torchmetrics is installed; the states are summed across processes.
        As :class:`RegistrationQualityMetric`: pairs with nothing to measure are skipped and
        counted in ``num_skipped``, the states stay float64/int64 whatever dtype the module is
        cast to (``.to(dtype)``, ``.bfloat16()``; torchmetrics already ignores ``.half()``), and
        persistent states are checked when loaded.

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
            >>> float(metric.compute())
            1.0
            >>> int(metric.compute_details().num_pairs)
            2
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
            self.add_state("num_skipped", default=torch.zeros((), dtype=torch.long), dist_reduce_fx="sum")
            self.map_shape = map_shape

        def update(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> None:
            """Add a batch of registered pairs: img1, img2 (B, C, H, W), valid (B, 1, H, W).

            Pairs with nothing to measure are counted in ``num_skipped``, not averaged.
            """
            q, m, n, skipped = _batch_state(
                img1, img2, valid, self.quality_config, self.data_range, self.validate, self.pad
            )
            self.map_sum = _add_map(self.map_sum, m)
            self.quality_sum += q
            self.num_pairs += n
            self.num_skipped += skipped

        def compute(self) -> torch.Tensor:
            """The mean quality index over every pair (of every process) since the last reset."""
            return _result(self.quality_sum, self.map_sum, self.num_pairs, self.num_skipped).quality_index

        def compute_details(self) -> QualityMetricResult:
            """Index, mean map and counts over every pair (of every process), synced as ``compute``."""
            with self.sync_context(
                dist_sync_fn=self.dist_sync_fn, should_sync=self._to_sync, should_unsync=self._should_unsync
            ):
                return _result(self.quality_sum, self.map_sum, self.num_pairs, self.num_skipped)

        def _apply(self, fn, *args, **kwargs):
            """Device moves apply to the states (and their defaults); dtype changes do not."""
            return super()._apply(_keeping_dtypes(fn), *args, **kwargs)

        def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
            if any(prefix + k in state_dict for k in STATE):  # states are saved only when persistent
                check_state(loaded_state(self, state_dict, prefix), self.map_shape)
            super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
