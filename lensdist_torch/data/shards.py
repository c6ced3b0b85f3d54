"""Generated data sets on disk: shards, manifest, resume (SPEC 7; issue: `lensdist generate`).

Layout of an output folder::

    manifest.json                 format version, config, fingerprint, scenes, sets, counts
    train/shard-00000.pt ...      pairs [0, 500), [500, 1000), ... of the training set
    test/shard-00000.pt           the test set (distorted pairs first, then class R)

A set is cut into fixed shards of ``protocol.shard_size`` pairs by pair index, so the same
command runs as an array job (``--shard I/N`` takes the shards k with k % N == I), shards merge
by pair index, and an interrupted run resumes by skipping the shards already on disk. Each
shard is written atomically (bytes to a temporary file, then ``os.replace``), and its bytes
depend only on the config and the pair indices: a resumed run gives byte-identical files.
Shards load with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import hashlib
import io
import json
import multiprocessing as mp
from pathlib import Path

import torch
from tqdm.auto import tqdm

from lensdist_torch.config import LensdistConfig, config_from_dict, config_to_dict
from lensdist_torch.core.images import load_image, load_scene
from lensdist_torch.core.storage import atomic_write_bytes
from lensdist_torch.data.synthesis import SETS, footprint, make_pairs, scene_zoom, sequence_footprint, set_size

__all__ = [
    "FORMAT_VERSION",
    "CLASS_KEYS",
    "ShardError",
    "config_fingerprint",
    "load_scenes",
    "shard_ranges",
    "shard_path",
    "write_shard",
    "load_shard",
    "generate_shard",
    "generate",
    "load_set",
    "read_manifest",
]

FORMAT_VERSION = 1
_KIND = "lensdist-shard"
_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}
MIN_ZOOM = 0.25  # a scene that must be magnified more than 4 x is too small to be a scene
_TENSOR_KEYS = (
    "index", "seed", "scene", "k2", "k4", "delta_avg", "delta_max", "class_avg", "class_max",
    "motion", "M", "H", "converged", "residual", "perturbed", "counts",
)


#: The config sections that change a data set's pairs (the fingerprint covers them).
_DATA_SECTIONS = ("quality", "image", "distortion", "protocol", "registration")

#: The per-pair class key of each Delta metric in a shard record.
CLASS_KEYS = {"delta_avg": "class_avg", "delta_max": "class_max"}


class ShardError(ValueError):
    """A shard file that is corrupted, foreign, or from another config or format version."""


def config_fingerprint(config: LensdistConfig, scene_ids: list[str]) -> str:
    """A hash of every setting that changes the pairs or the files: the quality, image,
    distortion, protocol and registration sections (chunk sizes do not; ``shard_size`` does,
    since it fixes which pairs each shard file holds), and the scenes."""
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
    return [(s, min(s + shard_size, n_pairs)) for s in range(0, n_pairs, shard_size)]


def shard_path(out: str | Path, set_name: str, k: int) -> Path:
    return Path(out) / set_name / f"shard-{k:05d}.pt"


def write_shard(path: str | Path, record: dict) -> None:
    """Save a shard atomically; the bytes depend only on ``record`` (never on the file name)."""
    buf = io.BytesIO()
    torch.save(record, buf)
    atomic_write_bytes(Path(path), buf.getvalue())


def load_shard(path: str | Path, fingerprint: str | None = None) -> dict:
    """Load and check a shard: kind, format version, keys, shapes, and optionally the config.

    Raises:
        ShardError: corrupted file, not a lensdist shard, another format version or config.
    """
    path = Path(path)
    try:
        rec = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as exc:
        raise ShardError(f"shard {path} is corrupted or not a torch file: {exc}") from exc
    if not isinstance(rec, dict) or rec.get("kind") != _KIND:
        raise ShardError(f"{path} is not a lensdist shard (kind {rec.get('kind') if isinstance(rec, dict) else None!r})")
    if rec.get("format_version") != FORMAT_VERSION:
        raise ShardError(f"shard {path} has format version {rec.get('format_version')}, expected {FORMAT_VERSION}")
    if fingerprint is not None and rec.get("fingerprint") != fingerprint:
        raise ShardError(
            f"shard {path} was generated with another config or scenes (fingerprint "
            f"{rec.get('fingerprint')}, expected {fingerprint})"
        )
    missing = [k for k in _TENSOR_KEYS if not isinstance(rec.get(k), torch.Tensor)]
    if missing:
        raise ShardError(f"shard {path} lacks {missing}")
    n = rec["end"] - rec["start"]
    if any(rec[k].shape[0] != n for k in _TENSOR_KEYS) or not torch.equal(
        rec["index"], torch.arange(rec["start"], rec["end"])
    ):
        raise ShardError(f"shard {path} is inconsistent: expected pairs [{rec['start']}, {rec['end']})")
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


def _shard_ok(path: Path, fingerprint: str, start: int, end: int) -> bool:
    if not path.exists():
        return False
    try:
        rec = load_shard(path, fingerprint)
    except ShardError:
        return False  # a foreign or corrupted file is regenerated, never trusted
    return (rec["start"], rec["end"]) == (start, end)  # e.g. a --limit run's shorter last shard


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
    """Generate the sets' shards that belong to ``shard`` = (I, N) and are not yet on disk.

    Returns a summary: pairs per set, shards written and skipped, and, once a set is
    complete, its counts (failed registrations, pairs per class).
    """
    out = Path(out)
    for s in sets:
        if s not in SETS:
            raise ValueError(f"sets must be among {SETS}, got {s!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    if not (isinstance(batch_size, int) and batch_size >= 1):
        raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
    if not (len(shard) == 2 and shard[1] >= 1 and 0 <= shard[0] < shard[1]):
        raise ValueError(f"shard must be (I, N) with 0 <= I < N, got {shard!r}")
    if sequence and scenes_dir is None:
        raise ValueError("sequence=True needs scenes_dir: the folder of the sequence's frames")
    scenes, scene_ids = load_scenes(config, scenes_dir, sequence)
    fp = config_fingerprint(config, scene_ids)
    manifest = {
        "format_version": FORMAT_VERSION,
        "fingerprint": fp,
        "config": config_to_dict(config),
        "scenes": scene_ids,
        "sets": {},
    }
    tasks = []
    for s in sets:
        n = set_size(config, s) if limit is None else min(limit, set_size(config, s))
        ranges = shard_ranges(n, config.protocol.shard_size)
        manifest["sets"][s] = {"n_pairs": n, "shard_size": config.protocol.shard_size, "n_shards": len(ranges)}
        for k, (a, b) in enumerate(ranges):
            if k % shard[1] == shard[0] and not _shard_ok(shard_path(out, s, k), fp, a, b):
                tasks.append((s, k, a, b))
    old = _read_json(out / "manifest.json")
    if old is not None and old.get("fingerprint") != fp:
        raise ValueError(
            f"{out} holds a data set of another config or scenes (fingerprint {old.get('fingerprint')}, "
            f"now {fp}); use another --out"
        )
    _write_json(out / "manifest.json", manifest)
    total = sum(b - a for _, _, a, b in tasks)
    bar = tqdm(total=total, unit="pair", desc="generate", disable=not progress)
    if workers == 1:
        # One thread, as in the worker processes: float32 reductions of the registration
        # depend on the thread count, and a shard's bytes must not depend on --workers.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            for s, k, a, b in tasks:
                rec = generate_shard(scenes, config, s, a, b, fp, batch_size, on_batch=bar.update, sequence=sequence)
                write_shard(shard_path(out, s, k), rec)
        finally:
            torch.set_num_threads(threads)
    elif tasks:
        cfg = config_to_dict(config)
        jobs = [(cfg, scenes_dir, sequence, s, k, a, b, fp, batch_size, str(out)) for s, k, a, b in tasks]
        with mp.get_context("spawn").Pool(workers) as pool:
            for n in pool.imap_unordered(_worker, jobs):
                bar.update(n)
    bar.close()
    summary = {"out": str(out), "written": len(tasks), "pairs_generated": total, "sets": {}}
    for s in sets:
        info = dict(manifest["sets"][s])
        paths = [shard_path(out, s, k) for k in range(info["n_shards"])]
        if all(p.exists() for p in paths):
            data = load_set(out, s, limit=info["n_pairs"])
            info["complete"] = True
            info["registration_failed"] = int((~data["converged"]).sum())
            info["pairs_per_class_avg"] = torch.bincount(data["class_avg"], minlength=5).tolist()
            info["pairs_per_class_max"] = torch.bincount(data["class_max"], minlength=5).tolist()
        else:
            info["complete"] = False
            info["shards_present"] = sum(p.exists() for p in paths)
        summary["sets"][s] = info
        manifest["sets"][s] = info
    _write_json(out / "manifest.json", manifest)
    return summary


def read_manifest(out: str | Path) -> dict:
    m = _read_json(Path(out) / "manifest.json")
    if m is None:
        raise FileNotFoundError(f"no manifest.json in {out}: run `lensdist generate --out {out}` first")
    if m.get("format_version") != FORMAT_VERSION:
        raise ShardError(f"{out}/manifest.json has format version {m.get('format_version')}, expected {FORMAT_VERSION}")
    return m


def load_set(out: str | Path, set_name: str, limit: int | None = None) -> dict:
    """Merge a set's shards by pair index into one dict of tensors; all shards must be present."""
    m = read_manifest(out)
    if set_name not in m["sets"]:
        raise ValueError(f"{out} holds no {set_name!r} set; it has {sorted(m['sets'])}")
    info = m["sets"][set_name]
    recs = [load_shard(shard_path(out, set_name, k), m["fingerprint"]) for k in range(info["n_shards"])]
    merged = {k: torch.cat([r[k] for r in recs]) for k in _TENSOR_KEYS}
    if not torch.equal(merged["index"], torch.arange(info["n_pairs"])):
        raise ShardError(f"the {set_name!r} shards in {out} do not hold pairs 0..{info['n_pairs'] - 1} in order "
                         "(a shard file renamed or copied over another?)")
    if limit is not None:
        merged = {k: v[:limit] for k, v in merged.items()}
    merged["config"] = config_from_dict(m["config"])
    return merged


def _read_json(path: Path):
    if not path.exists():
        return None
    return json.loads(path.read_text())


def _write_json(path: Path, data) -> None:
    atomic_write_bytes(path, (json.dumps(data, indent=2) + "\n").encode())
