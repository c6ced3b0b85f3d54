"""Image checks, grey conversion, loading, and the embedded scenes (docs/method.md section 1).

Files are decoded by kornia (``kornia.io``, the Rust decoders of kornia_rs); the suffix, in any
letter case, chooses the decoder. :data:`IMAGE_SUFFIXES` lists exactly what it reads here:

===================  ============================================================================
``.png``             grey, RGB, RGBA at 8 or 16 bits; 8-bit palette (expanded to its colours)
``.jpg``, ``.jpeg``  grey and RGB (YCbCr), baseline and progressive
``.tif``, ``.tiff``  1 or 3 channels of 8-bit, 16-bit or 32-bit float samples (float in [0, 1])
``.webp``            RGB and RGBA, lossy and lossless
===================  ============================================================================

Refused with a one-line ``ValueError`` naming the file: other suffixes (BMP, GIF, PNM, ...), PNGs
with 1, 2 or 4-bit samples or grey + alpha, CMYK JPEGs, 4-channel, 64-bit float or integer
TIFFs, float TIFFs with values outside [0, 1] or NaN, content that does not match the suffix (a PNG
named ``.jpg``), empty, truncated or corrupt files, directories, unreadable files, and images of
more than ``max_pixels`` pixels (read from the header before decoding). An alpha channel is
dropped (the colours are kept as stored); 8-bit samples are divided by 255, 16-bit by 65535.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale

from lensdist_torch.config.checks import one_line
from lensdist_torch.core.image_headers import read_header

__all__ = [
    "IMAGE_SUFFIXES",
    "MAX_PIXELS",
    "centre_crop_box",
    "check_image",
    "check_image_pair",
    "should_validate",
    "to_grey",
    "as_batch",
    "load_image",
    "load_scene",
    "scene_names",
    "resize_to",
]

_DATA = Path(__file__).resolve().parent.parent / "data" / "scenes"

#: File suffixes (lower case) that :func:`load_image` decodes; any letter case is accepted.
IMAGE_SUFFIXES: frozenset[str] = frozenset({".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp"})

#: Default largest image :func:`load_image` accepts, in pixels (100 megapixels: about 1.2 GB as
#: float RGB).
MAX_PIXELS = 100_000_000

# pixels converted to float at once: bounds the conversion's temporaries (~16 MB a chunk)
_CHUNK_PIXELS = 1 << 20


def should_validate(validate: bool) -> bool:
    """Whether to run the value checks (NaN, Inf, ranges: each a host sync): asked, and not while torch.compile traces.

    The one switch of the package's value checks: every entry point's ``validate`` (the
    metric's, the estimators') and :func:`check_image`'s ``finite`` go through it.

    Example:
        >>> should_validate(True), should_validate(False)
        (True, False)
    """
    return bool(validate) and not torch.compiler.is_compiling()


def check_image(img: object, name: str = "img", finite: bool = True) -> torch.Tensor:
    """Check that ``img`` is a (B, C, H, W) image tensor of a supported dtype.

    Raises:
        TypeError: not a tensor, or an integer dtype other than uint8.
        ValueError: not 4-D, an empty batch or image, a channel count other than 1 or 3, or
            (with ``finite``) NaN or Inf values.

    Example:
        >>> check_image(torch.zeros(2, 3, 4, 5, dtype=torch.uint8)).shape  # returned as it is
        torch.Size([2, 3, 4, 5])
        >>> check_image(torch.zeros(3, 4, 5), "frame")
        Traceback (most recent call last):
        ...
        ValueError: frame must have shape (B, C, H, W), got (3, 4, 5)
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
    if should_validate(finite) and img.is_floating_point() and not bool(torch.isfinite(img.sum(dtype=acc))):
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


