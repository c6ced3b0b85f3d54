"""Image checks, grey conversion, loading, and the embedded scenes (SPEC section 1)."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale

__all__ = [
    "check_image",
    "check_image_pair",
    "check_valid_mask",
    "to_grey",
    "as_batch",
    "load_image",
    "load_scene",
    "scene_names",
    "resize_to",
]

_DATA = Path(__file__).resolve().parent.parent / "data" / "scenes"


def check_image(img: object, name: str = "img", finite: bool = True) -> torch.Tensor:
    """Check that ``img`` is a (B, C, H, W) image tensor of a supported dtype.

    Raises:
        TypeError: not a tensor, or an integer dtype other than uint8.
        ValueError: not 4-D, an empty batch or image, a channel count other than 1 or 3, or
            (with ``finite``) NaN or Inf values.
    """
    if not isinstance(img, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(img).__name__}")
    if img.dtype != torch.uint8 and not img.is_floating_point():
        raise TypeError(f"{name} must be a float tensor in [0, 1] or uint8, got dtype {img.dtype}")
    if img.dim() != 4:
        raise ValueError(f"{name} must have shape (B, C, H, W), got {tuple(img.shape)}")
    if img.shape[0] == 0:
        raise ValueError(f"{name} is an empty batch: shape {tuple(img.shape)}")
    if img.shape[1] not in (1, 3):
        raise ValueError(f"{name} must have 1 or 3 channels, got shape {tuple(img.shape)}")
    if img.shape[2] == 0 or img.shape[3] == 0:
        raise ValueError(f"{name} has an empty image: shape {tuple(img.shape)}")
    # One reduction instead of isfinite().all(): NaN and Inf propagate through a sum. The exact
    # (slower) test runs only to word the error.
    acc = torch.float64 if img.dtype == torch.float64 else torch.float32  # float16 sums overflow
    if finite and img.is_floating_point() and not bool(torch.isfinite(img.sum(dtype=acc))):
        if not bool(torch.isfinite(img).all()):
            raise ValueError(f"{name} contains NaN or Inf values")
        raise ValueError(f"{name} has values so large that they overflow; expected [0, 1]")
    return img


def check_image_pair(
    img1: object, img2: object, block_size: int | None = None, finite: bool = True
) -> None:
    """Check two images of the same shape, optionally divisible into blocks."""
    check_image(img1, "img1", finite)
    check_image(img2, "img2", finite)
    if img1.shape != img2.shape:  # type: ignore[union-attr]
        raise ValueError(
            f"img1 and img2 must have the same shape, got {tuple(img1.shape)} and {tuple(img2.shape)}"  # type: ignore[union-attr]
        )
    if block_size is not None:
        h, w = img1.shape[-2:]  # type: ignore[union-attr]
        if h % block_size or w % block_size:
            raise ValueError(
                f"img1/img2 height and width must be multiples of block_size={block_size}, "
                f"got {h} x {w}"
            )


def check_valid_mask(valid: object, like: torch.Tensor, name: str = "valid") -> torch.Tensor:
    """Check a validity mask of shape (B, 1, H, W) matching ``like``; return it as ``like``'s dtype."""
    if not isinstance(valid, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or None, got {type(valid).__name__}")
    b, _, h, w = like.shape
    if tuple(valid.shape) != (b, 1, h, w):
        raise ValueError(f"{name} must have shape {(b, 1, h, w)}, got {tuple(valid.shape)}")
    return valid.to(dtype=like.dtype, device=like.device)


def to_grey(img: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) uint8 or float -> (B, 1, H, W) float in [0, 1].

    uint8 is divided by 255; three channels become grey with the ITU-R 601 luma weights
    (kornia's ``rgb_to_grayscale``).
    """
    if img.dtype == torch.uint8:
        img = img.float() / 255.0
    if img.shape[1] == 3:
        img = rgb_to_grayscale(img)
    return img


def as_batch(img: torch.Tensor, name: str = "img") -> torch.Tensor:
    """(H, W), (C, H, W) or (1, C, H, W) -> (1, C, H, W)."""
    if not isinstance(img, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(img).__name__}")
    if img.dim() == 2:
        return img[None, None]
    if img.dim() == 3:
        return img[None]
    if img.dim() == 4 and img.shape[0] == 1:
        return img
    raise ValueError(f"{name} must have shape (H, W), (C, H, W) or (1, C, H, W), got {tuple(img.shape)}")


def load_image(path: str | Path, grey: bool = True) -> torch.Tensor:
    """Load an image file as a (1, C, H, W) float tensor in [0, 1] (C = 1 with ``grey``).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file cannot be decoded as an image (the message names the file).
    """
    from kornia.io import ImageLoadType, load_image as _kornia_load

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    try:
        img = _kornia_load(str(path), ImageLoadType.UNCHANGED, device="cpu")
    except Exception as exc:  # kornia_rs raises several types for undecodable files
        raise ValueError(f"cannot read image {path}: {exc}") from exc
    if img.dim() == 2:
        img = img[None]
    if img.shape[0] == 4:  # drop alpha
        img = img[:3]
    if img.shape[0] == 2:  # grey + alpha
        img = img[:1]
    if img.dtype == torch.uint8:
        img = img.float() / 255.0
    elif img.dtype == torch.uint16:
        img = img.float() / 65535.0
    else:
        img = img.float()
    img = img[None]
    if grey and img.shape[1] == 3:
        img = rgb_to_grayscale(img)
    return img.contiguous()


def scene_names() -> list[str]:
    """Names of the embedded CC0 scenes (see ``lensdist_torch/data/README.md``)."""
    return sorted(p.stem for p in _DATA.glob("*.png"))


def load_scene(name: str = "gravel") -> torch.Tensor:
    """An embedded scene as a (1, 1, 512, 512) float tensor in [0, 1]."""
    names = scene_names()
    if name not in names:
        raise ValueError(f"unknown scene {name!r}; embedded scenes are {names}")
    return load_image(_DATA / f"{name}.png", grey=True)


def resize_to(img: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bring a (B, C, h, w) image to (height, width): centre crop to the aspect ratio, then
    area-resample (antialiased bilinear). Used by entry points that take a user's photos."""
    h, w = img.shape[-2:]
    target = width / height
    if w / h > target:  # too wide: crop columns
        new_w = max(1, round(h * target))
        x0 = (w - new_w) // 2
        img = img[..., :, x0 : x0 + new_w]
    elif w / h < target:
        new_h = max(1, round(w / target))
        y0 = (h - new_h) // 2
        img = img[..., y0 : y0 + new_h, :]
    if img.shape[-2:] == (height, width):
        return img
    return F.interpolate(img, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
