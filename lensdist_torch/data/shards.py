"""Generated data sets on disk: shards, checksums, manifest, resume, lock (`lensdist generate`).

The pairs are those of docs/method.md.

Layout of an output folder::

    manifest.json                    format version, config, fingerprint, scenes, sets, counts
    train/shard-00000.pt ...         pairs [0, 500), [500, 1000), ... of the training set
    train/shard-00000.pt.sha256 ...  the sha256 of each shard file (``sha256sum -c`` reads it)
    test/shard-00000.pt              the test set (distorted pairs first, then class R)
    .lock-I-of-N                     while a run writes its share I/N (its pid and host)

A set is cut into fixed shards of ``protocol.shard_size`` pairs by pair index, so the same
command runs as an array job (``--shard I/N`` takes the shards k with k % N == I), shards merge
by pair index, and an interrupted run resumes by skipping the shards already on disk. A shard's
bytes depend only on the config and the pair indices: a resumed run gives byte-identical files.

Integrity: every shard is written with the library's versioned writer (``save_versioned``,
atomic) followed by a checksum file holding the sha256 of its bytes, and every read
(``load_shard``, ``load_set``, the resume check of ``generate``) verifies that digest before it
unpickles (``torch.load(weights_only=True)``) and then checks the kind, format version, config
fingerprint and the pairs the shard must hold. A changed byte, a truncated file or a shard
copied over another is never used: a one-line ShardError naming the file, or, when
``generate`` resumes, the shard is regenerated and reported.

The manifest only grows: a run merges its sets into the recorded ones, keeps the sets it was
not asked for, refuses a ``limit`` that would shrink a recorded set, is validated on every read,
and is not rewritten when nothing changed (a complete, read-only data set can be re-checked).
A run that writes holds a lock file for its share; a run over overlapping shares is refused
(the shares of one array job do not overlap and run side by side), and a lock left by a dead
process on this host is taken over.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import multiprocessing as mp
import os
import re
import socket
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm.auto import tqdm

from lensdist_torch.config import LensdistConfig, config_from_dict, config_to_dict
from lensdist_torch.core.images import load_image, load_scene
from lensdist_torch.core.storage import atomic_write_bytes, load_versioned, save_versioned
from lensdist_torch.data.synthesis import SETS, footprint, make_pairs, scene_zoom, sequence_footprint, set_size

__all__ = [
    "FORMAT_VERSION",
    "CLASS_KEYS",
    "ShardError",
    "DataSetLocked",
    "config_fingerprint",
    "load_scenes",
    "shard_ranges",
    "shard_path",
    "checksum_path",
    "write_shard",
    "load_shard",
    "generate_shard",
    "generate",
    "load_set",
    "read_manifest",
]

#: 2: a sha256 checksum file beside every shard, written and read by save/load_versioned.
FORMAT_VERSION = 2
_KIND = "lensdist-shard"
_MANIFEST = "manifest.json"
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
MIN_ZOOM = 0.25  # a scene that must be magnified more than 4 x is too small to be a scene
_TENSOR_KEYS = (
    "index", "seed", "scene", "k2", "k4", "delta_avg", "delta_max", "class_avg", "class_max",
    "motion", "M", "H", "converged", "residual", "perturbed", "counts",
)
_N_CLASSES = 5  # classes 1-4 and R, as stored in class_avg / class_max
_MANIFEST_LOCK_WAIT_S = 30.0  # the manifest's lock is held for one read-merge-write only
_LOCK_NAME = re.compile(r"\.lock-(\d+)-of-(\d+)")


#: The config sections that change a data set's pairs (the fingerprint covers them).
_DATA_SECTIONS = ("quality", "image", "distortion", "protocol", "registration")

#: The per-pair class key of each Delta metric in a shard record.
CLASS_KEYS = {"delta_avg": "class_avg", "delta_max": "class_max"}


class ShardError(ValueError):
    """A shard or manifest file that is corrupted, foreign, or of another config or format version.

    The message names the file.
    """


class DataSetLocked(ValueError):
    """Another run is writing the same shards of the data set folder (the message names its lock file)."""


def config_fingerprint(config: LensdistConfig, scene_ids: list[str]) -> str:
    """A hash of every setting that changes the pairs or the files, and of the scenes.

    The quality, image, distortion, protocol and registration sections count (chunk sizes do
    not; ``shard_size`` does, since it fixes which pairs each shard file holds).
    """
    d = config_to_dict(config)
    d = {name: d[name] for name in _DATA_SECTIONS}
    for name in ("quality", "registration"):
        d[name].pop("chunk_size", None)
    d["scenes"] = scene_ids
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def load_scenes(
    config: LensdistConfig, scenes_dir: str | Path | None = None, sequence: bool = False
) -> tuple[list[torch.Tensor], list[str]]:
    """The scene images (1, 1, H, W) and their ids (embedded name, or file name + content hash).

    With ``sequence``, the folder holds consecutive frames of one real, undistorted sequence
    (sorted by file name, all of one size); pair i is made of frames i and i + 1 (cyclically).

    Raises:
        ValueError: naming the file, for an unreadable image or one too small for the footprint.
    """
    if scenes_dir is None:
        return [load_scene(n) for n in config.protocol.scenes], list(config.protocol.scenes)
    folder = Path(scenes_dir)
    if not folder.is_dir():
        raise FileNotFoundError(f"--scenes folder not found: {folder}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"--scenes folder {folder} holds no image files ({sorted(_IMAGE_SUFFIXES)})")
    box = sequence_footprint(config) if sequence else footprint(config)
    scenes, ids = [], []
    for f in files:
        img = load_image(f, grey=True)  # raises ValueError naming the file if undecodable
        z = scene_zoom(tuple(img.shape[-2:]), box)
        if z < MIN_ZOOM:
            need_w, need_h = MIN_ZOOM * (box[1] - box[0]), MIN_ZOOM * (box[3] - box[2])
            raise ValueError(
                f"scene image {f} is too small: {img.shape[-1]} x {img.shape[-2]} px; the views need "
                f"at least {need_w:.0f} x {need_h:.0f} px (a zoom of {MIN_ZOOM})"
            )
        if sequence and scenes and img.shape != scenes[0].shape:
            raise ValueError(f"sequence frame {f} is {tuple(img.shape[-2:])}, the first frame {tuple(scenes[0].shape[-2:])}")
        scenes.append(img)
        ids.append(("frame:" if sequence else "") + f"{f.name}:{hashlib.sha256(f.read_bytes()).hexdigest()[:12]}")
    if sequence and len(scenes) < 2:
        raise ValueError(f"--sequence folder {folder} needs at least 2 frames, found {len(scenes)}")
    return scenes, ids


def shard_ranges(n_pairs: int, shard_size: int) -> list[tuple[int, int]]:
    """The pairs [start, end) of each shard of a set of ``n_pairs``."""
    return [(s, min(s + shard_size, n_pairs)) for s in range(0, n_pairs, shard_size)]


def shard_path(out: str | Path, set_name: str, k: int) -> Path:
    """The file of shard ``k`` of a set."""
    return Path(out) / set_name / f"shard-{k:05d}.pt"


def checksum_path(path: str | Path) -> Path:
    """The checksum file of a shard: ``shard-00000.pt.sha256``, one ``sha256sum`` line."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def _checksum_line(digest: str, name: str) -> str:
    return f"{digest}  {name}\n"


