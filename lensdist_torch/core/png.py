r"""The one PNG writer: 8- or 16-bit grey or RGB frames as PNG bytes (stdlib zlib), and the casts to it.

Example:
    >>> encode_png(to_uint8(torch.zeros(1, 2, 3)))[:4]
    b'\x89PNG'
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import torch

__all__ = ["encode_png", "to_uint8", "to_uint16", "deep_samples"]


def encode_png(img: torch.Tensor) -> bytes:
    r"""A (C, H, W) uint8 or uint16 tensor (C = 1 grey, 3 RGB) as PNG bytes (8 or 16 bits a sample).

    stdlib zlib, the 'Sub' filter on every row.

    Example:
        >>> encode_png(torch.zeros(1, 2, 3, dtype=torch.uint8))[:8]
        b'\x89PNG\r\n\x1a\n'
        >>> encode_png(torch.zeros(3, 2, 3, dtype=torch.uint16))[24]  # the IHDR's bit depth
        16
    """
    if not (isinstance(img, torch.Tensor) and img.dtype in (torch.uint8, torch.uint16) and img.dim() == 3
            and img.shape[0] in (1, 3)):
        raise ValueError("img must be a (C, H, W) uint8 or uint16 tensor with C = 1 or 3")
    c, h, w = img.shape
    rows = img.permute(1, 2, 0).contiguous()
    depth, bpp = (8, c) if img.dtype == torch.uint8 else (16, 2 * c)
    if depth == 16:  # big-endian bytes
        wide = rows.to(torch.int32)
        rows = torch.stack([(wide >> 8).to(torch.uint8), (wide & 255).to(torch.uint8)], -1)
    rows = rows.reshape(h, w * bpp)
    sub = rows.clone()
    sub[:, bpp:] = rows[:, bpp:] - rows[:, :-bpp]  # uint8 arithmetic wraps modulo 256, as PNG's filter
    raw = torch.cat([torch.ones(h, 1, dtype=torch.uint8), sub], 1).numpy().tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, depth, 0 if c == 1 else 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


def to_uint8(x: torch.Tensor) -> torch.Tensor:
    """Float in [0, 1] (clamped) -> uint8, rounded to the nearest of 256 levels.

    Example:
        >>> to_uint8(torch.tensor([-0.1, 0.5, 1.2])).tolist()
        [0, 128, 255]
    """
    return (x.clamp(0, 1) * 255).round().to(torch.uint8)


def to_uint16(x: torch.Tensor) -> torch.Tensor:
    """Float in [0, 1] (clamped) -> uint16, rounded to the nearest of 65,536 levels.

    Example:
        >>> to_uint16(torch.tensor([0.0, 1.0])).tolist()
        [0, 65535]
    """
    return (x.clamp(0, 1) * 65535).round().to(torch.uint16)


def deep_samples(source: Path | None, img: torch.Tensor) -> bool:
    """Whether a frame read from ``source`` (None: a video) has more than 8 bits a sample.

    Example:
        >>> deep_samples(None, torch.zeros(1, 1, 2, 2))  # a video's frames are 8-bit
        False
    """
    if source is None:
        return False
    suffix = source.suffix.lower()
    if suffix == ".png":
        with source.open("rb") as f:
            return f.read(25)[24:25] == b"\x10"  # the IHDR's bit depth (load_image checked the header)
    if suffix in (".tif", ".tiff"):  # 16-bit or float samples: off the 8-bit grid somewhere
        return bool(((img * 255 - (img * 255).round()).abs() > 1e-3).any())
    return False  # JPEG, WebP: 8 bits
