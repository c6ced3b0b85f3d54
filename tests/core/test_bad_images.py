"""Bad image files and tensors end in a one-line error naming the file or the argument, never in a
wrong image (lensdist_torch/core/images.py). Files are written with a minimal PNG writer (zlib)
and kornia's writers; PIL, where installed, only adds the formats kornia cannot write."""

from __future__ import annotations

import math
import os
import struct
import zlib

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from kornia.io import write_image
from one_line import one_line

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


def _png_bytes(rows: np.ndarray, colour: int, depth: int, *, size=None, extra: bytes = b"", interlace: int = 0) -> bytes:
    """A PNG of the pixels ``rows`` ((H, W) or (H, W, C); big-endian ``>u2`` for 16 bits; packed
    bytes with an explicit ``size`` below 8 bits), filter 0 on every row."""
    if interlace:  # Adam7: the seven passes one after the other
        raw = b""
        for x0, y0, dx, dy in ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)):
            sub = rows[y0::dy, x0::dx]
            if sub.size:
                raw += b"".join(b"\x00" + r.tobytes() for r in sub)
    else:
        raw = b"".join(b"\x00" + r.tobytes() for r in rows)
    h, w = size if size is not None else rows.shape[:2]
    ihdr = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, interlace)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


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
            with pytest.raises(ValueError) as info:
                load_image(path)
            one_line(info, str(path), suffix, ".png")

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


@pytest.mark.bad_input
@pytest.mark.parametrize("suffix", [".bmp", ".gif", ".pgm", ".heic", ""])
def test_unsupported_suffix(tmp_path, rgb_png, suffix):
    path = tmp_path / f"photo{suffix}"
    path.write_bytes(rgb_png.read_bytes())
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "suffix")


@pytest.mark.bad_input
def test_directory(tmp_path):
    folder = tmp_path / "shots.png"
    folder.mkdir()
    with pytest.raises(ValueError) as info:
        load_image(folder)
    one_line(info, str(folder), "directory")


@pytest.mark.bad_input
def test_not_a_regular_file(tmp_path):
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    path = tmp_path / "pipe.png"
    os.mkfifo(path)
    with pytest.raises(ValueError) as info:
        load_image(path)  # must not block on opening it
    one_line(info, str(path), "not a regular file")


@pytest.mark.bad_input
def test_missing_file_keeps_its_type(tmp_path):
    with pytest.raises(FileNotFoundError) as info:
        load_image(tmp_path / "missing.png")
    one_line(info, "missing.png")


@pytest.mark.bad_input
def test_unreadable_file(tmp_path, rgb_png):
    if hasattr(os, "geteuid") and os.geteuid() == 0:
        pytest.skip("root reads files without read permission")
    rgb_png.chmod(0)
    try:
        with pytest.raises(ValueError) as info:
            load_image(rgb_png)
        one_line(info, str(rgb_png))
    finally:
        rgb_png.chmod(0o644)


@pytest.mark.bad_input
@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif", ".webp"])
def test_empty_file(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "empty")


@pytest.mark.bad_input
def test_text_file_named_png(tmp_path):
    path = tmp_path / "notes.png"
    path.write_text("this is not an image\n")
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "not a PNG")


@pytest.mark.bad_input
def test_png_named_jpg(tmp_path, rgb_png):
    path = tmp_path / "photo.jpg"
    path.write_bytes(rgb_png.read_bytes())
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "PNG data", ".png")


@pytest.mark.bad_input
def test_jpeg_named_tif(tmp_path):
    write_image(tmp_path / "a.jpg", torch.from_numpy(_rand_u8(3, 8, 8)))
    path = tmp_path / "a.tif"
    path.write_bytes((tmp_path / "a.jpg").read_bytes())
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "JPEG data")


@pytest.mark.bad_input
@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif"])
@pytest.mark.parametrize("keep", [0.5, 0.9])
def test_truncated_file(tmp_path, suffix, keep):
    full = tmp_path / f"full{suffix}"
    write_image(full, torch.from_numpy(_rand_u8(3, 64, 80, seed=8)), quality=90)
    data = full.read_bytes()
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path))