def _read_checksum(path: Path) -> str:
    """The sha256 recorded for the shard ``path``; ShardError if its checksum file is absent or damaged."""
    side = checksum_path(path)
    try:
        text = side.read_bytes().decode("ascii", "replace")
    except FileNotFoundError:
        raise ShardError(
            f"shard {path} has no checksum file {side.name} (an interrupted run or an older format: "
            "rerun `lensdist generate`)"
        ) from None
    digest = text[:64]
    if not re.fullmatch(r"[0-9a-f]{64}", digest) or text != _checksum_line(digest, path.name):
        raise ShardError(f"checksum file {side} is damaged (expected one line: sha256, two spaces, {path.name})")
    return digest


def write_shard(path: str | Path, record: dict) -> str:
    """Save a shard with ``save_versioned`` (atomically), then its checksum file; returns the sha256.

    The bytes depend only on ``record`` (never on the file name).
    """
    path = Path(path)
    digest = save_versioned(path, _KIND, FORMAT_VERSION, record)
    atomic_write_bytes(checksum_path(path), _checksum_line(digest, path.name).encode())
    return digest


def load_shard(path: str | Path, fingerprint: str | None = None, expect: tuple[str, int, int] | None = None) -> dict:
    """Load and check a shard: its sha256, kind, format version, keys and shapes.

    Optionally also the config (``fingerprint``) and the pairs it must hold (``expect`` =
    (set, start, end)).

    Raises:
        FileNotFoundError: no such shard.
        ShardError: naming the file: no or another checksum (changed bytes, truncated, copied
            over another shard), not a lensdist shard, another format version, config or place.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"shard not found: {path}")
    rec = load_versioned(
        path, _KIND, FORMAT_VERSION, "data-set", sha256=_read_checksum(path), error=ShardError, noun="shard"
    )
    if fingerprint is not None and rec.get("fingerprint") != fingerprint:
        raise ShardError(
            f"shard {path} was generated with another config or scenes (fingerprint "
            f"{rec.get('fingerprint')}, expected {fingerprint})"
        )
    missing = [k for k in _TENSOR_KEYS if not isinstance(rec.get(k), torch.Tensor)]
    if missing:
        raise ShardError(f"shard {path} lacks {missing}")
    start, end = rec.get("start"), rec.get("end")
    if not (type(start) is int and type(end) is int and 0 <= start < end):
        raise ShardError(f"shard {path} has no valid pair range (start {start!r}, end {end!r})")
    n = end - start
    if any(rec[k].shape[0] != n for k in _TENSOR_KEYS) or not torch.equal(rec["index"], torch.arange(start, end)):
        raise ShardError(f"shard {path} is inconsistent: expected pairs [{start}, {end})")
    if expect is not None and (rec.get("set"), start, end) != tuple(expect):
        raise ShardError(
            f"shard {path} holds {rec.get('set')!r} pairs [{start}, {end}), expected {expect[0]!r} pairs "
            f"[{expect[1]}, {expect[2]}) (a shard copied over another, or left by a shorter --limit run)"
        )
    return rec


def _record(batches, set_name: str, start: int, end: int, fingerprint: str) -> dict:
    def cat(f):
        return torch.cat([f(b) for b in batches])

    return {
        "kind": _KIND,
        "format_version": FORMAT_VERSION,
        "fingerprint": fingerprint,
        "set": set_name,
        "start": start,
        "end": end,
        "index": cat(lambda b: b.params.index),
        "seed": cat(lambda b: b.params.seed),
        "scene": cat(lambda b: b.params.scene),
        "k2": cat(lambda b: b.params.k2),
        "k4": cat(lambda b: b.params.k4),
        "delta_avg": cat(lambda b: b.delta["delta_avg"]),
        "delta_max": cat(lambda b: b.delta["delta_max"]),
        "class_avg": cat(lambda b: b.classes["delta_avg"]),
        "class_max": cat(lambda b: b.classes["delta_max"]),
        "motion": cat(lambda b: b.params.motion),
        "M": cat(lambda b: b.params.M),
        "H": cat(lambda b: b.H),
        "converged": cat(lambda b: b.converged),
        "residual": cat(lambda b: b.residual),
        "perturbed": cat(lambda b: b.params.perturbed),
        "counts": cat(lambda b: b.counts),
    }


def generate_shard(scenes, config, set_name, start, end, fingerprint, batch_size=16, on_batch=None, sequence=False) -> dict:
    """Generate pairs [start, end) of a set as one shard record."""
    batches = []
    for s in range(start, end, batch_size):
        idx = list(range(s, min(s + batch_size, end)))
        batches.append(make_pairs(scenes, config, set_name, idx, sequence=sequence))
        if on_batch is not None:
            on_batch(len(idx))
    return _record(batches, set_name, start, end, fingerprint)


def _worker(task):
    cfg_dict, scenes_dir, sequence, set_name, k, start, end, fingerprint, batch_size, out = task
    torch.set_num_threads(1)
    config = config_from_dict(cfg_dict)
    scenes, _ = load_scenes(config, scenes_dir, sequence)
    rec = generate_shard(scenes, config, set_name, start, end, fingerprint, batch_size, sequence=sequence)
    write_shard(shard_path(out, set_name, k), rec)
    return end - start


# ---------------------------------------------------------------------------------- what is on disk


@dataclass
class _SetState:
    """One set of ``n_pairs`` pairs on disk: each shard verified, missing, or bad (and why)."""

    name: str
    n_pairs: int
    shard_size: int
    stats: dict[int, tuple[int, torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    bad: dict[int, str] = field(default_factory=dict)

    @property
    def ranges(self) -> list[tuple[int, int]]:
        return shard_ranges(self.n_pairs, self.shard_size)

    def record(self) -> dict:
        """The set's manifest record: its size and, once every shard is verified, its counts."""
        n_shards = len(self.ranges)
        rec = {"n_pairs": self.n_pairs, "shard_size": self.shard_size, "n_shards": n_shards}
        if len(self.stats) < n_shards:
            return {**rec, "complete": False, "shards_present": len(self.stats)}
        failed, per_avg, per_max = zip(*self.stats.values()) if self.stats else ((), (), ())
        zero = torch.zeros(_N_CLASSES, dtype=torch.long)
        return {
            **rec,
            "complete": True,
            "registration_failed": sum(failed),
            "pairs_per_class_avg": sum(per_avg, zero).tolist(),
            "pairs_per_class_max": sum(per_max, zero).tolist(),
        }


