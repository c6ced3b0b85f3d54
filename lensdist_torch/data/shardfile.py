"""One shard file of a generated data set, and the check of a set's shards on disk.

A shard is written with the library's versioned writer (``save_versioned``, atomic), then a
checksum file beside it (``shard-00000.pt.sha256``, one ``sha256sum`` line) with the sha256 of
its bytes. ``load_shard`` verifies that digest before it unpickles (``load_versioned``,
``torch.load(weights_only=True)``), then the kind, format version, config fingerprint, keys,
shapes and the pairs the shard must hold: a changed byte, a truncated file or a shard copied
over another is a one-line ShardError naming the file, never data. A shard is also checked
against the sha256 the manifest recorded for it (a shard rewritten together with its checksum
file), and a set's shards against the manifest's counts and shard count (``check_counts``,
``no_stray_shards``: an edited manifest).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import torch

from lensdist_torch.core.storage import atomic_write_bytes, load_versioned, save_versioned
from lensdist_torch.data.manifest import FORMAT_VERSION, MANIFEST, N_CLASSES, ShardError

__all__ = [
    "KIND",
    "TENSOR_KEYS",
    "SetState",
    "shard_ranges",
    "shard_path",
    "checksum_path",
    "write_shard",
    "load_shard",
    "verify_set",
    "no_stray_shards",
    "check_counts",
]

KIND = "lensdist-shard"
TENSOR_KEYS = (
    "index", "seed", "scene", "k2", "k4", "delta_avg", "delta_max", "class_avg", "class_max",
    "motion", "M", "H", "converged", "residual", "perturbed", "counts",
)


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
    digest = save_versioned(path, KIND, FORMAT_VERSION, record, digest=False)  # the checksum file covers it
    atomic_write_bytes(checksum_path(path), _checksum_line(digest, path.name).encode())
    return digest


def load_shard(
    path: str | Path, fingerprint: str | None = None, expect: tuple[str, int, int] | None = None, sha256: str | None = None
) -> dict:
    """Load and check a shard: its sha256, kind, format version, keys and shapes.

    Optionally also the config (``fingerprint``), the pairs it must hold (``expect`` =
    (set, start, end)) and the sha256 the manifest recorded for it (``sha256``: a shard
    changed together with its checksum file is refused).

    Raises:
        FileNotFoundError: no such shard.
        ShardError: naming the file: no or another checksum (changed bytes, truncated, copied
            over another shard), not a lensdist shard, another format version, config or place.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"shard not found: {path}")
    digest = _read_checksum(path)
    rec = load_versioned(path, kind=KIND, version=FORMAT_VERSION, what="data-set", sha256=digest, error=ShardError, noun="shard")
    if fingerprint is not None and rec.get("fingerprint") != fingerprint:
        raise ShardError(
            f"shard {path} was generated with another config or scenes (fingerprint "
            f"{rec.get('fingerprint')}, expected {fingerprint})"
        )
    missing = [k for k in TENSOR_KEYS if not isinstance(rec.get(k), torch.Tensor)]
    if missing:
        raise ShardError(f"shard {path} lacks {missing}")
    start, end = rec.get("start"), rec.get("end")
    if not (type(start) is int and type(end) is int and 0 <= start < end):
        raise ShardError(f"shard {path} has no valid pair range (start {start!r}, end {end!r})")
    n = end - start
    if any(rec[k].shape[0] != n for k in TENSOR_KEYS) or not torch.equal(rec["index"], torch.arange(start, end)):
        raise ShardError(f"shard {path} is inconsistent: expected pairs [{start}, {end})")
    if expect is not None and (rec.get("set"), start, end) != tuple(expect):
        raise ShardError(
            f"shard {path} holds {rec.get('set')!r} pairs [{start}, {end}), expected {expect[0]!r} pairs "
            f"[{expect[1]}, {expect[2]}) (a shard copied over another, or left by a shorter --limit run)"
        )
    if sha256 is not None and digest != sha256:  # last: the checks above name what is wrong more precisely
        raise ShardError(
            f"shard {path} is not the one recorded in {MANIFEST}: its sha256 differs from the manifest's "
            "(the shard and its checksum file were changed)"
        )
    return rec


