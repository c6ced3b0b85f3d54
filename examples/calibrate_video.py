"""A video or a folder of frames to its camera's lens and undistorted frames, in Python.

The same path as ``lensdist calibrate PATH --out OUT`` then ``lensdist undistort PATH --from
OUT/calibration.json --out OUT/undistorted``: the answer (Delta_avg with its 95 % interval, the
class or "cannot tell" and why, which path answered, OpenCV's camera) saved as JSON, then every
frame corrected by the lens that answer stands for, with its validity mask.

    python examples/calibrate_video.py VIDEO_OR_FOLDER OUT [--method auto|multiview|direct]
    python examples/calibrate_video.py --demo OUT [--method direct]

``--demo`` first renders 12 frames of a camera panning over an embedded scene through a known
barrel lens (eq. 4, k2 = 1e-6 at 240 x 320) into ``OUT/frames`` and prints the truth beside the
answer.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lensdist_torch import delta_avg, synthetic_sequence
from lensdist_torch.calibration import calibrate_path
from lensdist_torch.calibration.controllers.answer_file import write_answer
from lensdist_torch.core.png import encode_png, to_uint8
from lensdist_torch.workflows.undistort import undistort_path

DEMO_K2, DEMO_SIZE = 1e-6, (240, 320)


def render_demo(folder: Path) -> float:
    """12 frames through eq. 4 with k2 = DEMO_K2 written as PNG; returns the true Delta_avg in px."""
    folder.mkdir(parents=True, exist_ok=True)
    frames, _ = synthetic_sequence(12, DEMO_K2, 0.0, size=DEMO_SIZE, seed=1)
    for i, frame in enumerate(frames):
        (folder / f"frame_{i:03d}.png").write_bytes(encode_png(to_uint8(frame)))
    return float(delta_avg([DEMO_K2], [0.0], *DEMO_SIZE)[0])


def main(argv: list[str] | None = None) -> dict:
    """Run the example with ``argv`` (the command line when None); returns the calibration's answer."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("path", nargs="?", help="a video or a folder of frames (not with --demo)")
    parser.add_argument("out", help="output folder")
    parser.add_argument("--demo", action="store_true", help="render a sequence through a known lens first")
    parser.add_argument("--method", default="auto", choices=("auto", "multiview", "direct"), help="which paths run")
    args = parser.parse_args(argv)
    out = Path(args.out)
    if args.demo == (args.path is not None):
        parser.error("give a PATH or --demo, not both")
    path, truth = (out / "frames", render_demo(out / "frames")) if args.demo else (Path(args.path), None)

    answer = calibrate_path(path, method=args.method)          # the dict `lensdist calibrate --json` prints
    saved = write_answer(answer, out)  # what `lensdist calibrate --out OUT` writes
    interval = ", ".join(
        "no bound" if v is None else f"{v:.2f}" for v in answer["delta_avg_user_interval"] or (None, None)
    )
    value = answer["delta_avg_user_px"]
    print(
        f"Delta_avg {'unknown' if value is None else f'{value:.2f}'} px [{interval}] (95 %), class {answer['class']}, "
        f"by the {answer['method']} path" + (f"; truth {truth:.2f} px" if truth is not None else "")
    )
    if answer["class"] is None:
        print(f"cannot tell: {answer['reason']}")
        return answer
    done = undistort_path(path, out / "undistorted", from_json=saved, overwrite=True)
    print(f"{done['frames']} frames undistorted into {out / 'undistorted'} (masks in masks/)")
    return answer


if __name__ == "__main__":
    main()