def _verify_set(out: Path, set_name: str, n_pairs: int, shard_size: int, fingerprint: str) -> _SetState:
    """Verify every shard of a set of ``n_pairs`` (checksum, config, pairs held)."""
    state = _SetState(set_name, n_pairs, shard_size)
    for k, (a, b) in enumerate(state.ranges):
        path = shard_path(out, set_name, k)
        if not path.exists():
            continue
        try:
            rec = load_shard(path, fingerprint, expect=(set_name, a, b))
        except FileNotFoundError:
            continue  # removed meanwhile: missing
        except ShardError as exc:
            state.bad[k] = str(exc)  # corrupted, foreign or another range: regenerated, never trusted
            continue
        state.stats[k] = (
            int((~rec["converged"]).sum()),
            torch.bincount(rec["class_avg"], minlength=_N_CLASSES),
            torch.bincount(rec["class_max"], minlength=_N_CLASSES),
        )
    return state


# ---------------------------------------------------------------------------------- manifest


def _manifest_problem(m) -> str | None:
    """What is wrong with a parsed manifest, or None."""
    if not isinstance(m, dict):
        return f"a JSON {type(m).__name__}, not an object"
    missing = [k for k in ("format_version", "fingerprint", "config", "scenes", "sets") if k not in m]
    if missing:
        return f"missing field(s) {missing}"
    if m["format_version"] != FORMAT_VERSION or isinstance(m["format_version"], bool):
        return f"format version {m['format_version']!r}, this library reads {FORMAT_VERSION} (generate into another --out)"
    scenes = m["scenes"]
    if not (isinstance(scenes, list) and scenes and all(isinstance(s, str) for s in scenes)):
        return "scenes must be a non-empty list of names"
    try:
        config = config_from_dict(m["config"])
    except (TypeError, ValueError, AttributeError) as exc:
        return "config: " + " ".join(str(exc).split())
    if m["fingerprint"] != config_fingerprint(config, scenes):
        return f"fingerprint {m['fingerprint']!r} does not match its config and scenes (edited or damaged)"
    if not isinstance(m["sets"], dict):
        return "sets must be an object"
    for name, rec in m["sets"].items():
        problem = _record_problem(rec, config, name) if name in SETS else f"unknown set (sets are {list(SETS)})"
        if problem:
            return f"sets.{name}: {problem}"
    return None


