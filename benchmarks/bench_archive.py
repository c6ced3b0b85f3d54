"""An archive run's cost against its single runs: inputs per hour sequentially, with --shard, and with Ray.

Renders ``--inputs`` N folders of ``--frames`` frames at ``--size`` (eq. 4 with k2 cycling
through 1e-6, 4e-6 and 0 at 240 x 320, scaled to the size; ``synthetic_sequence``, one seed
each) and times, on ``--threads`` torch threads (1: the default, one input per core):

- ``single``: ``calibrate_path(input, method=--method)`` on each input in this process, one
  after the other (after one untimed warm-up call), and their sum;
- ``single_cli``: ``lensdist calibrate INPUT --json`` on each, a fresh process each time, as a
  user's shell loop runs them (the library's import counted);
- ``archive``: ``run_archive(inputs, OUT)`` in this process, its wall time, inputs per hour and
  ``overhead_ratio`` = its wall time / the sum of ``single`` (the issue's goal: at most 1.05);
- ``rerun``: the same call again (nothing to calibrate: the digests and the table);
- ``shard_2``: ``lensdist calibrate INPUTS --out OUT --shard 0/2`` and ``1/2`` as two processes
  at once, from the first start to the last exit;
- ``ray``: where Ray imports, ``ray.init(num_cpus=2)`` and ``run_archive(..., engine="ray",
  cpus_per_input=1)`` (its start counted apart).

Each table is checked against the sequential one (every column but ``seconds``). The load
averages at the start and the end say how much else ran on the cores. Writes JSON to ``--out``.

    python benchmarks/bench_archive.py --inputs 6 --out docs/results/bench_archive.json
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from lensdist_torch.calibration import calibrate_path, synthetic_sequence
from lensdist_torch.calibration.controllers.archive import run_archive
from lensdist_torch.core import atomic_write_text
from lensdist_torch.core.png import encode_png, to_uint8

LENSES = (1e-6, 4e-6, 0.0)  # k2 at 240 x 320


def render(root: Path, n: int, frames: int, size: tuple[int, int]) -> list[str]:
    s = size[1] / 320
    paths = []
    for i in range(n):
        folder = root / f"input_{i:03d}"
        folder.mkdir(parents=True)
        for j, frame in enumerate(synthetic_sequence(frames, LENSES[i % 3] / s**2, 0.0, size=size, seed=i + 1)[0]):
            (folder / f"frame_{j:03d}.png").write_bytes(encode_png(to_uint8(frame)))
        paths.append(str(folder))
    return paths


def table(out: Path) -> list[dict]:
    with open(out / "answers.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k != "seconds"} for row in csv.DictReader(f)]


def per_hour(n: int, seconds: float) -> float:
    return round(3600 * n / seconds, 1)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--inputs", type=int, default=6)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--size", type=int, nargs=2, default=(240, 320), metavar=("H", "W"))
    p.add_argument("--method", default="direct", choices=("auto", "multiview", "direct"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", required=True, help="JSON file to write")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads), MKL_NUM_THREADS=str(args.threads))
    tmp = Path(tempfile.mkdtemp(prefix="bench_archive_"))
    paths = render(tmp / "inputs", args.inputs, args.frames, tuple(args.size))
    report = {"command": "python benchmarks/bench_archive.py " + " ".join(argv or sys.argv[1:]),
              "machine": {"cpus": os.cpu_count(), "torch_threads": args.threads, "python": platform.python_version(),
                          "torch": torch.__version__, "load_average_start": [round(v, 2) for v in os.getloadavg()]},
              "inputs": args.inputs, "frames": args.frames, "size": list(args.size), "method": args.method}

    calibrate_path(paths[0], method=args.method)  # warm-up: lazy imports and first-call costs
    single = []
    for path in paths:
        t0 = time.perf_counter()
        calibrate_path(path, method=args.method)
        single.append(time.perf_counter() - t0)
    report["single"] = {"seconds": [round(s, 3) for s in single], "sum_s": round(sum(single), 2),
                        "inputs_per_hour": per_hour(len(paths), sum(single))}

    cli = [sys.executable, "-m", "lensdist_torch.cli", "calibrate"]
    t0 = time.perf_counter()
    for path in paths:
        subprocess.run([*cli, path, "--json", "--quiet", "--method", args.method], env=env, check=True,
                       stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    report["single_cli"] = {"sum_s": round(wall, 2), "inputs_per_hour": per_hour(len(paths), wall)}

    seq = tmp / "archive"
    t0 = time.perf_counter()
    run = run_archive(paths, seq, method=args.method)
    wall = time.perf_counter() - t0
    report["archive"] = {"wall_s": round(wall, 2), "inputs_per_hour": per_hour(len(paths), wall),
                         "overhead_ratio": round(wall / sum(single), 4), "computed": run.computed,
                         "rows": len(run.rows), "failed": run.failed}
    t0 = time.perf_counter()
    again = run_archive(paths, seq, method=args.method)
    report["rerun"] = {"wall_s": round(time.perf_counter() - t0, 3), "computed": again.computed, "reused": again.reused}

    sharded = tmp / "sharded"
    t0 = time.perf_counter()
    procs = [subprocess.Popen([*cli, *paths, "--out", str(sharded), "--quiet", "--method", args.method,
                               "--shard", f"{i}/2"], env=env, stdout=subprocess.DEVNULL) for i in range(2)]
    codes = [proc.wait() for proc in procs]
    wall = time.perf_counter() - t0
    report["shard_2"] = {"wall_s": round(wall, 2), "inputs_per_hour": per_hour(len(paths), wall), "exit": codes,
                         "same_table": table(sharded) == table(seq)}

    try:
        import ray
    except ImportError:
        report["ray"] = None
    else:
        t0 = time.perf_counter()
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        start = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_archive(paths, tmp / "ray", method=args.method, engine="ray", cpus_per_input=args.threads)
        wall = time.perf_counter() - t0
        ray.shutdown()
        report["ray"] = {"version": ray.__version__, "start_s": round(start, 2), "wall_s": round(wall, 2),
                         "inputs_per_hour": per_hour(len(paths), wall), "same_table": table(tmp / "ray") == table(seq)}
    report["machine"]["load_average_end"] = [round(v, 2) for v in os.getloadavg()]  # other work on the cores
    atomic_write_text(args.out, json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
