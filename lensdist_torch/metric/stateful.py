"""The stateful registration-quality metric for validation loops (torchmetrics' pattern).

``update`` adds a batch of registered pairs, ``compute`` returns the mean quality index as a
0-dim tensor (what ``MetricCollection``, ``self.log`` and ``log_dict`` expect),
``compute_details`` returns everything, ``reset`` starts again:

* the mean quality index over all pairs seen (weighted by pairs, not by batches), the index
  of a pair being 1 - the mean of its hard registration map (docs/method.md, section 4);
* the mean registration-error map, the lens-distortion signature of a data set (a homography
  fitted to distorted images leaves errors that grow with the distance from the centre);
* the number of pairs, and the number of pairs skipped because they had nothing to measure (no
  pixel of the mask valid after its 3 x 3 erosion, or every valid pixel in the risk map: an
  index there would read 1.0, perfect, although nothing was compared). Such pairs are never
  averaged, with or without ``validate``.

The state is four sums (float64 for the sums, int64 for the counts). :class:`RegistrationQualityMetric`
is one class: a ``torchmetrics.Metric`` where torchmetrics is installed (states summed across
processes), else an ``nn.Module`` whose states are buffers
(:class:`~lensdist_torch.metric._state.MetricBase`); either way ``.to(device)`` moves the states,
``state_dict`` saves them, and dtype casts leave them float64/int64 (float16 sums stop growing
after a few thousand pairs). ``load_state_dict`` checks what it loads: counts non-negative
integers, sums finite and consistent with the count, the map of the metric's shape.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from lensdist_torch.config import QualityConfig
from lensdist_torch.metric._inputs import check_data_range, get_config, measured
from lensdist_torch.metric._state import STATE, MetricBase, check_state, loaded_state
from lensdist_torch.metric.quality import measured_map

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
                "(no pixel of the mask valid after its 3 x 3 erosion, or flat images: "
                "every valid pixel in the risk map)"
            )
        raise RuntimeError("compute() needs at least one update() with a pair (or call it after reset + update)")
    return QualityMetricResult(
        quality_index=quality_sum / n, registration_map=map_sum / n, num_pairs=num_pairs.clone(),
        num_skipped=num_skipped.clone())


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


class RegistrationQualityMetric(MetricBase):
    """Accumulates the quality index and the registration map over a validation set.

    One class: a ``torchmetrics.Metric`` where torchmetrics is installed (states summed across
    processes, ready for ``MetricCollection`` and Lightning's ``log_dict``), else a plain
    ``nn.Module`` with the same methods and the states as buffers.

    Args:
        config: thresholds and block size; the defaults when None.
        data_range: the value of white in float inputs.
        validate: check values in each ``update`` (one host sync); skipped while compiling.
        pad: pad images to whole blocks (else H, W must be multiples of the block size).
        map_shape: (h, w) of the maps in blocks, e.g. (40, 53) for 320 x 424 images; None
            takes it from the first batch. Pass it for distributed runs in which a process may
            see no batch (a lazily shaped map cannot be summed with an empty one).
        **kwargs: ``torchmetrics.Metric``'s options (e.g. ``sync_on_compute``); they need
            torchmetrics.

    Shape:
        - img1, img2: (B, C, H, W); valid: (B, 1, H, W) or None.
        - compute(): () float64, the mean quality index (1 = no registration error).
        - compute_details(): QualityMetricResult with that index, the (1, ceil(H/b), ceil(W/b))
          mean map and the () counts of pairs averaged and skipped.

    A pair with nothing to measure (no pixel of its mask valid after the 3 x 3 erosion, or
    every valid pixel in the risk map) is never averaged, with or without ``validate``:
    ``update`` leaves it out of the sums and counts it in ``num_skipped``. The states stay
    float64/int64 under ``.half()``, ``.float()``, ``.bfloat16()`` and ``.to(dtype)`` (device
    moves apply), and ``load_state_dict`` refuses a state no sequence of updates can give (a
    negative count, a NaN sum, sums that do not match the count) with a one-line ValueError
    naming the field.

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

    is_differentiable = False
    higher_is_better = True
    full_state_update = False

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
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        check_data_range(data_range)
        self.config = get_config(config)
        self.data_range = data_range
        self.validate = validate
        self.pad = pad
        self.map_shape = map_shape
        defaults = (torch.zeros((), dtype=torch.float64), _initial_map(map_shape))
        defaults += (torch.zeros((), dtype=torch.long), torch.zeros((), dtype=torch.long))
        for name, default in zip(STATE, defaults):
            self.add_state(name, default=default, dist_reduce_fx="sum", persistent=True)

    @torch.no_grad()
    def update(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> None:
        """Add a batch of registered pairs (no host sync with ``validate=False``).

        Pairs with nothing to measure are counted in ``num_skipped``, not averaged.

        Args:
            img1: (B, C, H, W) registered images, float in [0, data_range] or uint8.
            img2: (B, C, H, W) the other images, on img1's device.
            valid: (B, 1, H, W) validity masks on img1's device, or None.
        """
        q, m, n, skipped = _batch_state(img1, img2, valid, self.config, self.data_range, self.validate, self.pad)
        device = self.quality_sum.device
        self.map_sum = _add_map(self.map_sum, m.to(device))
        self.quality_sum = self.quality_sum + q.to(device)
        self.num_pairs = self.num_pairs + _to_device(n, device)
        self.num_skipped = self.num_skipped + _to_device(skipped, device)
        self._batch = (q, n)

    def compute(self) -> torch.Tensor:
        """The mean quality index over every pair (of every process) since the last reset: () float64.

        Raises:
            RuntimeError: no pair was added.
        """
        return _result(self.quality_sum, self.map_sum, self.num_pairs, self.num_skipped).quality_index

    def compute_details(self) -> QualityMetricResult:
        """The mean index, the mean registration map and the counts of pairs averaged and skipped.

        Synced across processes as ``compute`` is.

        Raises:
            RuntimeError: no pair was added.
        """
        with self.sync_context(
            dist_sync_fn=self.dist_sync_fn, should_sync=self._to_sync, should_unsync=self._should_unsync
        ):
            return _result(self.quality_sum, self.map_sum, self.num_pairs, self.num_skipped)

    def forward(self, img1: torch.Tensor, img2: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Add the batch and return its own mean index (as ``torchmetrics.Metric.forward``).

        NaN when none of the batch's pairs has anything to measure.
        """
        self.update(img1, img2, valid)
        q, n = self._batch
        return q / torch.as_tensor(n, device=q.device)

    def _apply(self, fn, *args, **kwargs):
        """Device moves apply to the states (and their defaults); dtype changes do not."""
        return super()._apply(_keeping_dtypes(fn), *args, **kwargs)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if any(prefix + k in state_dict for k in STATE):  # states are saved only when persistent
            check_state(loaded_state(self, state_dict, prefix), self.map_shape)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        """The block size and data range, shown in the module's repr."""
        return f"block_size={self.config.block_size}, data_range={self.data_range}"