def _is_count(v, top: int) -> bool:
    return type(v) is int and 0 <= v <= top


def _record_problem(rec, config: LensdistConfig, name: str) -> str | None:
    if not isinstance(rec, dict):
        return "not an object"
    n, size = rec.get("n_pairs"), set_size(config, name)
    if not _is_count(n, size):
        return f"n_pairs must be an int in [0, {size}], got {n!r}"
    if rec.get("shard_size") != config.protocol.shard_size:
        return f"shard_size {rec.get('shard_size')!r}, its config says {config.protocol.shard_size}"
    n_shards = len(shard_ranges(n, config.protocol.shard_size))
    if rec.get("n_shards") != n_shards:
        return f"n_shards {rec.get('n_shards')!r}, {n} pairs make {n_shards}"
    if not isinstance(rec.get("complete"), bool):
        return "complete must be true or false"
    if not rec["complete"]:
        return None if _is_count(rec.get("shards_present"), n_shards) else f"shards_present must be an int in [0, {n_shards}]"
    if not _is_count(rec.get("registration_failed"), n):
        return f"registration_failed must be an int in [0, {n}]"
    for key in ("pairs_per_class_avg", "pairs_per_class_max"):
        v = rec.get(key)
        if not (isinstance(v, list) and len(v) == _N_CLASSES and all(_is_count(c, n) for c in v) and sum(v) == n):
            return f"{key} must be {_N_CLASSES} counts summing to n_pairs {n}"
    return None


