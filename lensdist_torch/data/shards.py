"""Generated data sets on disk: generate, resume, load (`lensdist generate`; pairs of docs/method.md).

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

Nothing damaged is used and nothing recorded is lost: every shard read (``load_shard``,
``load_set``, the resume check) verifies its sha256 and place (``data/shardfile.py``), and a
bad shard is an error or, on resume, regenerated and reported; the manifest is validated, only
grows and is not rewritten when nothing changed (``data/manifest.py``); a run that writes holds
its share's lock file (``data/locks.py``). This module re-exports their public names.
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from lensdist_torch.config import LensdistConfig, config_from_dict, config_to_dict, stored_config
from lensdist_torch.core.images import IMAGE_SUFFIXES, load_image, load_scene
from lensdist_torch.core.outputs import refuse_foreign_folder
from lensdist_torch.core.threads import torch_threads
from lensdist_torch.data.locks import DataSetLocked, share_lock
from lensdist_torch.data.manifest import (
    FORMAT_VERSION,
    MANIFEST,
    ShardError,
    check_same_data,
    config_fingerprint,
    merge_manifest,
    read_manifest,
    save_manifest,
)
from lensdist_torch.data.shardfile import (
    KIND,
    TENSOR_KEYS,
    SetState,
    check_counts,
    checksum_path,
    load_shard,
    no_stray_shards,
    shard_path,
    shard_ranges,
    verify_set,
    write_shard,
)
from lensdist_torch.data.synthesis import SETS, footprint, make_pairs, scene_zoom, sequence_footprint, set_size
from lensdist_torch.data.workers import parent_alive, stop_on_sigterm, worker_pool

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

MIN_ZOOM = 0.25  # a scene that must be magnified more than 4 x is too small to be a scene

#: The per-pair class key of each Delta metric in a shard record.
CLASS_KEYS = {"delta_avg": "class_avg", "delta_max": "class_max"}


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
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ValueError(f"--scenes folder {folder} holds no image files ({sorted(IMAGE_SUFFIXES)})")
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


def _record(batches, set_name: str, start: int, end: int, fingerprint: str) -> dict:
    def cat(f):
        return torch.cat([f(b) for b in batches])

    return {
        "kind": KIND,
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


def generate_shard(scenes, *, config, set_name, start, end, fingerprint, batch_size=16, on_batch=None, sequence=False) -> dict:
    """Generate pairs [start, end) of a set as one shard record."""
    batches = []
    for s in range(start, end, batch_size):
        idx = list(range(s, min(s + batch_size, end)))
        batches.append(make_pairs(scenes, config=config, set_name=set_name, indices=idx, sequence=sequence))
        if on_batch is not None:
            on_batch(len(idx))
    return _record(batches, set_name, start, end, fingerprint)


def _worker(task):
    cfg_dict, scenes_dir, sequence, set_name, k, start, end, fingerprint, batch_size, out = task
    torch.set_num_threads(1)
    config = config_from_dict(cfg_dict)
    scenes, _ = load_scenes(config, scenes_dir, sequence)
    rec = generate_shard(scenes, config=config, set_name=set_name, start=start, end=end, fingerprint=fingerprint,
                         batch_size=batch_size, sequence=sequence)
    if not parent_alive():
        os._exit(0)  # orphaned: no shard written on behalf of a run that is gone, and no broken pipe
    write_shard(shard_path(out, set_name, k), rec)
    return end - start


# ---------------------------------------------------------------------------------- generate


def _note(msg: str) -> None:
    print(f"lensdist generate: {msg}", file=sys.stderr)


def _check_arguments(sets, shard, workers, batch_size, limit, scenes_dir, sequence) -> None:
    if isinstance(sets, str) or not isinstance(sets, (list, tuple)) or not sets:
        raise ValueError(f"sets must be a non-empty list of set names among {SETS}, got {sets!r}")
    for s in sets:
        if s not in SETS:
            raise ValueError(f"sets must be among {SETS}, got {s!r}")
    if not (type(workers) is int and workers >= 1):
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    if not (type(batch_size) is int and batch_size >= 1):
        raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
    if not (
        isinstance(shard, (tuple, list)) and len(shard) == 2 and all(type(v) is int for v in shard)
        and shard[1] >= 1 and 0 <= shard[0] < shard[1]
    ):
        raise ValueError(f"shard must be (I, N), two ints with 0 <= I < N, got {shard!r}")
    if limit is not None and not (type(limit) is int and limit >= 1):
        raise ValueError(f"limit must be a positive int, got {limit!r}")
    if sequence and scenes_dir is None:
        raise ValueError("sequence=True needs scenes_dir: the folder of the sequence's frames")


@dataclass
class _Plan:
    """What a run finds: the manifest on disk, its sets verified, and the shards its share must write."""

    old: dict | None
    states: dict[str, SetState]
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


def _recorded(old: dict | None, set_name: str, n_pairs: int, shard_size: int) -> list[str] | None:
    """The shard digests the manifest records for this very set (same pairs and shard size), if any."""
    rec = (old or {}).get("sets", {}).get(set_name)
    if rec and rec.get("complete") and rec["n_pairs"] == n_pairs and rec["shard_size"] == shard_size:
        return rec.get("shard_sha256")
    return None


def _plan(config, out: Path, fingerprint: str, sets, shard, limit) -> _Plan:
    old = read_manifest(out) if (out / MANIFEST).exists() else None
    check_same_data(out, old, fingerprint)
    sizes = _set_sizes(config, out, old, sets, limit)
    states = {
        s: verify_set(out, s, n_pairs=n, shard_size=config.protocol.shard_size, fingerprint=fingerprint,
                      recorded=_recorded(old, s, n, config.protocol.shard_size))
        for s, n in sizes.items()
    }
    tasks = [
        (s, k, a, b)
        for s, st in states.items()
        for k, (a, b) in enumerate(st.ranges)
        if k % shard[1] == shard[0] and k not in st.stats
    ]
    return _Plan(old=old, states=states, tasks=tasks)


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
        with torch_threads(1):
            for s, k, a, b in tasks:
                rec = generate_shard(scenes, config=config, set_name=s, start=a, end=b, fingerprint=fingerprint,
                                     batch_size=batch_size, on_batch=bar.update, sequence=sequence)
                write_shard(shard_path(out, s, k), rec)
    elif tasks:
        cfg = config_to_dict(config)
        jobs = [(cfg, scenes_dir, sequence, s, k, a, b, fingerprint, batch_size, str(out)) for s, k, a, b in tasks]
        with worker_pool(workers) as pool:  # workers ignore Ctrl-C and exit quietly if this process dies
            for n in pool.imap_unordered(_worker, jobs):
                bar.update(n)
    bar.close()
    return total


def generate(
    config: LensdistConfig,
    out: str | Path,
    *,
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
        ValueError: bad arguments; another config's data set, or other files and no data set, in
            ``out`` (``core.outputs.refuse_foreign_folder``); a ``limit`` that would shrink a recorded set.
        ShardError: a manifest that is not valid (naming the file).
        DataSetLocked: another live run over overlapping shares.

    Example:
        >>> import tempfile
        >>> cfg = config_from_dict({"protocol": {"n_test_distorted": 3, "n_test_undistorted": 1}})  # 4 test pairs
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     summary = generate(cfg, tmp, sets=["test"], progress=False)
        ...     again = generate(cfg, tmp, sets=["test"], progress=False)  # verified on disk: nothing to write
        >>> summary["pairs_generated"], summary["sets"]["test"]["complete"], again["written"]
        (4, True, 0)
    """
    out = Path(out)
    _check_arguments(sets, shard, workers, batch_size, limit, scenes_dir, sequence)
    refuse_foreign_folder(out, "`out`", SETS)  # someone's folder gets no data set written among its files
    scenes, scene_ids = load_scenes(config, scenes_dir, sequence)
    fp = config_fingerprint(config, scene_ids)
    header = {"format_version": FORMAT_VERSION, "fingerprint": fp, "config": config_to_dict(config), "scenes": scene_ids}
    plan = _plan(config, out, fp, sets, shard, limit)
    if not plan.tasks and merge_manifest(plan.old, header, plan.records()) == plan.old:
        return _summary(out, sets, plan.old, plan, pairs=0, workers=1, capped=None, written=False)
    with share_lock(out, shard):
        plan = _plan(config, out, fp, sets, shard, limit)  # again, under the lock
        written = save_manifest(out, header, plan.records())
        used, capped = _cap_workers(workers, len(plan.tasks))
        if capped:
            _note(capped)
        for s, k, _, _ in plan.tasks:
            if k in plan.states[s].bad:
                _note(f"regenerating {plan.states[s].bad[k]}")
        with stop_on_sigterm():  # SIGTERM: one line, the workers stopped, exit 143 (data/workers.py)
            pairs = _run_tasks(plan.tasks, out, config, scenes, scenes_dir, sequence, fp, batch_size, used, progress)
        sizes = {s: st.n_pairs for s, st in plan.states.items()}
        done = {s: verify_set(out, s, n_pairs=n, shard_size=config.protocol.shard_size, fingerprint=fp).record()
                for s, n in sizes.items()}
        written = save_manifest(out, header, done) or written
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
    """Merge a set's shards by pair index into one dict of tensors (the first ``limit`` pairs).

    The set must be recorded complete in the manifest, and every shard present and verified
    (sha256 against its checksum file and against the manifest's ``shard_sha256``, config,
    the pairs it holds); no shard file may lie beyond the recorded ones, and the pairs'
    failed registrations and classes must be the manifest's counts.

    Raises:
        FileNotFoundError: no manifest, or a shard missing (the set is incomplete).
        ShardError: naming the file: a manifest that is not valid, that records the set as
            incomplete or without shard digests, or that disagrees with the shards; a shard that
            fails a check.
        ValueError: no such set in the folder; ``limit`` not None or a positive int.

    Example:
        >>> import tempfile
        >>> cfg = config_from_dict({"protocol": {"n_test_distorted": 3, "n_test_undistorted": 1}})
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     _ = generate(cfg, tmp, sets=["test"], progress=False)
        ...     test = load_set(tmp, "test", limit=2)
        >>> tuple(test["k2"].shape), tuple(test["counts"].shape), test["config"] == cfg
        ((2,), (2, 1, 40, 53), True)
    """
    if limit is not None and not (type(limit) is int and limit >= 1):
        raise ValueError(f"limit must be None or a positive int, got {limit!r}")
    m = read_manifest(out)
    if set_name not in m["sets"]:
        raise ValueError(f"{out} holds no {set_name!r} set; it has {sorted(m['sets'])}")
    info = m["sets"][set_name]
    ranges = shard_ranges(info["n_pairs"], info["shard_size"])
    paths = [shard_path(out, set_name, k) for k in range(len(ranges))]
    missing = [p for p in paths if not p.exists()]
    run = f"run `lensdist generate --out {out}`"
    if missing:
        raise FileNotFoundError(
            f"the {set_name!r} set in {out} is incomplete: {len(missing)} of {len(paths)} shards missing "
            f"(first {missing[0]}); {run} to finish it"
        )
    where = Path(out) / MANIFEST
    if not info["complete"]:
        raise ShardError(f"{where} records the {set_name!r} set as incomplete; {run} to verify and record it")
    if "shard_sha256" not in info:
        raise ShardError(
            f"{where} records no shard digests for the {set_name!r} set (written by an older lensdist); "
            f"{run} to verify the shards and record them"
        )
    no_stray_shards(Path(out), set_name, len(ranges), info["n_pairs"])
    recs = [
        load_shard(p, m["fingerprint"], expect=(set_name, a, b), sha256=d)
        for p, (a, b), d in zip(paths, ranges, info["shard_sha256"])
    ]
    merged = {k: torch.cat([r[k] for r in recs]) for k in TENSOR_KEYS}
    check_counts(merged, info, where, set_name)
    if limit is not None:
        merged = {k: v[:limit] for k, v in merged.items()}
    merged["config"] = stored_config(m["config"])  # retired keys that never shaped the pairs dropped
    return merged