@pytest.mark.bad_input
def test_png_signature_only(tmp_path):
    path = tmp_path / "sig.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "truncated")


@pytest.mark.bad_input
def test_corrupt_png_data(tmp_path, rgb_png):
    data = bytearray(rgb_png.read_bytes())
    data[60] ^= 0xFF  # inside the compressed image data: its CRC no longer matches
    path = tmp_path / "corrupt.png"
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path))


@pytest.mark.bad_input
def test_png_pixel_bomb_is_refused_before_decoding(tmp_path, no_decoder):
    """A few hundred bytes whose header asks for 100000 x 100000 pixels (40 GB as float)."""
    path = tmp_path / "bomb.png"
    path.write_bytes(_png_bytes(np.zeros((1, 1), np.uint8), 0, 8, size=(100_000, 100_000)))
    assert path.stat().st_size < 1000
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "100000 x 100000", "max_pixels=100000000")


@pytest.mark.bad_input
def test_png_over_a_custom_limit(rgb_png, no_decoder):
    with pytest.raises(ValueError) as info:
        load_image(rgb_png, max_pixels=100)
    one_line(info, str(rgb_png), "16 x 12", "max_pixels=100")


@pytest.mark.bad_input
def test_jpeg_over_the_limit_from_its_frame_header(tmp_path, no_decoder):
    exif = b"\xff\xe1" + struct.pack(">H", 2 + 3000) + b"\x00" * 3000  # a big segment before the frame
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, 20000, 30000, 3) + b"\x01\x22\x00\x02\x11\x01\x03\x11\x01"
    path = tmp_path / "huge.jpg"
    path.write_bytes(b"\xff\xd8" + exif + sof + b"\xff\xda" + b"\x00" * 20)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "30000 x 20000")


@pytest.mark.bad_input
def test_tiff_over_a_custom_limit(tmp_path, no_decoder):
    path = tmp_path / "a.tif"
    import kornia.io as kio  # the real writer (the fixture only replaced the loader)

    kio.write_image(path, torch.from_numpy(_rand_u8(3, 40, 50)))
    with pytest.raises(ValueError) as info:
        load_image(path, max_pixels=1999)
    one_line(info, str(path), "50 x 40")


@pytest.mark.bad_input
def test_webp_over_the_limit_from_its_header(tmp_path, no_decoder):
    bits = (16384 - 1) | ((16384 - 1) << 14)  # lossless: 14-bit width - 1 and height - 1
    body = b"VP8L" + struct.pack("<I", 5) + b"\x2f" + struct.pack("<I", bits) + b"\x00" * 8
    path = tmp_path / "huge.webp"
    path.write_bytes(b"RIFF" + struct.pack("<I", 4 + len(body)) + b"WEBP" + body)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "16384 x 16384")


@pytest.mark.bad_input
def test_webp_with_an_unknown_chunk(tmp_path):
    path = tmp_path / "odd.webp"
    path.write_bytes(b"RIFF" + struct.pack("<I", 30) + b"WEBP" + b"ABCD" + b"\x00" * 22)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "WebP")


@pytest.mark.bad_input
def test_grey_alpha_png(tmp_path):
    path = tmp_path / "la.png"
    path.write_bytes(_png_bytes(_rand_u8(6, 10, 2), 4, 8))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "grey + alpha")


@pytest.mark.bad_input
@pytest.mark.parametrize("depth", [1, 2, 4])
def test_png_with_fewer_than_8_bits(tmp_path, depth):
    path = tmp_path / f"g{depth}.png"
    path.write_bytes(_png_bytes(_rand_u8(6, 2), 0, depth, size=(6, 16 // depth)))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), f"{depth}-bit")


@pytest.mark.bad_input
def test_png_of_zero_width(tmp_path):
    path = tmp_path / "zero.png"
    path.write_bytes(_png_bytes(np.zeros((1, 1), np.uint8), 0, 8, size=(1, 0)))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "0 x 1")


@pytest.mark.bad_input
def test_palette_png_without_a_palette(tmp_path):
    path = tmp_path / "nopal.png"
    path.write_bytes(_png_bytes(_rand_u8(6, 10), 3, 8))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "palette")


@pytest.mark.bad_input
def test_palette_index_beyond_the_palette(tmp_path):
    idx = np.full((6, 10), 9, np.uint8)  # the palette has 4 entries
    path = tmp_path / "badidx.png"
    path.write_bytes(_png_bytes(idx, 3, 8, extra=_chunk(b"PLTE", _rand_u8(4, 3).tobytes())))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "palette entry 9")


