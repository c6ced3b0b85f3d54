"""The inputs .ci/wheel_check.sh feeds the README's commands, made with the installed package.

Two overlapping grey PNG views of the embedded gravel scene (8 px vertical motion), a.png and
b.png, and frames/: 10 frames of a distorted camera panning down the scene.
"""

import sys
from pathlib import Path

from lensdist_torch import load_scene
from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
from lensdist_torch.core.png import encode_png

out = Path(sys.argv[1])
scene = (load_scene("gravel")[0] * 255).round().byte()  # (1, H, W) uint8
(out / "a.png").write_bytes(encode_png(scene[:, :320, :424].contiguous()))
(out / "b.png").write_bytes(encode_png(scene[:, 8:328, :424].contiguous()))

frames = out / "frames"
frames.mkdir(exist_ok=True)
for i, frame in enumerate(synthetic_sequence(10, 6e-6, 0.0, size=(240, 320), seed=3)[0]):
    (frames / f"frame_{i:03d}.png").write_bytes(encode_png((frame * 255).round().byte()))