def to_grey(img: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) uint8 or float -> (B, 1, H, W) float in [0, 1].

    uint8 is divided by 255; three channels become grey with the ITU-R 601 luma weights
    (kornia's ``rgb_to_grayscale``).

    Example:
        >>> red = torch.tensor([255, 0, 0], dtype=torch.uint8).view(1, 3, 1, 1)
        >>> tuple(to_grey(red).shape), round(float(to_grey(red)), 3)  # red's luma weight
        ((1, 1, 1, 1), 0.299)
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


def _check_pixels(path: Path, height: int, width: int, max_pixels: int | None) -> None:
    if max_pixels is not None and height * width > max_pixels:
        raise ValueError(
            f"image file {path} is {width} x {height} pixels ({height * width / 1e6:.1f} megapixels), over "
            f"the limit of max_pixels={max_pixels} ({max_pixels / 1e6:g} megapixels)"
        )


def load_image(path: str | Path, grey: bool = True, max_pixels: int | None = MAX_PIXELS) -> torch.Tensor:
    """Load an image file as a (1, C, H, W) float32 tensor in [0, 1] (C = 1 with ``grey``, else 1 or 3).

    The formats and what is refused: this module's docstring. The size is read from the header and
    checked against ``max_pixels`` before decoding (a small file claiming a huge image costs
    nothing); the conversion to float works in strips (memory: the decoded file plus the result).

    Args:
        path: the image file.
        grey: convert colour to grey with the ITU-R 601 luma weights (kornia's ``rgb_to_grayscale``).
        max_pixels: largest height x width accepted; ``None`` for no limit.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: anything else that stops the file from giving a correct image; the one-line
            message names the file.

    Example:
        >>> import tempfile
        >>> from kornia.io import write_image
        >>> rgb = torch.tensor([[[255, 0]], [[0, 255]], [[0, 0]]], dtype=torch.uint8)  # (3, 1, 2): red, green
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     write_image(Path(tmp) / "tiny.png", rgb)
        ...     grey, colour = load_image(Path(tmp) / "tiny.png"), load_image(Path(tmp) / "tiny.png", grey=False)
        >>> tuple(grey.shape), [round(v, 3) for v in grey.flatten().tolist()], colour.flatten().tolist()
        ((1, 1, 1, 2), [0.299, 0.587], [1.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    """
    if max_pixels is not None and (isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels <= 0):
        raise ValueError(f"max_pixels must be a positive int or None, got {max_pixels!r}")
    path = _image_path(path)
    img, lut = _decode(path, max_pixels)
    return _to_float(img, lut, _sample_scale(img, path), grey)


def _image_path(path: str | Path) -> Path:
    """``path`` as a Path to an existing regular file with an image suffix, else the one-line error."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"image file not found: {path}")
    if path.is_dir():
        raise ValueError(f"image path {path} is a directory, not an image file")
    if not path.is_file():
        raise ValueError(f"image path {path} is not a regular file")
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        raise ValueError(
            f"image file {path} has the suffix {path.suffix or '(none)'!r}; the decoder reads "
            f"{', '.join(sorted(IMAGE_SUFFIXES))} (any case)"
        )
    return path


def _decode(path: Path, max_pixels: int | None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The decoded samples (C, H, W) and a PNG's palette (N, 3) where the decoder gave its indices.

    The header's size is checked against ``max_pixels`` before decoding, the decoded size after.
    """
    from kornia.io import ImageLoadType
    from kornia.io import load_image as _kornia_load

    try:
        with path.open("rb") as f:
            size, palette = read_header(f, path)
    except OSError as exc:
        raise ValueError(f"cannot read image file {path}: {exc.strerror or one_line(exc, 300)}") from exc
    if size is not None:
        _check_pixels(path, *size, max_pixels)
    try:
        img = _kornia_load(str(path), ImageLoadType.UNCHANGED, device="cpu")
    except Exception as exc:  # kornia_rs raises several types for undecodable files
        reason = one_line(exc, 300).removeprefix(f"Failed to decode image '{path}': ")
        raise ValueError(f"cannot decode image file {path}: {reason}") from exc
    img = img[None] if img.dim() == 2 else img
    channels, height, width = img.shape
    if height == 0 or width == 0:
        raise ValueError(f"image file {path} holds an empty image ({width} x {height} pixels)")
    _check_pixels(path, height, width, max_pixels)
    lut = None
    if palette is not None and channels == 1 and img.dtype == torch.uint8:  # the decoder gave the indices
        lut = torch.frombuffer(bytearray(palette), dtype=torch.uint8).view(-1, 3)
        if int(img.max()) >= lut.shape[0]:
            raise ValueError(f"image file {path} is not a valid PNG: a pixel uses palette entry {int(img.max())} "
                             f"of {lut.shape[0]}")
        channels = 3
    if channels not in (1, 3, 4):
        raise ValueError(f"image file {path} has {channels} channels; expected 1 (grey), 3 (RGB) or 4 (RGBA)")
    return img, lut


def _sample_scale(img: torch.Tensor, path: Path) -> float | None:
    """The value of white of the decoded samples (None: float32 already in [0, 1]), else the one-line error."""
    if img.dtype == torch.uint8:
        return 255.0
    if img.dtype == torch.uint16:
        return 65535.0
    if img.dtype != torch.float32:
        raise ValueError(f"image file {path} decodes to {img.dtype} samples; expected 8 or 16-bit integers or float32")
    lo, hi = (float(v) for v in torch.aminmax(img[:3]))
    if not (lo >= -1e-6 and hi <= 1 + 1e-6):  # warps round a hair past 0 and 1
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"image file {path} holds NaN or Inf values")
        raise ValueError(
            f"image file {path} holds float values in [{lo:g}, {hi:g}]; a float image must lie in "
            "[0, 1] (rescale it, or save it as 8 or 16-bit integers)"
        )
    return None