def read_manifest(out: str | Path) -> dict:
    """The validated manifest of a data set folder.

    Raises:
        FileNotFoundError: no manifest.json.
        ShardError: naming the file: not JSON, another format version, a missing or wrong field.
    """
    path = Path(out) / _MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"no manifest.json in {out}: run `lensdist generate --out {out}` first")
    try:
        m = json.loads(path.read_bytes())
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise ShardError(
            f"{path} is not valid JSON ({' '.join(str(exc).split())}); delete it and rerun `lensdist generate` "
            "to rebuild it from the verified shards"
        ) from None
    problem = _manifest_problem(m)
    if problem:
        raise ShardError(
            f"{path} is not a valid lensdist manifest: {problem}; delete it and rerun `lensdist generate` "
            "to rebuild it from the verified shards"
        )
    return m


def _merge(old: dict | None, header: dict, records: dict[str, dict]) -> dict:
    """``header`` + the recorded sets + ``records``; a set's record only grows (more pairs wins)."""
    sets = dict(old["sets"]) if old else {}
    for name, rec in records.items():
        if name not in sets or sets[name]["n_pairs"] <= rec["n_pairs"]:
            sets[name] = rec
    return json.loads(json.dumps({**header, "sets": sets}))  # as read back: lists, not tuples


def _save_manifest(out: Path, header: dict, records: dict[str, dict]) -> bool:
    """Merge ``records`` into the manifest on disk and write it if anything changed (returns whether)."""
    with _lock(out / ".manifest.lock", wait_s=_MANIFEST_LOCK_WAIT_S):
        old = read_manifest(out) if (out / _MANIFEST).exists() else None
        _check_same_data(out, old, header["fingerprint"])
        new = _merge(old, header, records)
        if new == old:
            return False
        atomic_write_bytes(out / _MANIFEST, (json.dumps(new, indent=2) + "\n").encode())
        return True


def _check_same_data(out: Path, manifest: dict | None, fingerprint: str) -> None:
    if manifest is not None and manifest["fingerprint"] != fingerprint:
        raise ValueError(
            f"{out} holds a data set of another config or scenes (fingerprint {manifest['fingerprint']}, "
            f"now {fingerprint}); use another --out"
        )


# ---------------------------------------------------------------------------------- locks

_HELD: set[Path] = set()  # the lock files this process holds


