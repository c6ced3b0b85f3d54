"""Bad image files and tensors end in a one-line error naming the file or the argument, never in a
wrong image (lensdist_torch/core/images.py). Files are written with a minimal PNG writer (zlib)
and kornia's writers; PIL, where installed, only adds the formats kornia cannot write."""

from __future__ import annotations

import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.io import write_image
from one_line import one_line_error

from lensdist_torch import quality_map
from lensdist_torch.core import images
from lensdist_torch.core.images import (
    IMAGE_SUFFIXES,
    MAX_PIXELS,
    as_batch,
    check_image,
    load_image,
    resize_to,
)

# ----------------------------------------------------------------------------- file writers


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png_bytes(
    rows: np.ndarray, colour: int, depth: int, *, size=None, extra: bytes = b"", interlace: int = 0
) -> bytes:
    """A PNG of the pixels ``rows`` ((H, W) or (H, W, C); big-endian ``>u2`` for 16 bits; packed
    bytes with an explicit ``size`` below 8 bits), filter 0 on every row."""
    if interlace:  # Adam7: the seven passes one after the other
        raw = b""
        for x0, y0, dx, dy in (
            (0, 0, 8, 8),
            (4, 0, 8, 8),
            (0, 4, 4, 8),
            (2, 0, 4, 4),
            (0, 2, 2, 4),
            (1, 0, 2, 2),
            (0, 1, 1, 2),
        ):
            sub = rows[y0::dy, x0::dx]
            if sub.size:
                raw += b"".join(b"\x00" + r.tobytes() for r in sub)
    else:
        raw = b"".join(b"\x00" + r.tobytes() for r in rows)
    h, w = size if size is not None else rows.shape[:2]
    ihdr = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, interlace)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", ihdr)
        + extra
        + _chunk(b"IDAT", zlib.compress(raw))
        + _chunk(b"IEND", b"")
    )


