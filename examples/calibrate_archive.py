"""An archive of videos or folders to one table: each camera's lens, and the inputs that disagree with it.

The same run as ``lensdist calibrate --manifest MANIFEST --out OUT``: each input's answer in
OUT/answers/ (what ``lensdist calibrate INPUT --json`` prints), one row per input in
OUT/answers.csv, the pooled Delta_avg per camera in OUT/cameras.csv. A second run into the same
OUT reuses every answer whose input and settings are unchanged.

    python examples/calibrate_archive.py MANIFEST OUT [--method auto|multiview|direct] [--engine local|ray]
    python examples/calibrate_archive.py --demo OUT [--method direct]

``--demo`` first renders a small archive into ``OUT/inputs`` with its manifest ``dives.csv``
(a ``path`` and a ``camera`` column): camera A's lens (eq. 4, k2 = 1e-6 at 240 x 320) in two
dives, the same camera after a lens change (k2 = 4e-6) in a third, camera B without distortion,
and a folder of unreadable files; it runs the archive twice and prints the truth beside each
camera's answer.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lensdist_torch import delta_avg, synthetic_sequence
from lensdist_torch.calibration.controllers.archive import archive_inputs, run_archive
from lensdist_torch.core.png import encode_png, to_uint8

DEMO_SIZE = (240, 320)
#: The demo's inputs: name, camera, eq. 4's k2 (None: unreadable files).
DEMO = (("dive_01", "A", 1e-6), ("dive_02", "A", 1e-6), ("dive_03", "A", 4e-6), ("dive_04", "B", 0.0),
        ("dive_05", "B", None))


def render_demo(folder: Path) -> Path:
    """The demo's inputs (8 frames each) and their manifest under ``folder``; returns the manifest."""
    for seed, (name, _, k2) in enumerate(DEMO):
        (folder / name).mkdir(parents=True, exist_ok=True)
        if k2 is None:
            (folder / name / "frame_000.png").write_bytes(b"not a png")
            continue
        for i, frame in enumerate(synthetic_sequence(8, k2, 0.0, size=DEMO_SIZE, seed=seed + 1)[0]):
            (folder / name / f"frame_{i:03d}.png").write_bytes(encode_png(to_uint8(frame)))
    manifest = folder / "dives.csv"
    manifest.write_text("path,camera\n" + "".join(f"{name},{camera}\n" for name, camera, _ in DEMO))
    return manifest


def main(argv: list[str] | None = None):
    """Run the example with ``argv`` (the command line when None); returns the run (an ``ArchiveRun``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifest", nargs="?", help="one path per line, or CSV with path and camera columns")
    parser.add_argument("out", help="output folder")
    parser.add_argument("--demo", action="store_true", help="render a small archive of known lenses first")
    parser.add_argument("--method", default="auto", choices=("auto", "multiview", "direct"), help="which paths run")
    parser.add_argument("--engine", default="local", choices=("local", "ray"), help="where the inputs run")
    args = parser.parse_args(argv)
    if args.demo == (args.manifest is not None):
        parser.error("give a MANIFEST or --demo, not both")
    out = Path(args.out)
    manifest = render_demo(out / "inputs") if args.demo else Path(args.manifest)

    inputs = archive_inputs(manifest=manifest)                  # paths relative to the manifest's folder
    run = run_archive(inputs, out, method=args.method, engine=args.engine)
    print(f"{run.inputs} inputs: {run.computed} calibrated, {run.reused} reused, {run.failed} without an answer")
    for row in run.rows:
        print(f"  {Path(row.path).name}: " + (f"Delta_avg {row.delta_avg_user_px:.2f} px, class {row.class_label}"
                                             if row.class_label else f"no class ({row.reason})"))
    truth = {camera: float(delta_avg([k2], [0.0], *DEMO_SIZE)[0]) for _, camera, k2 in DEMO[::-1] if k2 is not None}
    for cam in run.cameras:
        known = f"; truth {truth[cam.camera]:.2f} px" if args.demo else ""
        pooled = "none answered" if cam.delta_avg_px is None else (
            f"Delta_avg {cam.delta_avg_px:.2f} px [{cam.delta_avg_low_px:.2f}, {cam.delta_avg_high_px:.2f}] "
            f"over {cam.pooled} of {cam.inputs} inputs")
        print(f"camera {cam.camera} ({cam.size}): {pooled}{known}; disagreeing: "
              + (", ".join(Path(p).name for p in cam.disagreeing) or "none"))
    if args.demo:
        again = run_archive(inputs, out, method=args.method, engine=args.engine)
        print(f"run again: {again.computed} calibrated, {again.reused} reused")
    return run


if __name__ == "__main__":
    main()
