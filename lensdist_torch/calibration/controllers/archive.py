"""An archive of folders and videos calibrated in one run: one answer file per input, one table, resumable.

:func:`run_archive` runs :func:`~lensdist_torch.calibration.controllers.calibrate.calibrate_path`
on each input (:func:`archive_inputs`: paths, globs, a manifest) and writes, in ``out``::

    answers/NAME-KEY.json   each answer, byte for byte what `lensdist calibrate INPUT --json` prints
    rows/NAME-KEY.json      each input's row (ArchiveRow) and its key: the run's bookkeeping
    answers.csv             one row per input, in the inputs' order (answers.parquet where pyarrow imports)
    cameras.csv             per camera and frame size: the pooled Delta_avg and who disagrees with it

NAME is the input's file or folder name; KEY the first 8 hex digits of the SHA-256 of the path
as given, the input's digest (:func:`input_digest`) and the settings' (:func:`settings_digest`).
Every file is written atomically, an input's files as soon as it finishes, so an interrupted
run (Ctrl-C, a killed job) loses at most the inputs in flight, and a rerun skips every input
whose row exists for the same key: same path, same bytes, same settings and library version
(the books, shared with ``lensdist analyze --pairs``: :mod:`~lensdist_torch.calibration.controllers.archive_book`).
An input that fails (unreadable, fewer than 2 frames, ...) is a row with its reason; that
reason is final for its key too, except where the engine failed (a Ray worker lost) or the
input could not be read to a digest (a missing path): those rows are tried again by a rerun.

Engines: ``"local"`` (one input after the other in this process) and ``"ray"`` (``import ray``
only there, the ``ray`` extra: one task per input with ``cpus_per_input`` CPUs, gathered as they
finish; the rows are written by this process). ``shard=(I, N)`` runs the inputs k with
k % N == I, as ``lensdist generate --shard``; each share writes the table of every input whose
row exists, under a lock, so the last share to finish writes the whole table.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import hashlib
import struct
import time
from pathlib import Path

from lensdist_torch import __version__
from lensdist_torch.calibration.controllers.answer_file import answer_text
from lensdist_torch.calibration.controllers.archive_book import ArchiveBook, check_shard, payload_digest, share_of
from lensdist_torch.calibration.controllers.archive_table import (
    ArchiveRow,
    CameraSummary,
    answer_row,
    camera_summaries,
    failed_row,
    write_tables,
)
from lensdist_torch.calibration.controllers.calibrate import METHODS, calibrate_path
from lensdist_torch.config import LensdistConfig, config_to_dict
from lensdist_torch.config.checks import one_line, or_defaults
from lensdist_torch.core.frames import list_frames
from lensdist_torch.data.locks import lock

__all__ = ["ENGINES", "RAY_EXTRA", "ArchiveInput", "ArchiveRun", "archive_inputs", "input_digest", "settings_digest",
           "require_ray", "run_archive"]

#: Where an archive's inputs run: this process, one after the other, or Ray tasks.
ENGINES = ("local", "ray")
#: How to install the Ray engine.
RAY_EXTRA = 'pip install "lensdist_torch[ray]"'


@dataclasses.dataclass(frozen=True)
class ArchiveInput:
    """One input of an archive: a folder of frames or a video, and its camera group (None: by frame size).

    Example:
        >>> ArchiveInput(path="dive_01.mp4", camera="A").camera
        'A'
    """

    path: str
    camera: str | None = None


@dataclasses.dataclass(frozen=True)
class ArchiveRun:
    """What :func:`run_archive` did: its counts, the table's rows and the per-camera summaries.

    ``inputs``: all of the archive's; ``selected``: this share's; ``computed``: calibrated by this
    run; ``reused``: rows of an earlier run for the same key; ``rows``: the table (every input
    with a row, other shares' too), ``failed`` of them without an answer; ``files``: the tables
    written.

    Example:
        >>> run = ArchiveRun(out="o", inputs=2, selected=1, computed=1, reused=0, failed=0, rows=(), cameras=(),
        ...                  files=())
        >>> run.computed
        1
    """

    out: str
    inputs: int
    selected: int
    computed: int
    reused: int
    failed: int
    rows: tuple[ArchiveRow, ...]
    cameras: tuple[CameraSummary, ...]
    files: tuple[str, ...]


def _expand(pattern: str) -> list[str]:
    """A path as given, or a glob's matches sorted (none: ValueError)."""
    if Path(pattern).exists() or not any(c in pattern for c in "*?["):
        return [pattern]
    found = sorted(glob.glob(pattern, recursive=True))
    if not found:
        raise ValueError(f"{pattern} matches no file or folder")
    return found


def _manifest(path: str | Path) -> list[ArchiveInput]:
    """A manifest's inputs: one path per line (``#`` comments), or CSV with ``path`` and optional ``camera`` columns."""
    path = Path(path)
    lines = path.read_text(encoding="utf-8-sig").splitlines()
    first = next((line for line in lines if line.strip() and not line.lstrip().startswith("#")), "")
    header = [c.strip().lower() for c in next(csv.reader([first]), [])]
    base = path.parent
    if "path" in header:
        rows = csv.DictReader([line for line in lines if line.strip()])
        rows.fieldnames = [c.strip().lower() for c in rows.fieldnames or []]
        out = [ArchiveInput(path=str(base / r["path"].strip()), camera=(r.get("camera") or "").strip() or None)
               for r in rows if (r.get("path") or "").strip()]
    else:
        out = [ArchiveInput(path=str(base / line.strip())) for line in lines
               if line.strip() and not line.lstrip().startswith("#")]
    if not out:
        raise ValueError(f"manifest {path} lists no input")
    return out


def archive_inputs(paths=(), manifest: str | Path | None = None) -> list[ArchiveInput]:
    """An archive's inputs: ``paths`` (globs expanded, sorted) then the ``manifest``'s, each path once.

    A manifest is one path per line (blank lines and ``#`` comments skipped) or a CSV file whose
    header has a ``path`` column and optionally a ``camera`` column; its relative paths are
    relative to its folder.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     _ = (Path(tmp) / "m.csv").write_text("path,camera" + chr(10) + "a.mp4,A" + chr(10) + "b.mp4," + chr(10))
        ...     found = archive_inputs(["x/"], manifest=Path(tmp) / "m.csv")
        >>> [(Path(i.path).name, i.camera) for i in found]
        [('x', None), ('a.mp4', 'A'), ('b.mp4', None)]
    """
    found = [ArchiveInput(path=p) for pattern in paths for p in _expand(str(pattern))]
    found += _manifest(manifest) if manifest is not None else []
    if not found:
        raise ValueError("an archive needs at least one input (PATH, a glob or --manifest)")
    seen: set[str] = set()
    return [i for i in found if not (i.path in seen or seen.add(i.path))]


def input_digest(path: str | Path) -> str:
    """SHA-256 (hex) over an input's files: for each (a folder's images by name, or the video) its name, size and bytes.

    Reading every byte costs one pass over the archive per run (a disk's read speed); nothing
    but what calibrate reads counts (a folder's other files do not).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     video = Path(tmp) / "dive.mp4"
        ...     _ = video.write_bytes(b"frames")
        ...     first = input_digest(video)
        ...     _ = video.write_bytes(b"frames!")  # one byte more: another input
        ...     second = input_digest(video)
        >>> len(first), first == second
        (64, False)
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"path not found: {path}")
    h = hashlib.sha256(b"lensdist-archive-input-v1")
    for f in list_frames(path) if path.is_dir() else [path]:
        name = f.name.encode()
        with open(f, "rb") as fh:
            h.update(struct.pack("<QQ", len(name), f.stat().st_size) + name)
            h.update(hashlib.file_digest(fh, "sha256").digest())
    return h.hexdigest()


def settings_digest(*, method: str = "auto", max_frames: int | None = 300, focal: float | None = None,
                    device=None, settings: LensdistConfig | None = None) -> str:
    """SHA-256 (hex) of what decides an answer besides the input: the options, every setting, the library version.

    Example:
        >>> settings_digest(method="direct") == settings_digest(method="direct", device="cpu")
        True
        >>> settings_digest(method="direct") == settings_digest(method="auto")
        False
    """
    payload = {"method": method, "max_frames": max_frames, "focal": focal, "device": str(device or "cpu").split(":")[0],
               "config": config_to_dict(or_defaults(settings, LensdistConfig, "settings")), "version": __version__}
    return payload_digest(payload)


def require_ray():
    """The ``ray`` module, or an ImportError of one line naming the extra that installs it.

    Example:
        >>> try:
        ...     _ = require_ray()
        ... except ImportError as err:
        ...     assert RAY_EXTRA in str(err)
    """
    try:
        import ray
    except ImportError:
        raise ImportError(f"the ray engine needs Ray: {RAY_EXTRA}") from None
    return ray


def _calibrate_one(path: str, kwargs: dict, threads: int | None = None) -> tuple[dict | None, str | None, float, bool]:
    """(answer or None, reason or None, seconds, final) of one input; what a Ray task runs."""
    if threads:
        import torch

        torch.set_num_threads(threads)
    t0 = time.perf_counter()
    try:
        answer = calibrate_path(path, **kwargs)
    except Exception as exc:  # the input's failure is its row, never the end of the run
        return None, one_line(exc, 500), time.perf_counter() - t0, not isinstance(exc, MemoryError)
    return answer, None, time.perf_counter() - t0, True


class _Calibrations(ArchiveBook):
    """The books of a calibrate archive: an item is an :class:`ArchiveInput`, its row an :class:`ArchiveRow`."""

    row_type = ArchiveRow

    def digest(self, item: ArchiveInput) -> str:
        return input_digest(item.path)

    def failed_row(self, item: ArchiveInput, reason: str, *, seconds: float | None = None,
                   digest: str | None = None) -> ArchiveRow:
        return failed_row(path=item.path, camera=item.camera, reason=reason, version=__version__, seconds=seconds,
                          digest=digest, settings=self.settings)

    def finish(self, inp: ArchiveInput, key: str, digest: str | None, result: tuple) -> None:
        """Record an input's calibration: (answer or None, reason or None, seconds, final) of :func:`_calibrate_one`."""
        answer, reason, seconds, final = result
        if answer is None:
            self.record(inp, key, digest, self.failed_row(inp, reason, seconds=seconds, digest=digest), final=final)
            return
        answer_file = f"answers/{self.stem(inp, key)}.json"
        row = answer_row(answer, camera=inp.camera, seconds=seconds, digest=digest, settings=self.settings,
                         answer_file=answer_file, version=__version__)
        self.record(inp, key, digest, row, final=final, answer=answer_text(answer) + "\n")


def _local(archive: _Calibrations, selected: list[ArchiveInput], kwargs: dict) -> None:
    for inp, key, digest in archive.pending(selected):
        archive.finish(inp, key, digest, _calibrate_one(inp.path, kwargs))


def _ray(archive: _Calibrations, selected: list[ArchiveInput], kwargs: dict, address: str | None, cpus: int) -> None:
    """One Ray task per input (``cpus`` CPUs, a GPU if the device is one), gathered with ``ray.wait`` as they finish."""
    ray = require_ray()
    started = not ray.is_initialized()
    if started:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    gpus = 1 if str(kwargs.get("device") or "cpu").startswith("cuda") else 0
    task = ray.remote(num_cpus=cpus, num_gpus=gpus)(_calibrate_one)
    pending: dict = {}

    def gather(ready) -> None:
        for ref in ready:
            inp, key, digest = pending.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as exc:  # the worker, not the input: tried again by a rerun
                result = (None, f"the Ray task failed: {one_line(exc, 300)}", None, False)
            archive.finish(inp, key, digest, result)

    try:
        for inp, key, digest in archive.pending(selected):
            pending[task.remote(inp.path, dict(kwargs, quiet=True), cpus)] = (inp, key, digest)
            gather(ray.wait(list(pending), num_returns=len(pending), timeout=0)[0])
        while pending:
            gather(ray.wait(list(pending), num_returns=1)[0])
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
    finally:
        if started:
            ray.shutdown()


def run_archive(
    inputs,
    out: str | Path,
    *,
    method: str = "auto",
    max_frames: int | None = 300,
    focal: float | None = None,
    device=None,
    settings: LensdistConfig | None = None,
    shard: tuple[int, int] = (0, 1),
    engine: str = "local",
    ray_address: str | None = None,
    cpus_per_input: int | None = None,
    quiet: bool = True,
) -> ArchiveRun:
    """Calibrate every input of an archive into ``out`` (module docstring): answers, rows, tables.

    Args:
        inputs: :class:`ArchiveInput` or paths (:func:`archive_inputs` expands globs and manifests).
        out: the output folder (made where missing; a rerun into it resumes).
        method: "auto", "multiview" or "direct", as ``calibrate_path`` takes it, for every input.
        max_frames: read at most this many frames of each input (None: all).
        focal: OpenCV's fx = fy in pixels for every input (None: the half diagonal).
        device: where the registration and self-calibration run (a Ray task gets a GPU for "cuda").
        settings: the library's :class:`~lensdist_torch.config.LensdistConfig` (None: the defaults).
        shard: (I, N): this run's share of the inputs, those k with k % N == I.
        engine: one of :data:`ENGINES`. "ray" needs the ``ray`` extra (:data:`RAY_EXTRA`).
        ray_address: the Ray cluster to join ("auto": the one of this machine); None starts a local
            Ray. A Ray already initialised in this process is used as it is.
        cpus_per_input: CPUs of each Ray task, and its torch threads (default: ``multiview.num_threads``).
        quiet: no progress bars.

    Returns:
        An :class:`ArchiveRun`; an input that fails is a row with its reason, never an exception.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     run = run_archive([Path(tmp) / "missing.mp4"], Path(tmp) / "out", method="direct")
        ...     again = run_archive([Path(tmp) / "missing.mp4"], Path(tmp) / "out", method="direct")
        ...     header = (Path(tmp) / "out" / "answers.csv").read_text().split(",")[:3]
        >>> run.failed, run.rows[0].reason.startswith("path not found"), again.computed, header
        (1, True, 0, ['path', 'camera', 'ok'])
    """
    from tqdm import tqdm

    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "ray":
        require_ray()  # before any work
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    shard = check_shard(shard)
    items = [i if isinstance(i, ArchiveInput) else ArchiveInput(path=str(i)) for i in inputs]
    if not items:
        raise ValueError("an archive needs at least one input")
    st = or_defaults(settings, LensdistConfig, "settings")
    kwargs = {"config": None if settings is None else settings.calibration, "settings": settings,
              "max_frames": max_frames, "focal": focal, "quiet": quiet, "device": device, "method": method}
    sdigest = settings_digest(method=method, max_frames=max_frames, focal=focal, device=device, settings=settings)
    selected = [inp for k, inp in enumerate(items) if k % shard[1] == shard[0]]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with share_of(out, shard), tqdm(total=len(selected), disable=quiet, desc="inputs", unit="input") as bar:
        archive = _Calibrations(out, sdigest, bar)
        try:
            if engine == "ray":
                _ray(archive, selected, kwargs, ray_address, cpus_per_input or st.multiview.num_threads)
            else:
                _local(archive, selected, kwargs)
        finally:  # also on Ctrl-C: the table of every finished input
            with lock(out / ".table.lock", wait_s=120.0):
                rows = archive.table(items)
                cameras = camera_summaries(rows)
                files = write_tables(out, rows, cameras)
    return ArchiveRun(out=str(out), inputs=len(items), selected=len(selected), computed=archive.computed,
                      reused=archive.reused, failed=sum(not r.ok for r in rows), rows=tuple(rows),
                      cameras=tuple(cameras), files=tuple(str(f) for f in files))