def _rand_u8(*shape, seed=0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def _tensor(arr: np.ndarray) -> torch.Tensor:
    """(H, W) or (H, W, C) array -> (1, C, H, W) float32 tensor of its values."""
    t = torch.from_numpy(arr.astype(np.float32))
    t = t[..., None] if t.dim() == 2 else t
    return t.permute(2, 0, 1)[None]




@pytest.fixture
def rgb_png(tmp_path):
    path = tmp_path / "rgb.png"
    path.write_bytes(_png_bytes(_rand_u8(12, 16, 3), 2, 8))
    return path


@pytest.fixture
def no_decoder(monkeypatch):
    """Make kornia's decoder fail loudly: a refusal must come from the header, before decoding."""
    import kornia.io

    def boom(*args, **kwargs):
        raise AssertionError("the decoder was called")

    monkeypatch.setattr(kornia.io, "load_image", boom)


# ----------------------------------------------------------------------------- what loads, and how


class TestFormats:
    def test_the_suffix_set(self):
        assert IMAGE_SUFFIXES == {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp"}
        assert all(s == s.lower() and s.startswith(".") for s in IMAGE_SUFFIXES)
        assert MAX_PIXELS == 100_000_000

    def test_every_suffix_loads(self, tmp_path):
        u8 = torch.from_numpy(_rand_u8(3, 12, 16))
        for suffix in sorted(IMAGE_SUFFIXES - {".webp"}) + [".PNG", ".JPG", ".TIFF"]:
            path = tmp_path / f"img{suffix}"
            write_image(path, u8, quality=100)
            img = load_image(path, grey=False)
            assert img.shape == (1, 3, 12, 16) and img.dtype == torch.float32
            if suffix.lower() in (".png", ".tif", ".tiff"):  # lossless
                assert torch.equal(img, u8.float()[None] / 255)

    def test_webp(self, tmp_path):
        pil = pytest.importorskip("PIL.Image")
        arr = _rand_u8(12, 16, 3)
        pil.fromarray(arr).save(tmp_path / "a.webp", lossless=True)
        assert torch.equal(load_image(tmp_path / "a.webp", grey=False), _tensor(arr) / 255)
        rgba = _rand_u8(12, 16, 4)
        rgba[..., 3] = np.maximum(rgba[..., 3], 1)  # fully transparent pixels may lose their colour
        pil.fromarray(rgba).save(tmp_path / "rgba.webp", lossless=True, exact=True)
        assert torch.equal(load_image(tmp_path / "rgba.webp", grey=False), _tensor(rgba[..., :3]) / 255)

    def test_the_decoder_refuses_what_is_not_listed(self, tmp_path):
        """BMP, GIF, PNM, TGA: kornia's decoder cannot read them (so --scenes must not list them)."""
        pil = pytest.importorskip("PIL.Image")
        import kornia.io

        arr = _rand_u8(8, 8, 3)
        for suffix in (".bmp", ".gif", ".ppm", ".tga"):
            path = tmp_path / f"img{suffix}"
            pil.fromarray(arr).save(path)
            with pytest.raises(ValueError):
                kornia.io.load_image(path, kornia.io.ImageLoadType.UNCHANGED)
            one_line_error(ValueError, lambda p=path: load_image(p), str(path), suffix, ".png")

    def test_grey_rgb_rgba_png(self, tmp_path):
        grey = _rand_u8(6, 10)
        (tmp_path / "g.png").write_bytes(_png_bytes(grey, 0, 8))
        assert torch.equal(load_image(tmp_path / "g.png"), _tensor(grey) / 255)
        rgba = _rand_u8(6, 10, 4)
        (tmp_path / "a.png").write_bytes(_png_bytes(rgba, 6, 8))
        colour = _tensor(rgba[..., :3]) / 255  # alpha dropped, colours as stored
        assert torch.equal(load_image(tmp_path / "a.png", grey=False), colour)
        assert torch.equal(load_image(tmp_path / "a.png"), rgb_to_grayscale(colour))

    def test_16_bit_png_is_divided_by_65535(self, tmp_path):
        g = np.random.default_rng(1).integers(0, 65536, (6, 10)).astype(">u2")
        g[0, 0], g[0, 1] = 0, 65535
        (tmp_path / "g16.png").write_bytes(_png_bytes(g, 0, 16))
        out = load_image(tmp_path / "g16.png")
        assert torch.equal(out, _tensor(g.astype(np.uint16)) / 65535.0)
        assert float(out[0, 0, 0, 0]) == 0.0 and float(out[0, 0, 0, 1]) == 1.0
        rgba = np.random.default_rng(2).integers(0, 65536, (5, 7, 4)).astype(">u2")
        (tmp_path / "a16.png").write_bytes(_png_bytes(rgba, 6, 16))
        want = _tensor(rgba[..., :3].astype(np.uint16)) / 65535.0
        assert torch.equal(load_image(tmp_path / "a16.png", grey=False), want)

    def test_16_bit_tiff(self, tmp_path):
        u16 = torch.from_numpy(np.random.default_rng(3).integers(0, 65536, (1, 6, 10)).astype(np.uint16))
        write_image(tmp_path / "g16.tif", u16)
        assert torch.equal(load_image(tmp_path / "g16.tif"), u16.float()[None] / 65535.0)

    def test_float_tiff_in_range_is_kept(self, tmp_path):
        x = torch.rand(1, 6, 10, generator=torch.Generator().manual_seed(0))
        x[0, 0, :2] = torch.tensor([0.0, 1.0])
        write_image(tmp_path / "f.tif", x)
        assert torch.equal(load_image(tmp_path / "f.tif"), x[None])

    def test_palette_png_is_its_colours(self, tmp_path):
        palette = _rand_u8(5, 3, seed=4)
        idx = np.random.default_rng(5).integers(0, 5, (6, 10)).astype(np.uint8)
        (tmp_path / "p.png").write_bytes(_png_bytes(idx, 3, 8, extra=_chunk(b"PLTE", palette.tobytes())))
        colours = _tensor(palette[idx]) / 255
        assert torch.equal(load_image(tmp_path / "p.png", grey=False), colours)
        assert torch.equal(load_image(tmp_path / "p.png"), rgb_to_grayscale(colours))

    def test_interlaced_png(self, tmp_path):
        arr = _rand_u8(13, 17, 3, seed=6)
        (tmp_path / "i.png").write_bytes(_png_bytes(arr, 2, 8, interlace=1))
        assert torch.equal(load_image(tmp_path / "i.png", grey=False), _tensor(arr) / 255)

    def test_grey_jpeg_has_one_channel(self, tmp_path):
        write_image(tmp_path / "g.jpg", torch.from_numpy(_rand_u8(1, 16, 16)), quality=95)
        assert load_image(tmp_path / "g.jpg", grey=False).shape == (1, 1, 16, 16)

    def test_conversion_in_strips_changes_nothing(self, tmp_path, monkeypatch):
        rgb = torch.from_numpy(_rand_u8(3, 37, 29, seed=7))
        write_image(tmp_path / "c.png", rgb)
        whole = rgb.float()[None] / 255
        monkeypatch.setattr(images, "_CHUNK_PIXELS", 100)  # 3 rows a strip, a short last strip
        assert torch.equal(load_image(tmp_path / "c.png", grey=False), whole)
        assert torch.equal(load_image(tmp_path / "c.png"), rgb_to_grayscale(whole))

    def test_size_limit_is_adjustable(self, rgb_png):
        assert load_image(rgb_png, max_pixels=12 * 16).shape == (1, 1, 12, 16)
        assert load_image(rgb_png, max_pixels=None).shape == (1, 1, 12, 16)


class TestResize:
    def test_large_image_matches_the_antialiased_reference(self):
        """A 2000 x 3000 photo: the result is within 1/255 of an independent float64 area-weighted
        (triangle filter) resampling of the centre crop."""
        g = torch.Generator().manual_seed(0)
        base = torch.rand(1, 1, 250, 375, generator=g)
        img = (F.interpolate(base, size=(2000, 3000), mode="bilinear", align_corners=False)
               + 0.1 * torch.rand(1, 1, 2000, 3000, generator=g)).clamp(0, 1)
        out = resize_to(img, 320, 424)
        assert out.shape == (1, 1, 320, 424)
        crop_w = round(2000 * 424 / 320)  # 2650 columns, centred
        x0 = (3000 - crop_w) // 2
        crop = img[0, 0, :, x0 : x0 + crop_w].double()

        def weights(n: int, m: int) -> torch.Tensor:
            scale = n / m
            centre = (torch.arange(m, dtype=torch.float64) + 0.5) * scale
            pos = torch.arange(n, dtype=torch.float64) + 0.5
            w = (1 - (pos[None] - centre[:, None]).abs() / scale).clamp_min(0)
            return w / w.sum(1, keepdim=True)

        ref = weights(2000, 320)[::4] @ crop @ weights(crop_w, 424).T  # every 4th row: enough, and fast
        assert float((out[0, 0, ::4].double() - ref).abs().max()) < 1 / 255


# ----------------------------------------------------------------------------- bad files


def bad_file(
    case_id: str, make, *words: str, exc=ValueError, names_path: bool = True, header_only: bool = False, **kwargs
):
    """One case of BAD_FILES: ``make(tmp_path, rgb_png)`` writes the bad file and gives its path;
    ``load_image(path, **kwargs)`` must raise ``exc`` with one line holding the path (unless not
    ``names_path``) and every one of ``words``. ``header_only``: refused from the header, before
    decoding (kornia's decoder fails loudly)."""
    return pytest.param(make, kwargs, exc, words, names_path, header_only, id=case_id)


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _kornia(path: Path, img: torch.Tensor, **kwargs) -> Path:
    write_image(path, img, **kwargs)
    return path


def _directory(tmp_path, _):
    folder = tmp_path / "shots.png"
    folder.mkdir()
    return folder


def _fifo(tmp_path, _):
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    path = tmp_path / "pipe.png"
    os.mkfifo(path)
    return path  # loading it must not block on opening it


def _jpeg_named_tif(tmp_path, _):
    jpeg = _kornia(tmp_path / "a.jpg", torch.from_numpy(_rand_u8(3, 8, 8)))
    return _write(tmp_path / "a.tif", jpeg.read_bytes())


def _truncated(suffix: str, keep: float):
    def make(tmp_path, _):
        full = _kornia(tmp_path / f"full{suffix}", torch.from_numpy(_rand_u8(3, 64, 80, seed=8)), quality=90)
        data = full.read_bytes()
        return _write(tmp_path / f"cut{suffix}", data[: int(len(data) * keep)])

    return make


def _corrupt_png(tmp_path, rgb_png):
    data = bytearray(rgb_png.read_bytes())
    data[60] ^= 0xFF  # inside the compressed image data: its CRC no longer matches
    return _write(tmp_path / "corrupt.png", bytes(data))


def _png_bomb(tmp_path, _):
    """A few hundred bytes whose header asks for 100000 x 100000 pixels (40 GB as float)."""
    path = _write(tmp_path / "bomb.png", _png_bytes(np.zeros((1, 1), np.uint8), 0, 8, size=(100_000, 100_000)))
    assert path.stat().st_size < 1000
    return path


def _huge_jpeg(tmp_path, _):
    exif = b"\xff\xe1" + struct.pack(">H", 2 + 3000) + b"\x00" * 3000  # a big segment before the frame
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, 20000, 30000, 3) + b"\x01\x22\x00\x02\x11\x01\x03\x11\x01"
    return _write(tmp_path / "huge.jpg", b"\xff\xd8" + exif + sof + b"\xff\xda" + b"\x00" * 20)


def _huge_webp(tmp_path, _):
    bits = (16384 - 1) | ((16384 - 1) << 14)  # lossless: 14-bit width - 1 and height - 1
    body = b"VP8L" + struct.pack("<I", 5) + b"\x2f" + struct.pack("<I", bits) + b"\x00" * 8
    return _write(tmp_path / "huge.webp", b"RIFF" + struct.pack("<I", 4 + len(body)) + b"WEBP" + body)


def _cmyk_jpeg(tmp_path, _):
    pil = pytest.importorskip("PIL.Image")
    path = tmp_path / "cmyk.jpg"
    pil.fromarray(_rand_u8(8, 8, 3)).convert("CMYK").save(path)
    return path


def _float_tiff_with_nan(tmp_path, _):
    x = torch.rand(1, 6, 10)
    x[0, 2, 3] = math.nan
    return _kornia(tmp_path / "nan.tif", x)


BAD_FILES = [
    *(
        bad_file(f"unsupported_suffix-{s or 'none'}", lambda t, rgb, s=s: _write(t / f"photo{s}", rgb.read_bytes()),
                 "suffix")
        for s in (".bmp", ".gif", ".pgm", ".heic", "")
    ),
    bad_file("directory", _directory, "directory"),
    bad_file("not_a_regular_file", _fifo, "not a regular file"),
    bad_file("missing_file_keeps_its_type", lambda t, _: t / "missing.png", "missing.png", exc=FileNotFoundError,
             names_path=False),
    *(bad_file(f"empty_file-{s}", lambda t, _, s=s: _write(t / f"empty{s}", b""), "empty")
      for s in (".png", ".jpg", ".tif", ".webp")),
    bad_file("text_file_named_png", lambda t, _: _write(t / "notes.png", b"this is not an image\n"), "not a PNG"),
    bad_file("png_named_jpg", lambda t, rgb: _write(t / "photo.jpg", rgb.read_bytes()), "PNG data", ".png"),
    bad_file("jpeg_named_tif", _jpeg_named_tif, "JPEG data"),
    *(bad_file(f"truncated_file-{s}-{keep}", _truncated(s, keep))
      for keep in (0.5, 0.9) for s in (".png", ".jpg", ".tif")),
    bad_file("png_signature_only", lambda t, _: _write(t / "sig.png", b"\x89PNG\r\n\x1a\n\x00\x00"), "truncated"),
    bad_file("corrupt_png_data", _corrupt_png),
    # pixel bombs and limits: refused from the header
    bad_file("png_pixel_bomb", _png_bomb, "100000 x 100000", "max_pixels=100000000", header_only=True),
    bad_file("png_over_a_custom_limit", lambda t, rgb: rgb, "16 x 12", "max_pixels=100", header_only=True,
             max_pixels=100),
    bad_file("jpeg_over_the_limit_from_its_frame_header", _huge_jpeg, "30000 x 20000", header_only=True),
    bad_file("tiff_over_a_custom_limit", lambda t, _: _kornia(t / "a.tif", torch.from_numpy(_rand_u8(3, 40, 50))),
             "50 x 40", header_only=True, max_pixels=1999),
    bad_file("webp_over_the_limit_from_its_header", _huge_webp, "16384 x 16384", header_only=True),
    bad_file("webp_with_an_unknown_chunk",
             lambda t, _: _write(t / "odd.webp", b"RIFF" + struct.pack("<I", 30) + b"WEBP" + b"ABCD" + b"\x00" * 22),
             "WebP"),
    # pixel formats that are not loaded
    bad_file("grey_alpha_png", lambda t, _: _write(t / "la.png", _png_bytes(_rand_u8(6, 10, 2), 4, 8)), "grey + alpha"),
    *(
        bad_file(f"png_with_fewer_than_8_bits-{d}",
                 lambda t, _, d=d: _write(t / f"g{d}.png", _png_bytes(_rand_u8(6, 2), 0, d, size=(6, 16 // d))),
                 f"{d}-bit")
        for d in (1, 2, 4)
    ),
    bad_file("png_of_zero_width",
             lambda t, _: _write(t / "zero.png", _png_bytes(np.zeros((1, 1), np.uint8), 0, 8, size=(1, 0))), "0 x 1"),
    bad_file("palette_png_without_a_palette", lambda t, _: _write(t / "nopal.png", _png_bytes(_rand_u8(6, 10), 3, 8)),
             "palette"),
    bad_file("palette_index_beyond_the_palette",  # index 9; the palette has 4 entries
             lambda t, _: _write(t / "badidx.png", _png_bytes(np.full((6, 10), 9, np.uint8), 3, 8,
                                                               extra=_chunk(b"PLTE", _rand_u8(4, 3).tobytes()))),
             "palette entry 9"),
    bad_file("cmyk_jpeg", _cmyk_jpeg, "4 colour components"),
    bad_file("jpeg_without_a_frame_header",
             lambda t, _: _write(t / "noframe.jpg",
                                 b"\xff\xd8\xff\xe0" + struct.pack(">H", 4) + b"JF" + b"\xff\xda" + b"\x00" * 16),
             "frame header"),
    bad_file("float_tiff_outside_0_1",
             lambda t, _: _kornia(t / "hdr.tif", torch.linspace(-3.0, 250.0, 60).view(1, 6, 10)),
             "[-3, 250]", "[0, 1]"),
    bad_file("float_tiff_with_nan", _float_tiff_with_nan, "NaN"),
    *(bad_file(f"bad_max_pixels-{limit}", lambda t, rgb: rgb, "max_pixels", names_path=False, max_pixels=limit)
      for limit in (0, -5, 2.5, True)),
]


@pytest.mark.bad_input
@pytest.mark.parametrize(("make", "kwargs", "exc", "words", "names_path", "header_only"), BAD_FILES)
def test_bad_file(tmp_path, rgb_png, request, make, kwargs, exc, words, names_path, header_only):
    if header_only:
        request.getfixturevalue("no_decoder")
    path = make(tmp_path, rgb_png)
    one_line_error(exc, lambda: load_image(path, **kwargs), *((str(path),) if names_path else ()), *words)


@pytest.mark.bad_input
def test_unreadable_file(tmp_path, rgb_png):
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        pytest.skip("root reads files without read permission")
    rgb_png.chmod(0)
    try:
        one_line_error(ValueError, lambda: load_image(rgb_png), str(rgb_png))
    finally:
        rgb_png.chmod(0o644)


# ----------------------------------------------------------------------------- bad tensors


def _quality_map_with_valid(shape, dtype, at, value):
    """quality_map of a random image with itself, under a mask of ones holding ``value`` at ``at``."""
    like = torch.rand(shape, dtype=dtype)
    valid = torch.ones(shape, dtype=dtype)
    valid[at] = value
    return quality_map(like, like, valid=valid)


def _photo_with_inf():
    x = torch.rand(3, 8, 8)
    x[1, 2, 2] = math.inf
    return check_image(as_batch(x, "photo"), "photo")


# (case id, the call, its error, the words of its one line); the validity mask is checked where it
# is used: by the metric's entry points (metric/_inputs.py)
BAD_TENSORS = [
    *(
        pytest.param(lambda b=bad: _quality_map_with_valid((2, 1, 16, 16), torch.float32, (1, 0, 3, 4), b),
                     ValueError, ("valid", "NaN or Inf"), id=f"valid_mask_not_finite-{bad}")
        for bad in (math.nan, math.inf, -math.inf)
    ),
    *(
        pytest.param(lambda b=bad: _quality_map_with_valid((1, 1, 16, 16), torch.float64, (0, 0, 0, 0), b),
                     ValueError, ("valid", "[0, 1]"), id=f"valid_mask_out_of_range-{bad}")
        for bad in (-0.5, 2.0)
    ),
    pytest.param(
        lambda: quality_map(torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 16),
                            valid=torch.ones(1, 1, 16, 16, dtype=torch.complex64)),
        TypeError, ("valid",), id="valid_mask_complex",
    ),
    pytest.param(_photo_with_inf, ValueError, ("photo", "NaN or Inf"), id="image_with_inf_through_as_batch"),
    pytest.param(lambda: as_batch(torch.rand(8), "photo"), ValueError, ("photo", "(H, W)"),
                 id="as_batch_of_a_1d_tensor"),
]


@pytest.mark.bad_input
@pytest.mark.parametrize(("call", "exc", "words"), BAD_TENSORS)
def test_bad_tensor(call, exc, words):
    one_line_error(exc, call, *words)


def test_valid_masks_that_are_fine():
    like = torch.rand(1, 1, 16, 16)
    ones = quality_map(like, like, valid=torch.ones(1, 1, 16, 16, dtype=torch.uint8))
    assert torch.equal(ones, quality_map(like, like, valid=torch.ones(1, 1, 16, 16, dtype=torch.bool)))
    assert torch.equal(ones, quality_map(like, like))  # all valid = no mask
