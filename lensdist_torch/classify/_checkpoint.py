"""Validation of a checkpoint's payload before anything is built from it.

A checkpoint has passed its kind and format-version check (``core.storage.load_versioned``)
but its contents are still untrusted: every size is checked against the tensors actually
stored, before any buffer is allocated, and every failure is one CheckpointError naming the
file and what is wrong.

The fitted values must also be ones a fit can produce (a file whose digest was recomputed
after an edit is still refused where its numbers are absurd). The bounds follow from what the
models are fitted on, quality maps with values in [0, 1] (``FEATURE_RANGE`` allows 0.1 of
noise either side; ``fit`` refuses features outside it), and from the fit itself:

* a mean of feature vectors lies in ``FEATURE_RANGE``;
* the rows of an eigen-space basis or PCA components are orthonormal (an SVD's right singular
  vectors): |U U^T - I| <= 1e-3 in float32, 2e-2 in float16;
* a training vector's coefficients (and, for the regressor, its residual norm) have a norm
  below ||x - mu|| <= width(FEATURE_RANGE) sqrt(D); so has the reject threshold (a distance);
* an explained-variance share lies in [0, 1];
* a Delta lies in [0, the image diagonal] (px): no lens moves a pixel further than that;
* k neighbours need more than k training pairs, and k is at most ``config.MAX_NEIGHBOURS``
  (the bound of ``regression.k``: the median must stay local); the PCA keeps min(n_components, N, D) rows;
* ``extra["scenes"]`` is a list of names and ``extra["texture"]`` the statistics of
  ``workflows.texture.texture_statistics``: finite histograms that sum to 1, a spread in [0, 1].
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from lensdist_torch.config import LensdistConfig, config_to_dict, stored_config
from lensdist_torch.core.storage import CheckpointError, check_compatible, load_versioned, save_versioned

Spec = dict[str, tuple[torch.dtype, tuple[Any, ...]]]


def save_model(model: torch.nn.Module, path: str | Path, *, kind: str, version: int, sizes: dict, extra: dict) -> None:
    """A fitted model's checkpoint, atomically: its sizes, its config, its buffers (on the CPU) and ``extra``.

    An existing file at ``path`` is replaced only if it is a checkpoint of ``kind``.
    """
    save_versioned(path, kind, version, {
        **sizes,
        "config": config_to_dict(model.config),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "extra": dict(extra),
    }, replace_same_kind_only=True)


def load_payload(path: str | Path, *, kind: str, version: int, what: str, map_location, sizes: tuple[str, ...],
                 expected: LensdistConfig | None) -> tuple[dict, LensdistConfig]:
    """A checkpoint's payload (digest verified) and its config, checked against ``expected``; ``sizes`` present."""
    payload = load_versioned(path, kind=kind, version=version, what=what, map_location=map_location, digest=True)
    require_keys(payload, (*sizes, "config", "state_dict"), path)
    config = config_of(payload, path)
    if expected is not None:
        check_compatible(config, expected, path)
    return payload, config


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
        return stored_config(payload["config"])
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
            raise CheckpointError(
                f"checkpoint {path}: {name} has shape {tuple(t.shape)}, expected {len(shape)} dimensions"
            )
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


#: The values a feature vector (a quality map) may hold, with 0.1 of slack for noise.
FEATURE_RANGE = (-0.1, 1.1)


def check_features_domain(x: torch.Tensor) -> None:
    """ValueError unless every feature lies in FEATURE_RANGE (what a fit may be given)."""
    lo, hi = FEATURE_RANGE
    if x.numel() and not bool(((x >= lo) & (x <= hi)).all()):
        raise ValueError(
            f"features must be quality maps, values in [0, 1] (within {FEATURE_RANGE}); got values in "
            f"[{float(x.min()):.4g}, {float(x.max()):.4g}]"
        )


def check_deltas(deltas: torch.Tensor, config: LensdistConfig) -> None:
    """ValueError unless every Delta lies in [0, the image diagonal] (px)."""
    top = max_delta(config)
    if deltas.numel() and not bool(((deltas >= 0) & (deltas <= top)).all()):
        raise ValueError(f"deltas must lie in [0, {top:.1f}] px (the image diagonal), got [{float(deltas.min()):.4g}, "
                         f"{float(deltas.max()):.4g}]")


