"""Write two overlapping grey PNG views of the embedded gravel scene (8 px vertical motion),
with the standard library only, for the wheel check in .ci/wheel_check.sh."""

import struct
import sys
import zlib
from pathlib import Path

from lensdist_torch import load_scene


def write_png(path: Path, img) -> None:
    h, w = img.shape
    raw = b"".join(b"\x00" + bytes(row) for row in img.tolist())
    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    path.write_bytes(png)


out = Path(sys.argv[1])
scene = (load_scene("gravel")[0, 0] * 255).round().byte()
write_png(out / "a.png", scene[:320, :424])
write_png(out / "b.png", scene[8:328, :424])