def _to_float(img: torch.Tensor, lut: torch.Tensor | None, scale: float | None, grey: bool) -> torch.Tensor:
    """(1, C, H, W) float32 in [0, 1], converted in strips of rows (memory: the input plus the result)."""
    _, height, width = img.shape
    colour = lut is not None or img.shape[0] >= 3
    out = torch.empty(1, 1 if (grey or not colour) else 3, height, width, dtype=torch.float32)
    rows = max(1, _CHUNK_PIXELS // width)
    for r0 in range(0, height, rows):
        part = img[:, r0 : r0 + rows]
        if lut is not None:
            part = lut[part[0].long()].permute(2, 0, 1)
        part = part[:3].float()  # drops alpha
        if scale is not None:
            part = part / scale
        if grey and colour:
            part = rgb_to_grayscale(part[None])[0]
        out[0, :, r0 : r0 + rows] = part
    return out


def scene_names() -> list[str]:
    """Names of the embedded CC0 scenes (see ``lensdist_torch/data/README.md``).

    Example:
        >>> scene_names()
        ['brick', 'grass', 'gravel']
    """
    return sorted(p.stem for p in _DATA.glob("*.png"))


def load_scene(name: str = "gravel") -> torch.Tensor:
    """An embedded scene as a (1, 1, 512, 512) float tensor in [0, 1].

    Example:
        >>> img = load_scene("gravel")
        >>> tuple(img.shape), img.dtype, 0 <= float(img.min()) <= float(img.max()) <= 1
        ((1, 1, 512, 512), torch.float32, True)
    """
    names = scene_names()
    if name not in names:
        raise ValueError(f"unknown scene {name!r}; embedded scenes are {names}")
    return load_image(_DATA / f"{name}.png", grey=True)


def centre_crop_box(h: int, w: int, height: int, width: int) -> tuple[int, int, int, int]:
    """(top, left, crop height, crop width) of the centred crop of an h x w image to height:width's aspect.

    The part of a user's image that :func:`resize_to` keeps (and the analysis sees).

    Example:
        >>> centre_crop_box(517, 389, 320, 424)
        (111, 0, 294, 389)
    """
    target = width / height
    if w / h > target:  # too wide: crop columns
        new_w = max(1, round(h * target))
        return 0, (w - new_w) // 2, h, new_w
    if w / h < target:
        new_h = max(1, round(w / target))
        return (h - new_h) // 2, 0, new_h, w
    return 0, 0, h, w


def resize_to(img: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Bring a (B, C, h, w) image to (height, width).

    A centre crop to the aspect ratio, then area resampling (antialiased bilinear). Used by entry
    points that take a user's photos.

    The crop is a view, and the antialiased resampling works in separable passes whose
    intermediates are about the size of the output (the figures: docs/method.md, section 1), so
    an image far larger than needed costs no memory beyond its own.

    Example:
        >>> row = torch.arange(10.0).view(1, 1, 1, 10)
        >>> resize_to(row, 1, 4).flatten().tolist()  # the centre crop is 1 x 4 already: no resampling
        [3.0, 4.0, 5.0, 6.0]
        >>> big = torch.full((1, 3, 90, 200), 0.5)  # cropped to 90 x 120, then resampled
        >>> out = resize_to(big, 30, 40)
        >>> tuple(out.shape), bool(torch.allclose(out, torch.full_like(out, 0.5)))
        ((1, 3, 30, 40), True)
    """
    top, left, ch, cw = centre_crop_box(img.shape[-2], img.shape[-1], height, width)
    img = img[..., top : top + ch, left : left + cw]
    if img.shape[-2:] == (height, width):
        return img
    return F.interpolate(img, size=(height, width), mode="bilinear", align_corners=False, antialias=True)
