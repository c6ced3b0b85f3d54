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

# a 10-frame sequence of a distorted camera panning down the scene, for calibrate / undistort
from lensdist_torch.workflows.calibrate import encode_png, synthetic_sequence  # noqa: E402

frames = out / "frames"
frames.mkdir(exist_ok=True)
for i, frame in enumerate(synthetic_sequence(10, 6e-6, 0.0, size=(240, 320), seed=3)[0]):
    (frames / f"frame_{i:03d}.png").write_bytes(encode_png((frame * 255).round().byte()))
