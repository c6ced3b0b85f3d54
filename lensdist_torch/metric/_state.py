"""The stateful metric's base and the checks of its loaded state (:mod:`~lensdist_torch.metric.stateful`).

:data:`MetricBase` is ``torchmetrics.Metric`` where torchmetrics is installed, else a plain
``nn.Module`` offering the part of its interface the metric uses (``add_state`` as buffers,
``reset``, a no-op ``sync_context``): one metric class either way.

A state no sequence of updates can produce (a negative count, a NaN sum, sums that do not
match the count, a map of another shape) is refused with a one-line ValueError naming the field.
"""

from __future__ import annotations

import contextlib
import math

import torch
from torch import nn

try:  # optional: the metric is a torchmetrics.Metric where torchmetrics is installed
    import torchmetrics as _torchmetrics
except ImportError:  # pragma: no cover - depends on the environment
    _torchmetrics = None

__all__ = ["STATE", "MetricBase", "check_state", "loaded_state"]

#: The accumulators, in the order of the buffers (and of the state_dict).
STATE = ("quality_sum", "map_sum", "num_pairs", "num_skipped")


def _count(name: str, value: object) -> int:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a tensor in the state_dict, got {type(value).__name__}")
    if value.is_meta:
        raise ValueError(f"{name} is on the meta device (no value) in the state_dict")
    if value.dim() != 0 or value.dtype == torch.bool or value.is_floating_point() or value.is_complex():
        raise ValueError(
            f"{name} must be a 0-dim integer tensor in the state_dict, got {value.dtype} {tuple(value.shape)}"
        )
    n = int(value)
    if n < 0:
        raise ValueError(f"{name} must be a count >= 0 in the state_dict, got {n}")
    return n


def _float_sum(name: str, value: object) -> torch.Tensor:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a tensor in the state_dict, got {type(value).__name__}")
    if value.is_meta:
        raise ValueError(f"{name} is on the meta device (no values) in the state_dict")
    if not value.is_floating_point():
        raise ValueError(f"{name} must be a float tensor in the state_dict, got dtype {value.dtype}")
    value = value.detach().double().cpu()
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains NaN or Inf values in the state_dict")
    return value


def check_state(state: dict, map_shape: tuple[int, int] | None) -> None:
    """One-line errors naming the field for a state that no sequence of updates can produce.

    Args:
        state: the four accumulators as they would be after loading.
        map_shape: the metric's fixed (h, w), or None (the map's shape taken from the state).
    """
    n = _count("num_pairs", state["num_pairs"])
    _count("num_skipped", state["num_skipped"])
    q = _float_sum("quality_sum", state["quality_sum"])
    m = _float_sum("map_sum", state["map_sum"])
    if q.dim() != 0:
        raise ValueError(f"quality_sum must be a 0-dim tensor in the state_dict, got shape {tuple(q.shape)}")
    tol = 1e-6 * n + 1e-9  # a pair's index and map mean agree to float64 rounding (float32 in old states)
    if not -tol <= float(q) <= n + tol:
        raise ValueError(
            f"quality_sum must lie in [0, num_pairs] = [0, {n}] (each index is in [0, 1]), got {float(q)!r}"
        )
    if map_shape is not None and tuple(m.shape) != (1, *map_shape):
        raise ValueError(f"map_sum must have shape {(1, *map_shape)} (this metric's map_shape), got {tuple(m.shape)}")
    if m.dim() == 0:
        if n or float(m) != 0.0:
            raise ValueError(
                f"map_sum must be a (1, h, w) map once pairs are counted, got a 0-dim {float(m)!r} with num_pairs {n}"
            )
        return
    if m.dim() != 3 or m.shape[0] != 1 or m.numel() == 0:
        raise ValueError(f"map_sum must have shape (1, h, w) with h, w > 0, got {tuple(m.shape)}")
    lo, hi = float(m.min()), float(m.max())
    if lo < -tol or hi > n + tol:
        raise ValueError(
            f"map_sum must lie in [0, num_pairs] = [0, {n}] (each block ratio is in [0, 1]), got [{lo!r}, {hi!r}]"
        )
    # every pair adds 1 - mean(map) to quality_sum and map to map_sum
    gap = float(q) + float(m.mean()) - n
    if not math.isfinite(gap) or abs(gap) > tol:
        raise ValueError(
            f"quality_sum ({float(q)!r}) does not match map_sum: quality_sum + mean(map_sum) must equal "
            f"num_pairs ({n}), off by {gap:.3g}"
        )


def loaded_state(module, state_dict, prefix: str) -> dict:
    """The accumulators after loading: the state_dict's, or the module's own where it has none.

    A state saved before ``num_skipped`` existed loads with no pair skipped.
    """
    key = prefix + "num_skipped"
    if key not in state_dict and all(prefix + k in state_dict for k in STATE[:3]):
        state_dict[key] = torch.zeros((), dtype=torch.long)
    return {k: state_dict.get(prefix + k, getattr(module, k)) for k in STATE}


class _ModuleMetric(nn.Module):
    """``torchmetrics.Metric``'s interface as the metric uses it, without torchmetrics.

    States are buffers (moved by ``.to``, saved by ``state_dict`` when persistent); ``reset``
    restores their defaults on the states' device; there are no processes to sync.
    """

    dist_sync_fn = None
    _to_sync = _should_unsync = True

    def __init__(self, **kwargs) -> None:
        if kwargs:
            raise TypeError(
                f"{type(self).__name__}: {', '.join(sorted(kwargs))} are torchmetrics.Metric options; "
                "pip install torchmetrics to use them"
            )
        super().__init__()
        self._defaults: dict[str, torch.Tensor] = {}

    def add_state(self, name: str, default: torch.Tensor, dist_reduce_fx: str | None = None, persistent: bool = False):
        """A state called ``name``, a buffer starting at ``default`` (``dist_reduce_fx`` unused)."""
        self._defaults[name] = default.clone()
        self.register_buffer(name, default.clone(), persistent=persistent)

    def reset(self) -> None:
        """Every state back to its default, on the device the states are on."""
        for name, default in self._defaults.items():
            setattr(self, name, default.clone().to(getattr(self, name).device))

    def sync_context(self, dist_sync_fn=None, should_sync: bool = True, should_unsync: bool = True):
        """No processes to gather: a context that does nothing."""
        return contextlib.nullcontext()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        """As torchmetrics: a state takes the saved tensor's shape (a lazily shaped map)."""
        for name in self._defaults:
            value = state_dict.get(prefix + name)
            current = getattr(self, name)
            if isinstance(value, torch.Tensor) and value.shape != current.shape:
                setattr(self, name, torch.zeros(value.shape, dtype=current.dtype, device=current.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


#: The stateful metric's base class: ``torchmetrics.Metric`` when installed, else :class:`_ModuleMetric`.
MetricBase = _torchmetrics.Metric if _torchmetrics is not None else _ModuleMetric