@dataclass
class SetState:
    """One set of ``n_pairs`` pairs on disk: each shard verified, missing, or bad (and why)."""

    name: str
    n_pairs: int
    shard_size: int
    stats: dict[int, tuple[int, torch.Tensor, torch.Tensor]] = field(default_factory=dict)
    bad: dict[int, str] = field(default_factory=dict)
    digests: dict[int, str] = field(default_factory=dict)

    @property
    def ranges(self) -> list[tuple[int, int]]:
        """The pairs [start, end) of each shard."""
        return shard_ranges(self.n_pairs, self.shard_size)

    def record(self) -> dict:
        """The set's manifest record: its size and, once every shard is verified, its counts."""
        n_shards = len(self.ranges)
        rec = {"n_pairs": self.n_pairs, "shard_size": self.shard_size, "n_shards": n_shards}
        if len(self.stats) < n_shards:
            return {**rec, "complete": False, "shards_present": len(self.stats)}
        failed, per_avg, per_max = zip(*self.stats.values()) if self.stats else ((), (), ())
        zero = torch.zeros(N_CLASSES, dtype=torch.long)
        return {
            **rec,
            "complete": True,
            "registration_failed": sum(failed),
            "pairs_per_class_avg": sum(per_avg, zero).tolist(),
            "pairs_per_class_max": sum(per_max, zero).tolist(),
            "shard_sha256": [self.digests[k] for k in range(n_shards)],
        }


def verify_set(
    out: Path, set_name: str, *, n_pairs: int, shard_size: int, fingerprint: str, recorded: list[str] | None = None
) -> SetState:
    """Verify every shard of a set of ``n_pairs`` (checksum, config, pairs held).

    ``recorded``: the sha256 per shard the manifest holds for this very set (same pairs and
    shard size); a shard that differs from it is bad (regenerated: a shard's bytes are a pure
    function of the config and its pairs).
    """
    state = SetState(name=set_name, n_pairs=n_pairs, shard_size=shard_size)
    for k, (a, b) in enumerate(state.ranges):
        path = shard_path(out, set_name, k)
        if not path.exists():
            continue
        try:
            rec = load_shard(path, fingerprint, expect=(set_name, a, b), sha256=recorded[k] if recorded else None)
            digest = _read_checksum(path)
        except FileNotFoundError:
            continue  # removed meanwhile: missing
        except ShardError as exc:
            state.bad[k] = str(exc)  # corrupted, foreign or another range: regenerated, never trusted
            continue
        state.digests[k] = digest
        state.stats[k] = (
            int((~rec["converged"]).sum()),
            torch.bincount(rec["class_avg"], minlength=N_CLASSES),
            torch.bincount(rec["class_max"], minlength=N_CLASSES),
        )
    return state


def no_stray_shards(out: Path, set_name: str, n_shards: int, n_pairs: int) -> None:
    """ShardError if the set's folder holds a shard file beyond the ones the manifest records."""
    for p in sorted((out / set_name).glob("shard-*.pt")):
        name = re.fullmatch(r"shard-(\d{5})\.pt", p.name)
        if name and int(name[1]) >= n_shards:
            raise ShardError(
                f"{p} lies beyond the {n_shards} shards ({n_pairs} pairs) that {out / MANIFEST} records for the "
                f"{set_name!r} set: the manifest was edited or the shard left by another run"
            )


def check_counts(merged: dict, info: dict, where: Path, set_name: str) -> None:
    """ShardError naming the manifest where its counts are not those of the shards' pairs."""
    have = {
        "n_pairs": int(merged["index"].numel()),
        "registration_failed": int((~merged["converged"]).sum()),
        "pairs_per_class_avg": torch.bincount(merged["class_avg"], minlength=N_CLASSES).tolist(),
        "pairs_per_class_max": torch.bincount(merged["class_max"], minlength=N_CLASSES).tolist(),
    }
    for key, value in have.items():
        if info[key] != value:
            raise ShardError(
                f"{where} records {key} {info[key]} for the {set_name!r} set, but its shards hold {value}: "
                "the manifest was edited"
            )