def _lock_holder(path: Path) -> tuple[int, str] | None:
    """(pid, host) written in a lock file; None if it cannot be read (being written, or damaged)."""
    try:
        parts = path.read_text().split()
    except (OSError, UnicodeDecodeError):
        return None
    if len(parts) != 2 or not parts[0].isdigit() or int(parts[0]) < 1:
        return None
    return int(parts[0]), parts[1]


def _is_stale(path: Path) -> bool:
    """A lock left by a dead process of this host (or unreadable for a minute).

    A lock of another host cannot be checked: it is live until deleted.
    """
    holder = _lock_holder(path)
    if holder is None:
        try:
            return time.time() - path.stat().st_mtime > 60
        except FileNotFoundError:
            return True
    pid, host = holder
    if host != socket.gethostname():
        return False
    if pid == os.getpid():
        return path not in _HELD  # our pid, but not our lock: a dead run's pid reused
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, another user's
    return False


def _try_lock(path: Path) -> bool:
    """Create ``path`` exclusively (O_CREAT | O_EXCL) with our pid and host; False if it exists."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write(f"{os.getpid()} {socket.gethostname()}\n")
    _HELD.add(path)
    return True


def _take(path: Path) -> bool:
    """Lock ``path``, taking over a stale lock; False while a live run holds it."""
    if _try_lock(path):
        return True
    if not _is_stale(path):
        return False
    _note(f"taking over the stale lock {path} (held by {_lock_holder(path) or 'nobody readable'})")
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    return _try_lock(path)


def _release(path: Path) -> None:
    _HELD.discard(path)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


def _busy(out: Path, lock: Path) -> str:
    pid, host = _lock_holder(lock) or ("?", "?")
    return (
        f"another `lensdist generate` (pid {pid} on {host}) is writing shards of {out}: wait for it to "
        f"finish, or delete {lock} if no such run is going"
    )


@contextlib.contextmanager
def _lock(path: Path, wait_s: float = 0.0):
    """Hold the lock file ``path``; waits up to ``wait_s`` for a live holder, then DataSetLocked."""
    deadline = time.monotonic() + wait_s
    while not _take(path):
        if time.monotonic() >= deadline:
            raise DataSetLocked(_busy(path.parent, path))
        time.sleep(0.05)
    try:
        yield
    finally:
        _release(path)


@contextlib.contextmanager
def _share_lock(out: Path, shard: tuple[int, int]):
    """Hold ``.lock-I-of-N`` while this run writes; DataSetLocked if a live run holds an overlapping share.

    Shares I/N and J/M have shards in common iff I = J mod gcd(N, M).
    """
    i, n = shard
    out.mkdir(parents=True, exist_ok=True)
    with _lock(out / f".lock-{i}-of-{n}"):
        for other in out.glob(".lock-*-of-*"):
            name = _LOCK_NAME.fullmatch(other.name)
            if name is None or other.name == f".lock-{i}-of-{n}":
                continue
            j, m = int(name[1]), int(name[2])
            if m >= 1 and (i - j) % math.gcd(n, m) == 0 and not _is_stale(other):
                raise DataSetLocked(_busy(out, other))
        yield


# ---------------------------------------------------------------------------------- generate


def _note(msg: str) -> None:
    print(f"lensdist generate: {msg}", file=sys.stderr)


def _check_arguments(sets, shard, workers, batch_size, limit, scenes_dir, sequence) -> None:
    for s in sets:
        if s not in SETS:
            raise ValueError(f"sets must be among {SETS}, got {s!r}")
    if not (type(workers) is int and workers >= 1):
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    if not (type(batch_size) is int and batch_size >= 1):
        raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
    if not (len(shard) == 2 and shard[1] >= 1 and 0 <= shard[0] < shard[1]):
        raise ValueError(f"shard must be (I, N) with 0 <= I < N, got {shard!r}")
    if limit is not None and not (type(limit) is int and limit >= 1):
        raise ValueError(f"limit must be a positive int, got {limit!r}")
    if sequence and scenes_dir is None:
        raise ValueError("sequence=True needs scenes_dir: the folder of the sequence's frames")


@dataclass
class _Plan:
    """What a run finds: the manifest on disk, its sets verified, and the shards its share must write."""

    old: dict | None
    states: dict[str, _SetState]
    tasks: list[tuple[str, int, int, int]]  # (set, k, start, end)

    def records(self) -> dict[str, dict]:
        return {name: st.record() for name, st in self.states.items()}


def _set_sizes(config: LensdistConfig, out: Path, old: dict | None, sets, limit: int | None) -> dict[str, int]:
    """Pairs per set for this run; a ``limit`` below a recorded set's size is refused (a record never shrinks)."""
    sizes = {}
    for s in sets:
        n = set_size(config, s) if limit is None else min(limit, set_size(config, s))
        have = old["sets"][s]["n_pairs"] if old and s in old["sets"] else 0
        if n < have:
            raise ValueError(
                f"{out} records {have} {s} pairs; --limit {limit} would shrink the set and rewrite good shards "
                "shorter: drop --limit (or give at least that many) or use another --out"
            )
        sizes[s] = n
    return sizes