def max_delta(config: LensdistConfig) -> float:
    """The largest plausible Delta (px): the diagonal of the analysis image."""
    return math.hypot(config.image.height, config.image.width)


def max_coefficient_norm(d: int) -> float:
    """The largest norm ||x - mu|| of two vectors of D features in FEATURE_RANGE (plus 1 % for rounding)."""
    return 1.01 * (FEATURE_RANGE[1] - FEATURE_RANGE[0]) * math.sqrt(d)


def in_range(sd: dict, name: str, *, lo: float, hi: float, path: str | Path, why: str) -> None:
    """CheckpointError naming ``name`` unless every value of ``sd[name]`` lies in [lo, hi]."""
    t = sd[name].float()
    if t.numel() and not bool(((t >= lo) & (t <= hi)).all()):
        raise CheckpointError(
            f"checkpoint {path}: {name} holds values in [{float(t.min()):.4g}, {float(t.max()):.4g}], "
            f"outside [{lo:.4g}, {hi:.4g}] ({why})"
        )


def row_norms_below(sd: dict, name: str, top: float, path: str | Path) -> None:
    t = sd[name].float()
    if t.numel() and float(t.norm(dim=-1).max()) > top:
        raise CheckpointError(
            f"checkpoint {path}: {name} has a row of norm {float(t.norm(dim=-1).max()):.4g}, above {top:.4g} "
            "(no quality map lies that far from the mean)"
        )


def orthonormal_rows(sd: dict, name: str, tol: float, path: str | Path) -> None:
    """CheckpointError unless the rows of each matrix in ``sd[name]`` (..., n, D) are orthonormal within ``tol``."""
    u = sd[name].float()
    if u.dim() == 2:
        u = u[None]
    eye = torch.eye(u.shape[-2])
    err = float((u @ u.transpose(-1, -2) - eye).abs().amax()) if u.numel() else 0.0
    if err > tol:
        raise CheckpointError(
            f"checkpoint {path}: the rows of {name} are not orthonormal (off by {err:.3g}, a fit gives at most {tol:g})"
        )


def _finite_floats(v: Any) -> bool:
    return isinstance(v, list) and all(type(x) in (int, float) and math.isfinite(x) for x in v)


def check_extra(payload: dict, path: str | Path) -> dict:
    """The payload's ``extra`` with its ``scenes`` and ``texture`` entries validated."""
    extra = extra_of(payload, path)
    if "scenes" in extra:
        scenes = extra["scenes"]
        if not (isinstance(scenes, list) and all(isinstance(s, str) and s for s in scenes)):
            raise CheckpointError(f"checkpoint {path}: extra.scenes must be a list of scene names, got {scenes!r:.80}")
    if "texture" in extra:
        problem = _texture_problem(extra["texture"])
        if problem:
            raise CheckpointError(f"checkpoint {path}: extra.texture {problem}")
    return extra


def _texture_problem(tex: Any) -> str | None:
    if not isinstance(tex, dict):
        return f"must be a dict, got {type(tex).__name__}"
    missing = [k for k in ("names", "edges", "reference", "spread") if k not in tex]
    if missing:
        return f"lacks {', '.join(missing)}"
    names, edges, ref, spread = tex["names"], tex["edges"], tex["reference"], tex["spread"]
    if not (isinstance(names, list) and names and all(isinstance(s, str) and s for s in names)):
        return "names must be a non-empty list of scene names"
    if not (_finite_floats(edges) and edges and all(a < b for a, b in zip(edges, edges[1:])) and edges[0] > 0):
        return "edges must be increasing positive finite numbers"
    if not (isinstance(ref, list) and len(ref) == len(names)):
        return f"reference must hold one histogram per name ({len(names)})"
    for h in ref:
        if not (_finite_floats(h) and len(h) == len(edges) + 1 and min(h) >= 0 and abs(sum(h) - 1) <= 1e-6):
            return f"reference must hold histograms of {len(edges) + 1} finite non-negative shares summing to 1"
    if type(spread) not in (int, float) or not 0 <= spread <= 1:  # a total-variation distance (NaN fails too)
        return f"spread must be a number in [0, 1], got {spread!r}"
    return None
