"""Image file headers: the size (and a PNG's palette) read before decoding, for :mod:`.images`.

A small file that claims a huge image is refused from its header, before any decoder allocates
memory; content that does not match the suffix is named.
"""

from __future__ import annotations

import struct
from pathlib import Path

__all__ = ["read_header"]

_KIND_OF_SUFFIX = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".tif": "TIFF", ".tiff": "TIFF", ".webp": "WebP"}
_SUFFIX_OF_KIND = {"PNG": ".png", "JPEG": ".jpg", "TIFF": ".tif", "WebP": ".webp"}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (SOF0-SOF15 without DHT 0xC4, JPG 0xC8 and DAC 0xCC)
_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})


# (size, palette) of a file: (height, width) or None where the header does not say plainly; the
# PNG palette (PLTE) of a palette image, else None
_Header = tuple[tuple[int, int] | None, bytes | None]
_MAGIC = ((_PNG_SIGNATURE, "PNG"), (b"\xff\xd8\xff", "JPEG"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
          (b"II+\x00", "TIFF"), (b"MM\x00+", "TIFF"), (b"BM", "BMP"), (b"GIF8", "GIF"), (b"qoif", "QOI"))


def read_header(f, path: Path) -> _Header:
    """Parse the header of the format the suffix names; raise ``ValueError`` if it is not there."""
    head = f.read(32)
    if not head:
        raise ValueError(f"image file {path} is empty")
    expected = _KIND_OF_SUFFIX[path.suffix.lower()]
    kind = next((k for m, k in _MAGIC if head.startswith(m)), None)
    kind = "WebP" if head[:4] == b"RIFF" and head[8:12] == b"WEBP" else kind
    if kind != expected:
        held = f"it holds {kind} data" if kind else "it is not in a known image format"
        hint = f"; rename it to {_SUFFIX_OF_KIND[kind]}" if kind in _SUFFIX_OF_KIND else ""
        raise ValueError(f"image file {path} is not a {expected} file ({held}){hint}")
    truncated = ValueError(f"image file {path} is truncated: its {kind} header is incomplete")
    if kind == "PNG":
        return _png_header(f, head, path, truncated)
    if kind == "JPEG":
        return _jpeg_header(f, path, truncated)
    if kind == "TIFF":
        return _tiff_header(f, head, truncated)
    return _webp_header(head, path, truncated)


def _png_header(f, head: bytes, path: Path, truncated: ValueError) -> _Header:
    if len(head) < 26:
        raise truncated
    if head[12:16] != b"IHDR":
        raise ValueError(f"image file {path} is not a valid PNG: it does not start with an IHDR chunk")
    width, height = struct.unpack(">II", head[16:24])
    depth, colour = head[24], head[25]
    if width == 0 or height == 0:
        raise ValueError(f"image file {path} is not a valid PNG: its header gives {width} x {height} pixels")
    if colour == 4 or depth < 8:
        what, fix = ("a grey + alpha PNG", "grey, RGB or RGBA") if colour == 4 else (f"a {depth}-bit PNG", "8/16 bits")
        raise ValueError(f"image file {path} is {what}, which the decoder cannot read; save it as {fix}")
    if (colour, depth) not in {(0, 8), (0, 16), (2, 8), (2, 16), (3, 8), (6, 8), (6, 16)}:
        raise ValueError(f"image file {path} is not a valid PNG: colour type {colour} with {depth}-bit samples")
    palette = None
    if colour == 3:  # the palette precedes the image data
        f.seek(8)
        while True:
            chunk = f.read(8)
            if len(chunk) < 8:
                raise truncated
            length, name = struct.unpack(">I", chunk[:4])[0], chunk[4:]
            if name == b"PLTE":
                palette = f.read(length)
                if len(palette) < length:
                    raise truncated
                if length == 0 or length % 3:
                    raise ValueError(f"image file {path} is not a valid PNG: its palette has {length} bytes")
                break
            if name in (b"IDAT", b"IEND"):
                raise ValueError(f"image file {path} is not a valid PNG: a palette image without a palette")
            f.seek(length + 4, 1)  # body and CRC
    return (height, width), palette


def _jpeg_header(f, path: Path, truncated: ValueError) -> _Header:
    f.seek(2)
    while True:
        byte = f.read(1)
        if not byte:
            raise truncated
        if byte != b"\xff":
            raise ValueError(f"image file {path} is not a valid JPEG: no frame header before its data")
        code = f.read(1)
        while code == b"\xff":  # fill bytes
            code = f.read(1)
        if not code:
            raise truncated
        marker = code[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # no length field
            continue
        length = f.read(2)
        if len(length) < 2:
            raise truncated
        if marker in _JPEG_SOF:
            frame = f.read(6)  # precision, height, width, components
            if len(frame) < 6:
                raise truncated
            height, width = struct.unpack(">HH", frame[1:5])
            if frame[5] not in (1, 3):
                msg = f"is a JPEG with {frame[5]} colour components (CMYK?), which the decoder cannot read"
                raise ValueError(f"image file {path} {msg}; save it as grey or RGB")
            if width == 0:
                raise ValueError(f"image file {path} is not a valid JPEG: its frame header gives width 0")
            return ((height, width) if height else None), None  # height 0: set later (DNL)
        if marker in (0xD9, 0xDA):  # end of image, start of scan
            raise ValueError(f"image file {path} is not a valid JPEG: no frame header before its data")
        f.seek(struct.unpack(">H", length)[0] - 2, 1)


def _tiff_header(f, head: bytes, truncated: ValueError) -> _Header:
    """Width and height from the first IFD (classic and BigTIFF); None where they are not plain."""
    end = "<" if head[:2] == b"II" else ">"
    big = head[2:4] in (b"+\x00", b"\x00+")  # BigTIFF: 8-byte offsets and counts
    count_fmt, entry_size, value_size = ("Q", 20, 8) if big else ("H", 12, 4)
    if len(head) < (16 if big else 8):
        raise truncated
    f.seek(struct.unpack(end + "Q", head[8:16])[0] if big else struct.unpack(end + "I", head[4:8])[0])
    raw = f.read(struct.calcsize(count_fmt))
    if len(raw) < struct.calcsize(count_fmt):
        raise truncated
    n = struct.unpack(end + count_fmt, raw)[0]
    entries = f.read(min(n, 4096) * entry_size)
    dims: dict[int, int] = {}
    for i in range(len(entries) // entry_size):
        e = entries[i * entry_size : (i + 1) * entry_size]
        tag, typ = struct.unpack(end + "HH", e[:4])
        fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)  # SHORT, LONG, LONG8 (BigTIFF)
        if tag in (256, 257) and fmt is not None and struct.calcsize(fmt) <= value_size:
            value = e[entry_size - value_size :]  # left-justified in the value field
            dims[tag] = struct.unpack(end + fmt, value[: struct.calcsize(fmt)])[0]
    return ((dims[257], dims[256]) if 256 in dims and 257 in dims else None), None


def _webp_header(head: bytes, path: Path, truncated: ValueError) -> _Header:
    if len(head) < 30:
        raise truncated
    chunk = head[12:16]
    if chunk == b"VP8 " and head[23:26] == b"\x9d\x01\x2a":
        width, height = (v & 0x3FFF for v in struct.unpack("<HH", head[26:30]))
    elif chunk == b"VP8L" and head[20] == 0x2F:
        bits = struct.unpack("<I", head[21:25])[0]
        width, height = (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    elif chunk == b"VP8X":
        width = 1 + int.from_bytes(head[24:27], "little")
        height = 1 + int.from_bytes(head[27:30], "little")
    else:
        raise ValueError(f"image file {path} is not a valid WebP: unknown first chunk {chunk!r}")
    return (height, width), None
