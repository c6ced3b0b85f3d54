"""Validation of a checkpoint's payload before anything is built from it.

A checkpoint has passed its kind and format-version check (``core.storage.load_versioned``)
but its contents are still untrusted: every size is checked against the tensors actually
stored, before any buffer is allocated, and every failure is one CheckpointError naming the
file and what is wrong.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from lensdist_torch.config import LensdistConfig, config_from_dict
from lensdist_torch.core.storage import CheckpointError

Spec = dict[str, tuple[torch.dtype, tuple[Any, ...]]]


def require_keys(payload: dict, keys: tuple[str, ...], path: str | Path) -> None:
    missing = [k for k in keys if k not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {', '.join(missing)}")


def positive_int(payload: dict, key: str, path: str | Path) -> int:
    v = payload[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise CheckpointError(f"checkpoint {path}: {key} must be a positive int, got {v!r}")
    return v


def config_of(payload: dict, path: str | Path) -> LensdistConfig:
    try:
        return config_from_dict(payload["config"])
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint {path} holds an invalid config: {exc}") from None


def extra_of(payload: dict, path: str | Path) -> dict:
    extra = payload.get("extra", {})
    if not isinstance(extra, dict):
        raise CheckpointError(f"checkpoint {path}: extra must be a dict, got {type(extra).__name__}")
    return extra


def check_state(sd: Any, spec: Spec, dims: dict[str, int], path: str | Path) -> dict[str, int]:
    """Check that ``sd`` holds exactly the tensors of ``spec``: dense, finite, of the right dtype and shape.

    ``spec`` maps a name to (dtype, shape). A shape entry is an int, a name bound in ``dims``,
    or a new name, bound by its first use and required to agree afterwards. Returns the bound
    sizes.
    """
    if not isinstance(sd, dict):
        raise CheckpointError(f"checkpoint {path}: state_dict must be a dict, got {type(sd).__name__}")
    missing, unexpected = [k for k in spec if k not in sd], sorted(str(k) for k in sd if k not in spec)
    if missing:
        raise CheckpointError(f"checkpoint {path}: state_dict lacks {', '.join(missing)}")
    if unexpected:
        raise CheckpointError(f"checkpoint {path}: state_dict has unexpected entries {', '.join(unexpected)}")
    dims = dict(dims)
    for name, (dtype, shape) in spec.items():
        t = sd[name]
        if not isinstance(t, torch.Tensor) or t.layout != torch.strided:
            raise CheckpointError(f"checkpoint {path}: {name} is not a dense tensor")
        if t.dtype != dtype:
            raise CheckpointError(f"checkpoint {path}: {name} has dtype {t.dtype}, expected {dtype}")
        if t.dim() != len(shape):
            raise CheckpointError(f"checkpoint {path}: {name} has shape {tuple(t.shape)}, expected {len(shape)} dimensions")
        for size, want in zip(t.shape, shape):
            if isinstance(want, str):
                want = dims.setdefault(want, size)
            if size != want:
                expected = tuple(d if isinstance(d, int) else dims.get(d, d) for d in shape)
                raise CheckpointError(f"checkpoint {path}: {name} has shape {tuple(t.shape)}, expected {expected}")
        # a zero-stride (expanded) view of a tiny storage would claim sizes the file never held
        need = t.numel() * t.element_size()
        if t.numel() and t.untyped_storage().nbytes() - t.storage_offset() * t.element_size() < need:
            raise CheckpointError(f"checkpoint {path}: {name} is a view larger than its stored data")
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(f"checkpoint {path}: {name} holds NaN or infinite values")
    if not bool(sd.get("fitted", True)):
        raise CheckpointError(f"checkpoint {path} holds an unfitted model")
    return dims
