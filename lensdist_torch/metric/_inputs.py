"""Input checks and preparation shared by the metric's entry points (docs/method.md, section 1).

One place decides what the maps and the loss accept:

* images: (B, C, H, W), C in {1, 3}, uint8 (divided by 255) or float in [0, data_range]
  (divided by ``data_range``); any H and W, padded to whole blocks by replicating the last row
  and column (``pad=True``), or H and W multiples of the block size (``pad=False``);
* the validity mask: (B, 1, H, W), bool or numeric in [0, 1]; a pixel is valid where the mask
  is >= 0.5 (warped masks are fractional at their edges). The mask is binarised and detached:
  no gradient ever reaches it. Padding pixels are invalid. An error is counted only where the
  mask is valid after a 3 x 3 erosion (:func:`erode_valid`); a sample with no such pixel has
  nothing to measure (:func:`check_pair_values` refuses it where a quality index is asked);
* placement: dense (strided) tensors, ``img2`` and ``valid`` on ``img1``'s device, none on the
  meta device (a meta tensor has no values to measure).

The value checks (NaN/Inf, the range of the images, the values of the mask) need the data on
the host: they cost one reduction per tensor and one synchronisation per call. ``validate=False``
skips them (kornia's convention); they are skipped automatically while ``torch.compile`` traces,
so that a compiled loss has no graph break. Type and shape checks always run (they are free).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from lensdist_torch.config import QualityConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.images import check_image_pair, should_validate, to_grey

#: Tolerance of the range checks, in units of ``data_range``: interpolation and rounding may put
#: a value a little outside [0, 1]; 0-255 images or mean/std-normalised ones are far outside.
RANGE_TOLERANCE = 1e-2


#: The default settings, built once (a frozen dataclass; building one costs ~20 us per call).
_DEFAULT_CONFIG = QualityConfig()


def get_config(config: QualityConfig | None) -> QualityConfig:
    """``config`` or the defaults; a TypeError for anything else."""
    return _DEFAULT_CONFIG if config is None else or_defaults(config, QualityConfig)  # one default, built once


def check_data_range(data_range: object) -> None:
    ok = isinstance(data_range, (int, float)) and not isinstance(data_range, bool)
    if not (ok and math.isfinite(data_range) and data_range > 0):  # type: ignore[arg-type]
        raise ValueError(f"data_range must be a positive number, got {data_range!r}")


def _number(x: float) -> str:
    return repr(float(f"{x:.6g}"))


def _range_error(name: str, lo: float, hi: float, data_range: float, tolerance: float = RANGE_TOLERANCE) -> str | None:
    """The one-line error for a float image with values outside [0, data_range] by over ``tolerance`` of it, or None."""
    eps = tolerance * data_range
    if data_range == 1.0:
        if hi > 1.0 + eps:
            if hi <= 255.0 * (1 + RANGE_TOLERANCE) and hi > 2.0:
                hint = "pass data_range=255"
            elif 255.0 < hi <= 65535.0 * (1 + RANGE_TOLERANCE):
                hint = "pass data_range=65535"
            else:
                hint = "pass data_range (the value of white) or clamp the images"
            return f"{name} has values up to {_number(hi)}; expected [0, 1] — {hint}"
        if lo < -eps:
            return (
                f"{name} has values down to {_number(lo)}; expected [0, 1] — "
                "images must be non-negative (undo a mean/std normalisation, or clamp)"
            )
        return None
    if hi > data_range + eps or lo < -eps:
        return (
            f"{name} has values in [{_number(lo)}, {_number(hi)}]; expected [0, data_range] "
            f"with data_range={_number(data_range)} — pass the value of white as data_range"
        )
    return None


def check_placement(tensors: list[tuple[str, torch.Tensor]], device: torch.device) -> None:
    """Dense tensors with values, all on ``device`` (img1's): a one-line error naming the tensor.

    Free (no data is read), so it always runs, with or without ``validate``.

    Raises:
        TypeError: a sparse (or otherwise non-strided) tensor.
        ValueError: a tensor on the meta device, or on another device than ``device``.
    """
    for name, t in tensors:
        if t.layout != torch.strided:
            raise TypeError(f"{name} must be a dense tensor, got layout {t.layout} (call .to_dense())")
        if t.is_meta:
            where = "" if device.type == "meta" else f" on {device}"
            raise ValueError(f"{name} is on the meta device (a shape, no values); expected a tensor with values{where}")
        if t.device != device:
            raise ValueError(f"{name} is on {t.device}; expected img1's device {device} (every input on one device)")


def check_mask_shape(valid: object, like: torch.Tensor, name: str = "valid") -> None:
    """Type and shape of a validity mask: a real or bool (B, 1, H, W) tensor matching ``like``.

    Its values are checked by :func:`check_values` (with the images, in one host sync).
    """
    if not isinstance(valid, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or None, got {type(valid).__name__}")
    if valid.is_complex():
        raise TypeError(f"{name} must be a bool or real tensor, got dtype {valid.dtype}")
    b, _, h, w = like.shape
    if tuple(valid.shape) != (b, 1, h, w):
        raise ValueError(f"{name} must have shape {(b, 1, h, w)}, got {tuple(valid.shape)}")


#: What a sample leaves to measure (:func:`~lensdist_torch.metric._hard.measure_codes`): no valid
#: pixel, valid pixels all in the risk map (flat images: no edge to compare), a pixel to measure.
NOTHING_VALID, ONLY_AT_RISK, MEASURABLE = 0.0, 0.5, 1.0


def measured(codes: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the samples whose code is ``MEASURABLE`` (the codes are exact: 0, 0.5 or 1)."""
    return codes == MEASURABLE


def check_values(
    images: list[tuple[str, torch.Tensor]],
    valid: torch.Tensor | None,
    *,
    data_range: float,
    measurable: torch.Tensor | None = None,
    measurable_name: str = "valid",
    tolerance: float = RANGE_TOLERANCE,
) -> None:
    """NaN/Inf and range of float images, NaN and range of the mask: one host sync in all.

    Args:
        images: (name, image) pairs.
        valid: the mask as given, or None.
        data_range: the value of white in float images.
        measurable: (B,) codes of what each sample leaves to measure (1 a valid pixel outside
            the risk map, 0.5 only pixels at risk, 0 no valid pixel), or None: every sample
            must have something (checked in the same host sync).
        measurable_name: the argument to blame when a sample has nothing to measure (``valid``,
            or ``img1`` when the images are too small to keep a pixel after padding).
        tolerance: how far outside [0, data_range] a float image may reach, in units of data_range.

    Raises:
        ValueError: one line naming the tensor (and ``data_range`` where it would help).
    """
    parts, names = [], []
    for name, img in images:
        if img.is_floating_point():
            parts += torch.aminmax(img)  # NaN propagates into both
            names.append(name)
    if valid is not None and valid.dtype != torch.bool:
        parts += torch.aminmax(valid)
        names.append("valid")
    if measurable is not None:
        parts += [measurable.min(), measurable.argmin()]
    if not parts:
        return
    if len({p.dtype for p in parts}) > 1:
        parts = [p.double() for p in parts]
    stats = torch.stack(parts).tolist()  # the one synchronisation
    for i, name in enumerate(names):
        lo, hi = stats[2 * i], stats[2 * i + 1]
        if not (math.isfinite(lo) and math.isfinite(hi)):
            if name == "valid":
                raise ValueError("valid contains NaN or Inf values; expected a mask in [0, 1]")
            raise ValueError(f"{name} contains NaN or Inf values")
        if name == "valid":
            if lo < -RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
                raise ValueError(
                    f"valid has values in [{_number(lo)}, {_number(hi)}]; expected a mask in [0, 1] "
                    "(bool, or float binarised at 0.5)"
                )
            continue
        message = _range_error(name, lo, hi, data_range, tolerance)
        if message is not None:
            raise ValueError(message)
    if measurable is not None and stats[-2] != MEASURABLE:
        at_risk = stats[-2] == ONLY_AT_RISK
        raise ValueError(_nothing_to_measure(measurable_name, int(stats[-1]), measurable.numel(), at_risk))


def _nothing_to_measure(name: str, index: int, batch: int, at_risk: bool = False) -> str:
    where = f"sample [{index}] of the batch of {batch}" if batch > 1 else "the pair"
    if at_risk:
        return (
            f"img1 and img2 leave no edge to measure in {where}: every valid pixel is in the risk map "
            "(both gradients at most theta_G nearby: flat images); a pair with nothing to measure has "
            "no quality index — drop it (validate=False gives NaN)"
        )
    if name == "valid":
        return (
            f"valid leaves no pixel to measure in {where} (none is valid after the 3 x 3 erosion); "
            "a pair with nothing to measure has no quality index — drop it (validate=False gives NaN)"
        )
    return (
        f"{name} is too small to measure: with one row or column, padded to whole blocks, no pixel "
        "is left after the 3 x 3 erosion; use at least 2 x 2 pixels (validate=False gives NaN)"
    )


def erode_valid(valid: torch.Tensor) -> torch.Tensor:
    """3 x 3 erosion of a validity mask; the image border counts as valid.

    max_pool2d pads with -inf, so pixels outside the image never invalidate their neighbours.

    Args:
        valid: (B, 1, H, W) float mask (1 = valid).

    Returns:
        (B, 1, H, W): the minimum of ``valid`` over each 3 x 3 window.

    Example:
        >>> v = torch.ones(1, 1, 5, 5)
        >>> v[0, 0, 2, 2] = 0
        >>> int(erode_valid(v).sum())  # the invalid pixel removes its 3 x 3 neighbourhood
        16
    """
    return -F.max_pool2d(-valid, kernel_size=3, stride=1, padding=1)


def binarise_valid(valid: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The mask as {0, 1} in ``like``'s dtype: valid where >= 0.5 (bool: where True), detached."""
    if valid.dtype == torch.bool:
        return valid.detach().to(like.dtype)
    return (valid.detach() >= 0.5).to(like.dtype)


def pad_to_blocks(g1, g2, valid, block: int):
    """Replicate-pad two (B, 1, H, W) images to whole blocks; the padding is invalid.

    Returns the padded images and the padded {0, 1} mask (all ones on the image when
    ``valid`` is None), or the inputs unchanged when H and W are already multiples of ``block``.
    """
    h, w = g1.shape[-2:]
    ph, pw = -h % block, -w % block
    if not (ph or pw):
        return g1, g2, valid
    if valid is None:
        valid = torch.ones_like(g1)
    g1 = F.pad(g1, (0, pw, 0, ph), mode="replicate")
    g2 = F.pad(g2, (0, pw, 0, ph), mode="replicate")
    return g1, g2, F.pad(valid, (0, pw, 0, ph), value=0.0)


def prepare_pair(img1, img2, valid, *, config, data_range, validate=True, pad=None, overshoot=None):
    """Check and convert a pair: grey images in [0, 1] of one dtype, the binarised mask, config.

    Args:
        img1: (B, C, H, W) uint8 or float image.
        img2: (B, C, H, W) the other image, on img1's device.
        valid: (B, 1, H, W) mask on img1's device, or None.
        config: QualityConfig or None.
        data_range: the value of white in float images.
        validate: run the value checks (skipped while compiling).
        pad: None: no block structure (per-pixel maps, any size); True: pad to whole blocks;
            False: H and W must be multiples of the block size.
        overshoot: None (values within ``RANGE_TOLERANCE`` of [0, data_range]), or how far
            outside it, in units of data_range, float images may reach (an interpolation's
            overshoot), taken as they are.

    Returns:
        g1, g2 (B, 1, H', W'), valid ({0, 1} (B, 1, H', W') or None), the config.
    """
    g1, g2, mask, cfg = prepare_unchecked(img1, img2, valid, config=config, data_range=data_range, pad=pad)
    if should_validate(validate):  # the mask as given, not as binarised
        check_values([("img1", img1), ("img2", img2)], valid, data_range=data_range,
                     tolerance=RANGE_TOLERANCE if overshoot is None else overshoot)
    return g1, g2, mask, cfg


def prepare_unchecked(img1, img2, valid, *, config, data_range, pad=None):
    """:func:`prepare_pair` without the value checks (types, shapes and placement are checked).

    For entry points that learn which samples have a pixel to measure while computing and then
    run :func:`check_pair_values` (one host sync for all the checks).
    """
    cfg = get_config(config)
    check_data_range(data_range)
    check_image_pair(img1, img2, cfg.block_size if pad is False else None, finite=False)
    if valid is not None:
        check_mask_shape(valid, img1)
    check_placement([("img1", img1), ("img2", img2)] + ([] if valid is None else [("valid", valid)]), img1.device)
    g1, g2 = to_grey(img1), to_grey(img2)
    dtype = torch.promote_types(g1.dtype, g2.dtype)
    g1, g2 = g1.to(dtype), g2.to(dtype)
    if valid is not None:
        valid = binarise_valid(valid, g1)
    if data_range != 1.0:  # uint8 is already / 255 (docs/method.md, section 1)
        if img1.is_floating_point():
            g1 = g1 / data_range
        if img2.is_floating_point():
            g2 = g2 / data_range
    if pad:
        g1, g2, valid = pad_to_blocks(g1, g2, valid, cfg.block_size)
    return g1, g2, valid, cfg


def check_pair_values(img1, img2, valid, *, data_range, measurable=None) -> None:
    """The value checks of :func:`prepare_pair`, and that every sample has a pixel to measure.

    Args:
        img1: the image as given.
        img2: the other image as given.
        valid: the mask as given, or None.
        data_range: the value of white in float images.
        measurable: (B,) codes of what each sample leaves to measure (``measure_codes``), or
            None (not checked).

    Raises:
        ValueError: one line naming the tensor; a sample with nothing to measure names
            ``valid`` (or ``img1`` when no mask was given and the image is too small).
    """
    name = "valid" if valid is not None else "img1"
    check_values(
        [("img1", img1), ("img2", img2)], valid, data_range=data_range, measurable=measurable, measurable_name=name
    )
