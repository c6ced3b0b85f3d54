"""COLMAP's feature extraction as ``lensdist calibrate`` runs it, in shards, against COLMAP's own on one thread.

The peer, measured in the same run on the same frames: ``pycolmap.extract_features`` on one thread
(what ``calibrate`` ran before, for a database that repeats bit for bit). The shards:
``calibration.features.extract_in_shards`` with ``--threads`` shards of one thread each. Both with
the options ``extract_and_match`` sets (RADIAL, ``multiview.max_image_side``, ``feature_cap``).
Alternates the two ``--repeats`` times, keeps each one's best, checks the two databases are the same
bit for bit and writes JSON to ``--out``.

    python benchmarks/bench_extraction.py FRAMES --frames 60 --threads 2 --out docs/results/bench_extraction.json

FRAMES: a folder of frames (``--frames`` of them, evenly spaced, as ``calibrate`` hands COLMAP).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from lensdist_torch.calibration.controllers.multiview_path import evenly_spaced
from lensdist_torch.calibration.features import extract_in_shards, extraction_options
from lensdist_torch.calibration.multiview_fits import pycolmap_or_error, quiet_log
from lensdist_torch.config import MultiViewConfig
from lensdist_torch.core import atomic_write_text
from lensdist_torch.core.frames import list_frames
from lensdist_torch.core.images import load_image


def _same(a: Path, b: Path, n: int) -> bool:
    pc = pycolmap_or_error()
    x, y = pc.Database.open(a), pc.Database.open(b)
    try:
        tables = ("read_all_cameras", "read_all_rigs", "read_all_frames", "read_all_images")
        return all([str(v) for v in getattr(x, t)()] == [str(v) for v in getattr(y, t)()] for t in tables) and all(
            np.array_equal(x.read_keypoints(i), y.read_keypoints(i))
            and np.array_equal(x.read_descriptors(i).data, y.read_descriptors(i).data)
            for i in range(1, n + 1)
        )
    finally:
        x.close()
        y.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames_dir", type=Path)
    ap.add_argument("--frames", type=int, default=60, help="frames handed to COLMAP, evenly spaced")
    ap.add_argument("--threads", type=int, default=2, help="the shards (multiview.num_threads)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    pc, cfg = pycolmap_or_error(), MultiViewConfig(num_threads=args.threads)
    files = list_frames(args.frames_dir)
    names = [files[i].name for i in evenly_spaced(len(files), args.frames)]
    size = tuple(load_image(files[0], max_pixels=None).shape[-2:])
    reader, extraction = extraction_options(cfg, size)
    extraction.num_threads = 1  # the peer: COLMAP's own extraction on one thread
    best = {"one_thread": float("inf"), "shards": float("inf")}
    with tempfile.TemporaryDirectory(prefix="bench-extraction-") as tmp:
        for r in range(args.repeats):
            for name in best:
                db = Path(tmp) / f"{name}{r}.db"
                t0 = time.perf_counter()
                with quiet_log():
                    if name == "one_thread":
                        pc.extract_features(db, args.frames_dir, image_names=names, camera_mode=pc.CameraMode.SINGLE,
                                            reader_options=reader, extraction_options=extraction,
                                            device=pc.Device.cpu)
                    else:
                        extract_in_shards(db, args.frames_dir, names, reader=reader, extraction=extraction,
                                          threads=args.threads)
                best[name] = min(best[name], time.perf_counter() - t0)
        same = _same(Path(tmp) / "one_thread0.db", Path(tmp) / "shards0.db", len(names))
    out = {
        "command": "python benchmarks/bench_extraction.py FRAMES "
        f"--frames {args.frames} --threads {args.threads} --repeats {args.repeats} --out {args.out}",
        "frames": len(names),
        "size": list(size),
        "features_per_frame_at_most": extraction.sift.max_num_features,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_average_at_end": list(os.getloadavg())},
        "best_seconds": best,
        "one_thread_over_shards": best["one_thread"] / best["shards"],
        "same_database": same,
    }
    atomic_write_text(args.out, json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
