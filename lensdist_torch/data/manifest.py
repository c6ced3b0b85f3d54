"""The manifest of a generated data set, ``manifest.json``.

It holds the format version, config, fingerprint and scenes, and per set its size and, once
complete, its counts and the sha256 of every shard file (``shard_sha256``; ``load_set`` checks
each shard against it, so a shard changed together with its checksum file is refused). Every
read validates it (one-line ShardError naming the file); a write merges a run's sets into
the recorded ones, so a set's record only grows and the sets a run was not asked for are kept,
and nothing is written when nothing changed (a complete, read-only data set can be re-checked).
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

from lensdist_torch.config import INERT, RETIRED, LensdistConfig, config_to_dict, retired_keys, stored_config
from lensdist_torch.config.quality import TEMPERATURES
from lensdist_torch.core.storage import atomic_write_bytes
from lensdist_torch.data.locks import lock
from lensdist_torch.data.synthesis import SETS, set_size

__all__ = [
    "FORMAT_VERSION",
    "MANIFEST",
    "N_CLASSES",
    "ShardError",
    "config_fingerprint",
    "data_config_difference",
    "read_manifest",
    "check_same_data",
    "merge_manifest",
    "save_manifest",
]

#: 2: a sha256 checksum file beside every shard, written and read by save/load_versioned.
FORMAT_VERSION = 2
MANIFEST = "manifest.json"
N_CLASSES = 5  # classes 1-4 and R, as stored in a shard's class_avg / class_max
_LOCK_WAIT_S = 30.0  # the manifest's lock is held for one read-merge-write only

#: The config sections that change a data set's pairs (the fingerprint covers them).
_DATA_SECTIONS = ("quality", "image", "distortion", "protocol", "registration")
#: Registration keys (a setting; constants now, the others) that only the analysis of a user's pair uses (the fallback).
_NOT_IN_DATA = ("feature_fallback", "max_keypoints", "match_ratio", "ransac_threshold", "min_inliers")
#: Per data section, its constants that were keys (``[registration]``, ``[protocol]``), at their values (lists for
#: tuples, as a config dict holds them): the fingerprint hashes them as it did the keys, so a data set keeps its own.
_CONSTANTS = {
    name: {key: list(r.value) if isinstance(r.value, tuple) else r.value
           for (section, key), r in RETIRED.items()
           if section == name and r.value is not None}
    for name in _DATA_SECTIONS
}


class ShardError(ValueError):
    """A shard or manifest file that is corrupted, foreign, or of another config or format version.

    The message names the file.
    """


def config_fingerprint(config: LensdistConfig, scene_ids: list[str]) -> str:
    """A hash of every setting that changes the pairs or the files, and of the scenes.

    The quality, image, distortion, protocol and registration sections count (chunk sizes do
    not; ``shard_size`` does, since it fixes which pairs each shard file holds; nor do the
    feature fallback's settings: the protocol's registration never uses it; nor
    ``protocol.unseen_scenes``).
    """
    d = {**_data_fields(config), "scenes": scene_ids}
    return hashlib.sha256(json.dumps(d, sort_keys=True, allow_nan=False).encode()).hexdigest()[:16]


def _data_fields(config: LensdistConfig) -> dict:
    """The config's sections and fields that change a data set's pairs (what the fingerprint covers)."""
    d = config_to_dict(config)
    d = {name: d[name] for name in _DATA_SECTIONS}
    for name in ("quality", "registration"):
        d[name].pop("chunk_size", None)
    for name in _DATA_SECTIONS:
        d[name].update(_CONSTANTS[name])  # the constants that were keys: a data set keeps its fingerprint
    d["quality"].pop("temperature")  # hashed as the four temperatures it scales, as when they were keys
    d["quality"].update({name: getattr(config.quality, name) for name in TEMPERATURES})
    for key in _NOT_IN_DATA:
        d["registration"].pop(key, None)
    d["protocol"].pop("unseen_scenes", None)  # only reproduce's extra test set reads it
    return d


def data_config_difference(data: LensdistConfig, other: LensdistConfig) -> str | None:
    """The first field that changes the pairs where ``other`` differs from a data set's config, or None.

    As "section.field (VALUE here, VALUE in the data)".
    """
    a, b = _data_fields(data), _data_fields(other)
    for section in _DATA_SECTIONS:
        for key in sorted(set(a[section]) | set(b[section])):
            if a[section].get(key) != b[section].get(key):
                return f"{section}.{key} ({b[section].get(key)!r} here, {a[section].get(key)!r} in the data)"
    return None


def read_manifest(out: str | Path) -> dict:
    """The validated manifest of a data set folder.

    Raises:
        FileNotFoundError: no manifest.json.
        ShardError: naming the file: not JSON, another format version, a missing or wrong field.
    """
    path = Path(out) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"no manifest.json in {out}: run `lensdist generate --out {out}` first")
    fix = "delete it and rerun `lensdist generate` to rebuild it from the verified shards"
    try:
        m = json.loads(path.read_bytes())
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError
        raise ShardError(f"{path} is not valid JSON ({' '.join(str(exc).split())}); {fix}") from None
    problem = _manifest_problem(m)
    if problem:
        raise ShardError(f"{path} is not a valid lensdist manifest: {problem}; {fix}")
    return m


def _manifest_problem(m) -> str | None:
    """What is wrong with a parsed manifest, or None."""
    if not isinstance(m, dict):
        return f"a JSON {type(m).__name__}, not an object"
    missing = [k for k in ("format_version", "fingerprint", "config", "scenes", "sets") if k not in m]
    if missing:
        return f"missing field(s) {missing}"
    if m["format_version"] != FORMAT_VERSION or isinstance(m["format_version"], bool):
        return (f"format version {m['format_version']!r}, this library reads {FORMAT_VERSION} "
                "(generate into another --out)")
    scenes = m["scenes"]
    if not (isinstance(scenes, list) and scenes and all(isinstance(s, str) for s in scenes)):
        return "scenes must be a non-empty list of names"
    inert = {".".join(k) for k in INERT}
    shaping = [k for k in retired_keys(m["config"]) if k not in inert] if isinstance(m["config"], dict) else []
    if shaping:
        return f"made by an earlier version of the pair protocol ({', '.join(shaping)}); generate into another --out"
    try:
        config = stored_config(m["config"])  # the inert retired keys dropped
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
    n, size, shard_size = rec.get("n_pairs"), set_size(config, name), config.protocol.shard_size
    if not _is_count(n, size):
        return f"n_pairs must be an int in [0, {size}], got {n!r}"
    if rec.get("shard_size") != shard_size:
        return f"shard_size {rec.get('shard_size')!r}, its config says {shard_size}"
    n_shards = -(-n // shard_size)
    if rec.get("n_shards") != n_shards:
        return f"n_shards {rec.get('n_shards')!r}, {n} pairs make {n_shards}"
    if not isinstance(rec.get("complete"), bool):
        return "complete must be true or false"
    if not rec["complete"]:
        if _is_count(rec.get("shards_present"), n_shards):
            return None
        return f"shards_present must be an int in [0, {n_shards}]"
    if not _is_count(rec.get("registration_failed"), n):
        return f"registration_failed must be an int in [0, {n}]"
    for key in ("pairs_per_class_avg", "pairs_per_class_max"):
        v = rec.get(key)
        if not (isinstance(v, list) and len(v) == N_CLASSES and all(_is_count(c, n) for c in v) and sum(v) == n):
            return f"{key} must be {N_CLASSES} counts summing to n_pairs {n}"
    digests = rec.get("shard_sha256")  # absent in a record of an older lensdist: load_set asks for a re-check
    if digests is not None and not (
        isinstance(digests, list) and len(digests) == n_shards
        and all(isinstance(d, str) and _SHA256.fullmatch(d) for d in digests)
    ):
        return f"shard_sha256 must list {n_shards} sha256 digests (hex), one per shard"
    return None


_SHA256 = re.compile(r"[0-9a-f]{64}")


def check_same_data(out: Path, manifest: dict | None, fingerprint: str) -> None:
    """ValueError if ``out`` records a data set of another config or scenes."""
    if manifest is not None and manifest["fingerprint"] != fingerprint:
        raise ValueError(
            f"{out} holds a data set of another config or scenes (fingerprint {manifest['fingerprint']}, "
            f"now {fingerprint}); use another --out"
        )


def merge_manifest(old: dict | None, header: dict, records: dict[str, dict]) -> dict:
    """``header`` + the recorded sets + ``records``; a set's record only grows (more pairs wins)."""
    sets = dict(old["sets"]) if old else {}
    for name, rec in records.items():
        if name not in sets or sets[name]["n_pairs"] <= rec["n_pairs"]:
            sets[name] = rec
    return json.loads(json.dumps({**header, "sets": sets}, allow_nan=False))  # as read back: lists, not tuples


def save_manifest(out: Path, header: dict, records: dict[str, dict]) -> bool:
    """Merge ``records`` into the manifest on disk and write it if anything changed (returns whether).

    The read-merge-write holds ``.manifest.lock``: runs of other shares may finish meanwhile.
    """
    out = Path(out)
    with lock(out / ".manifest.lock", wait_s=_LOCK_WAIT_S):
        old = read_manifest(out) if (out / MANIFEST).exists() else None
        check_same_data(out, old, header["fingerprint"])
        new = merge_manifest(old, header, records)
        if new == old:
            return False
        atomic_write_bytes(out / MANIFEST, (json.dumps(new, indent=2, allow_nan=False) + "\n").encode())
        return True