def _plan(config, out: Path, fingerprint: str, sets, shard, limit) -> _Plan:
    old = read_manifest(out) if (out / _MANIFEST).exists() else None
    _check_same_data(out, old, fingerprint)
    sizes = _set_sizes(config, out, old, sets, limit)
    states = {s: _verify_set(out, s, n, config.protocol.shard_size, fingerprint) for s, n in sizes.items()}
    tasks = [
        (s, k, a, b)
        for s, st in states.items()
        for k, (a, b) in enumerate(st.ranges)
        if k % shard[1] == shard[0] and k not in st.stats
    ]
    return _Plan(old, states, tasks)


def _cap_workers(workers: int, n_tasks: int) -> tuple[int, str | None]:
    """min(workers, tasks, CPUs) worker processes, and a note when that is fewer than asked."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    used = max(1, min(workers, n_tasks, cpus))
    if used >= workers or n_tasks == 0:
        return used, None
    return used, f"--workers {workers} capped to {used} ({n_tasks} shards to write, {cpus} CPUs)"


def _run_tasks(tasks, out: Path, config, scenes, scenes_dir, sequence, fingerprint, batch_size, workers, progress) -> int:
    """Generate and write the shards of ``tasks``; returns the pairs generated."""
    total = sum(b - a for _, _, a, b in tasks)
    bar = tqdm(total=total, unit="pair", desc="generate", disable=not progress)
    if workers == 1:
        # One thread, as in the worker processes: float32 reductions of the registration
        # depend on the thread count, and a shard's bytes must not depend on --workers.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            for s, k, a, b in tasks:
                rec = generate_shard(scenes, config, s, a, b, fingerprint, batch_size, on_batch=bar.update, sequence=sequence)
                write_shard(shard_path(out, s, k), rec)
        finally:
            torch.set_num_threads(threads)
    elif tasks:
        cfg = config_to_dict(config)
        jobs = [(cfg, scenes_dir, sequence, s, k, a, b, fingerprint, batch_size, str(out)) for s, k, a, b in tasks]
        with mp.get_context("spawn").Pool(workers) as pool:
            for n in pool.imap_unordered(_worker, jobs):
                bar.update(n)
    bar.close()
    return total


def generate(
    config: LensdistConfig,
    out: str | Path,
    sets=SETS,
    shard: tuple[int, int] = (0, 1),
    workers: int = 1,
    batch_size: int = 16,
    scenes_dir: str | Path | None = None,
    limit: int | None = None,
    progress: bool = True,
    sequence: bool = False,
) -> dict:
    """Generate the sets' shards that belong to ``shard`` = (I, N) and are not verified on disk.

    A run with nothing to write writes nothing (no lock, no manifest). Otherwise it holds the
    share's lock, writes the manifest with the planned sets, regenerates bad shards (reported),
    writes the missing ones with min(workers, shards, CPUs) processes, and records the sets.

    Returns a summary: shards written and pairs generated, the workers used (and a note when
    capped), the shards regenerated and why, whether the manifest was written, and per set its
    record (pairs, shards and, once complete, failed registrations and pairs per class).

    Raises:
        ValueError: bad arguments; another config's data set in ``out``; a ``limit`` that would
            shrink a recorded set.
        ShardError: a manifest that is not valid (naming the file).
        DataSetLocked: another live run over overlapping shares.
    """
    out = Path(out)
    _check_arguments(sets, shard, workers, batch_size, limit, scenes_dir, sequence)
    scenes, scene_ids = load_scenes(config, scenes_dir, sequence)
    fp = config_fingerprint(config, scene_ids)
    header = {"format_version": FORMAT_VERSION, "fingerprint": fp, "config": config_to_dict(config), "scenes": scene_ids}
    plan = _plan(config, out, fp, sets, shard, limit)
    if not plan.tasks and _merge(plan.old, header, plan.records()) == plan.old:
        return _summary(out, sets, plan.old, plan, pairs=0, workers=1, capped=None, written=False)
    with _share_lock(out, shard):
        plan = _plan(config, out, fp, sets, shard, limit)  # again, under the lock
        written = _save_manifest(out, header, plan.records())
        used, capped = _cap_workers(workers, len(plan.tasks))
        if capped:
            _note(capped)
        for s, k, _, _ in plan.tasks:
            if k in plan.states[s].bad:
                _note(f"regenerating {plan.states[s].bad[k]}")
        pairs = _run_tasks(plan.tasks, out, config, scenes, scenes_dir, sequence, fp, batch_size, used, progress)
        sizes = {s: st.n_pairs for s, st in plan.states.items()}
        done = {s: _verify_set(out, s, n, config.protocol.shard_size, fp).record() for s, n in sizes.items()}
        written = _save_manifest(out, header, done) or written
    return _summary(out, sets, read_manifest(out), plan, pairs=pairs, workers=used, capped=capped, written=written)


def _summary(out: Path, sets, manifest: dict, plan: _Plan, *, pairs: int, workers: int, capped, written: bool) -> dict:
    summary = {
        "out": str(out),
        "written": len(plan.tasks),
        "pairs_generated": pairs,
        "workers": workers,
        "regenerated": [plan.states[s].bad[k] for s, k, _, _ in plan.tasks if k in plan.states[s].bad],
        "manifest": "written" if written else "unchanged",
        "sets": {s: manifest["sets"][s] for s in sets},
    }
    if capped:
        summary["workers_capped"] = capped
    return summary


# ---------------------------------------------------------------------------------- reading


def load_set(out: str | Path, set_name: str, limit: int | None = None) -> dict:
    """Merge a set's shards by pair index into one dict of tensors.

    Every shard must be present and verified (sha256, config, the pairs it holds).

    Raises:
        FileNotFoundError: no manifest, or a shard missing (the set is incomplete).
        ShardError: naming the file: a manifest that is not valid, or a shard that fails a check.
        ValueError: no such set in the folder.
    """
    m = read_manifest(out)
    if set_name not in m["sets"]:
        raise ValueError(f"{out} holds no {set_name!r} set; it has {sorted(m['sets'])}")
    info = m["sets"][set_name]
    ranges = shard_ranges(info["n_pairs"], info["shard_size"])
    paths = [shard_path(out, set_name, k) for k in range(len(ranges))]
    missing = [p for p in paths if not p.exists()]
    if missing:
        raise FileNotFoundError(
            f"the {set_name!r} set in {out} is incomplete: {len(missing)} of {len(paths)} shards missing "
            f"(first {missing[0]}); run `lensdist generate --out {out}` to finish it"
        )
    recs = [load_shard(p, m["fingerprint"], expect=(set_name, a, b)) for p, (a, b) in zip(paths, ranges)]
    merged = {k: torch.cat([r[k] for r in recs]) for k in _TENSOR_KEYS}
    if limit is not None:
        merged = {k: v[:limit] for k, v in merged.items()}
    merged["config"] = config_from_dict(m["config"])
    return merged