@pytest.mark.bad_input
def test_cmyk_jpeg(tmp_path):
    pil = pytest.importorskip("PIL.Image")
    path = tmp_path / "cmyk.jpg"
    pil.fromarray(_rand_u8(8, 8, 3)).convert("CMYK").save(path)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "4 colour components")


@pytest.mark.bad_input
def test_jpeg_without_a_frame_header(tmp_path):
    path = tmp_path / "noframe.jpg"
    path.write_bytes(b"\xff\xd8\xff\xe0" + struct.pack(">H", 4) + b"JF" + b"\xff\xda" + b"\x00" * 16)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "frame header")


@pytest.mark.bad_input
def test_float_tiff_outside_0_1(tmp_path):
    path = tmp_path / "hdr.tif"
    write_image(path, torch.linspace(-3.0, 250.0, 60).view(1, 6, 10))
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "[-3, 250]", "[0, 1]")


@pytest.mark.bad_input
def test_float_tiff_with_nan(tmp_path):
    x = torch.rand(1, 6, 10)
    x[0, 2, 3] = math.nan
    path = tmp_path / "nan.tif"
    write_image(path, x)
    with pytest.raises(ValueError) as info:
        load_image(path)
    one_line(info, str(path), "NaN")


@pytest.mark.bad_input
@pytest.mark.parametrize("limit", [0, -5, 2.5, True])
def test_bad_max_pixels(rgb_png, limit):
    with pytest.raises(ValueError) as info:
        load_image(rgb_png, max_pixels=limit)
    one_line(info, "max_pixels")


# ----------------------------------------------------------------------------- bad tensors


# the validity mask is checked where it is used: by the metric's entry points (metric/_inputs.py)
@pytest.mark.bad_input
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_valid_mask_not_finite(bad):
    like = torch.rand(2, 1, 16, 16)
    valid = torch.ones(2, 1, 16, 16)
    valid[1, 0, 3, 4] = bad
    with pytest.raises(ValueError) as info:
        quality_map(like, like, valid=valid)
    one_line(info, "valid", "NaN or Inf")


@pytest.mark.bad_input
@pytest.mark.parametrize("bad", [-0.5, 2.0])
def test_valid_mask_out_of_range(bad):
    like = torch.rand(1, 1, 16, 16, dtype=torch.float64)
    valid = torch.ones(1, 1, 16, 16, dtype=torch.float64)
    valid[0, 0, 0, 0] = bad
    with pytest.raises(ValueError) as info:
        quality_map(like, like, valid=valid)
    one_line(info, "valid", "[0, 1]")


@pytest.mark.bad_input
def test_valid_mask_complex():
    with pytest.raises(TypeError) as info:
        quality_map(torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 16), valid=torch.ones(1, 1, 16, 16, dtype=torch.complex64))
    one_line(info, "valid")


def test_valid_masks_that_are_fine():
    like = torch.rand(1, 1, 16, 16)
    ones = quality_map(like, like, valid=torch.ones(1, 1, 16, 16, dtype=torch.uint8))
    assert torch.equal(ones, quality_map(like, like, valid=torch.ones(1, 1, 16, 16, dtype=torch.bool)))
    assert torch.equal(ones, quality_map(like, like))  # all valid = no mask


@pytest.mark.bad_input
def test_image_with_inf_through_as_batch():
    x = torch.rand(3, 8, 8)
    x[1, 2, 2] = math.inf
    with pytest.raises(ValueError) as info:
        check_image(as_batch(x, "photo"), "photo")
    one_line(info, "photo", "NaN or Inf")


@pytest.mark.bad_input
def test_as_batch_of_a_1d_tensor():
    with pytest.raises(ValueError) as info:
        as_batch(torch.rand(8), "photo")
    one_line(info, "photo", "(H, W)")
