"""Integrity of generated data sets (lensdist_torch/data/shards.py; `lensdist generate`):
corrupted shards are never used, the manifest is validated and never shrinks, one run at a
time writes a share, the worker count is capped, and a rerun with nothing to do writes nothing.

One tiny reference data set (the one of test_shards.py: 96 x 128 views, 8 training and 4 + 2
test pairs, shards of 4; tests/generated_sets.py) is generated once per module and copied for each
test that changes it (tests/data/conftest.py).
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import socket
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from generated_sets import TINY_CFG as CFG
from one_line import one_line

from lensdist_torch.cli import main as cli_main
from lensdist_torch.data import locks, manifest, shardfile, shards
from lensdist_torch.data.shards import (
    FORMAT_VERSION,
    DataSetLocked,
    ShardError,
    checksum_path,
    generate,
    load_set,
    load_shard,
    read_manifest,
    shard_path,
    write_shard,
)

ROOT = Path(__file__).resolve().parents[2]


def snapshot(out: Path) -> dict[str, tuple[str, int]]:
    """Every file of a folder (hidden ones included): its sha256 and mtime."""
    return {
        str(p.relative_to(out)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
        for p in sorted(out.rglob("*"))
        if p.is_file()
    }


def flip(path: Path, offset: int, mask: int = 0xFF) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))




# ---------------------------------------------------------------------------------- shard bytes


@pytest.mark.bad_input
class TestCorruptedShard:
    def test_every_byte_flip_is_detected(self, data):
        """50 random offsets over the whole file (header, pickle, tensor bytes, zip directory)."""
        path = shard_path(data, "train", 0)
        good = path.read_bytes()
        fp = read_manifest(data)["fingerprint"]
        rng = random.Random(0)
        offsets = rng.sample(range(len(good)), 50)
        for offset in offsets:
            flip(path, offset, rng.randrange(1, 256))
            with pytest.raises(ShardError, match=r"train/shard-00000\.pt is corrupted") as exc:
                load_shard(path, fp)
            one_line(exc)
            path.write_bytes(good)
        assert load_shard(path, fp)["index"].tolist() == [0, 1, 2, 3]

    def test_tensor_bytes_are_covered(self, data):
        """A flip inside the stored counts (the maps) is caught, not loaded as other values."""
        path = shard_path(data, "train", 1)
        rec = load_shard(path)
        raw = rec["counts"].numpy().tobytes()
        offset = path.read_bytes().find(raw[:64])
        assert offset > 0
        flip(path, offset + 10, 0x01)
        with pytest.raises(ShardError, match="corrupted"):
            load_shard(path)

    def test_flip_in_the_checksum_file(self, data):
        path = shard_path(data, "test", 0)
        for offset in (0, 63, 66, 80):
            side = checksum_path(path)
            good = side.read_bytes()
            flip(side, offset, 0x01)
            with pytest.raises(ShardError, match=r"test/shard-00000\.pt"):
                load_shard(path)
            side.write_bytes(good)

    def test_truncated(self, data):
        path = shard_path(data, "test", 1)
        good = path.read_bytes()
        for n in (0, 1, 100, len(good) // 2, len(good) - 1):
            path.write_bytes(good[:n])
            with pytest.raises(ShardError, match=r"test/shard-00001\.pt is corrupted"):
                load_shard(path)
        path.write_bytes(good + b"\0")  # and one byte longer
        with pytest.raises(ShardError, match="corrupted"):
            load_shard(path)

    def test_swapped_shards(self, data):
        """Two shard files swapped: both fail; swapped with their checksum files, the checksum
        line names the other file; with matching checksum lines, the pairs held are wrong."""
        a, b = shard_path(data, "train", 0), shard_path(data, "train", 1)
        ba, bb = a.read_bytes(), b.read_bytes()
        a.write_bytes(bb)
        b.write_bytes(ba)
        for p in (a, b):
            with pytest.raises(ShardError, match="corrupted"):
                load_shard(p)
        ca, cb = checksum_path(a).read_text(), checksum_path(b).read_text()
        checksum_path(a).write_text(cb)
        checksum_path(b).write_text(ca)
        with pytest.raises(ShardError, match="damaged"):
            load_shard(a)
        checksum_path(a).write_text(cb.replace("00001", "00000"))
        checksum_path(b).write_text(ca.replace("00000", "00001"))
        with pytest.raises(ShardError, match=r"holds 'train' pairs \[4, 8\), expected 'train' pairs \[0, 4\)"):
            load_shard(a, expect=("train", 0, 4))
        with pytest.raises(ShardError, match="expected 'train' pairs"):
            load_set(data, "train")

    def test_test_shard_in_place_of_a_train_shard(self, data):
        """Same pair range, same config, valid checksum: still the wrong set."""
        rec = load_shard(shard_path(data, "test", 0))
        write_shard(shard_path(data, "train", 0), rec)
        with pytest.raises(ShardError, match="holds 'test' pairs"):
            load_set(data, "train")
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 1 and "holds 'test' pairs" in summary["regenerated"][0]
        assert load_set(data, "train")["index"].tolist() == list(range(8))

    def test_missing_checksum_file(self, data):
        checksum_path(shard_path(data, "train", 1)).unlink()
        with pytest.raises(ShardError, match="no checksum file"):
            load_set(data, "train")
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 1 and "no checksum file" in summary["regenerated"][0]
        load_set(data, "train")

    def test_older_format_version(self, data):
        rec = load_shard(shard_path(data, "train", 0))
        write_shard(shard_path(data, "train", 0), {**rec, "format_version": 1})
        with pytest.raises(ShardError, match=f"format version 1, this library reads {FORMAT_VERSION}"):
            load_set(data, "train")

    def test_load_set_refuses_and_generate_regenerates(self, reference, data, capsys):
        """The audit's case: a changed byte loaded as changed values, and `written: 0`."""
        path = shard_path(data, "train", 0)
        flip(path, len(path.read_bytes()) // 2)
        with pytest.raises(ShardError, match=r"train/shard-00000\.pt is corrupted") as exc:
            load_set(data, "train")
        one_line(exc)
        capsys.readouterr()
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 1 and summary["pairs_generated"] == 4
        assert summary["regenerated"] == [f"shard {path} is corrupted: its sha256 is not the one recorded when it was written"]
        assert "regenerating shard" in capsys.readouterr().err
        assert snapshot(data).keys() == snapshot(reference).keys()
        assert path.read_bytes() == shard_path(reference, "train", 0).read_bytes()  # byte-identical again
        # marked incomplete while the shard was regenerated, then complete again: as before
        assert (data / "manifest.json").read_bytes() == (reference / "manifest.json").read_bytes()

    def test_command_line_error_is_one_line(self, data, tmp_path, capsys):
        flip(shard_path(data, "train", 1), 200)
        code = cli_main(["train", "--data", str(data), "--out", str(tmp_path / "c.pt")])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "train/shard-00001.pt is corrupted" in err
        assert not (tmp_path / "c.pt").exists()


# ---------------------------------------------------------------------------------- manifest


def _edit(m: dict, how: str) -> dict | list | str:
    if how == "not an object":
        return [m]
    if how == "no sets":
        del m["sets"]
    elif how == "old format version":
        m["format_version"] = 1
    elif how == "edited config":
        m["config"]["protocol"]["n_train"] = 4
    elif how == "unknown config key":
        m["config"]["image"]["colour"] = True
    elif how == "edited fingerprint":
        m["fingerprint"] = "0" * 16
    elif how == "no scenes":
        m["scenes"] = []
    elif how == "n_pairs a string":
        m["sets"]["train"]["n_pairs"] = "8"
    elif how == "n_pairs too large":
        m["sets"]["test"]["n_pairs"] = 7
    elif how == "wrong n_shards":
        m["sets"]["train"]["n_shards"] = 3
    elif how == "no complete":
        del m["sets"]["train"]["complete"]
    elif how == "counts do not add up":
        m["sets"]["test"]["pairs_per_class_avg"][0] += 1
    elif how == "unknown set":
        m["sets"]["val"] = m["sets"]["test"]
    return m


MANIFEST_EDITS = [
    ("not an object", "a JSON list, not an object"),
    ("no sets", r"missing field\(s\) \['sets'\]"),
    ("old format version", "format version 1, this library reads"),
    ("edited config", "fingerprint .* does not match"),
    ("unknown config key", "config: unknown key"),
    ("edited fingerprint", "fingerprint '0+' does not match its config"),
    ("no scenes", "scenes"),
    ("n_pairs a string", "sets.train: n_pairs must be an int"),
    ("n_pairs too large", r"sets.test: n_pairs must be an int in \[0, 6\]"),
    ("wrong n_shards", "sets.train: n_shards 3"),
    ("no complete", "sets.train: complete"),
    ("counts do not add up", "sets.test: pairs_per_class_avg"),
    ("unknown set", "sets.val: unknown set"),
]


@pytest.mark.bad_input
class TestManifest:
    @pytest.mark.parametrize("text", ["", "{", '{"format_version": 2,', "\xff\xfe", "null"])
    def test_malformed_json(self, data, text):
        (data / "manifest.json").write_bytes(text.encode("latin-1"))
        for call in (lambda: read_manifest(data), lambda: load_set(data, "train"), lambda: generate(CFG, data, progress=False)):
            with pytest.raises(ShardError, match=r"manifest\.json is not") as exc:
                call()
            one_line(exc)

    @pytest.mark.parametrize("how,match", MANIFEST_EDITS, ids=[h for h, _ in MANIFEST_EDITS])
    def test_wrong_fields(self, data, how, match):
        path = data / "manifest.json"
        path.write_text(json.dumps(_edit(json.loads(path.read_text()), how)))
        before = snapshot(data)
        with pytest.raises(ShardError, match=r"manifest\.json is not a valid lensdist manifest: " + match) as exc:
            load_set(data, "test")
        one_line(exc)
        with pytest.raises(ShardError, match=match):
            generate(CFG, data, progress=False)
        assert snapshot(data) == before  # a damaged manifest is reported, never overwritten

    def test_rebuilt_from_the_shards(self, reference, data):
        """The way out the error names: delete the manifest; the verified shards are kept."""
        (data / "manifest.json").write_text("{")
        (data / "manifest.json").unlink()
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 0 and summary["manifest"] == "written"
        assert (data / "manifest.json").read_bytes() == (reference / "manifest.json").read_bytes()


# ---------------------------------------------------------------------------------- never shrink


class TestNeverShrink:
    @pytest.mark.bad_input
    def test_limit_into_a_complete_set_is_refused(self, reference, data):
        before = snapshot(data)
        with pytest.raises(ValueError, match=r"records 8 train pairs; --limit 5 would shrink"):
            generate(CFG, data, limit=5, progress=False)
        with pytest.raises(ValueError, match=r"records 6 test pairs; --limit 3 would shrink"):
            generate(CFG, data, sets=["test"], limit=3, progress=False)
        assert snapshot(data) == before
        assert load_set(data, "test")["index"].tolist() == list(range(6))

    @pytest.mark.bad_input
    def test_limit_into_a_larger_unfinished_set_is_refused(self, data):
        for k in (0, 1):
            shard_path(data, "test", k).unlink()
        generate(CFG, data, sets=["test"], shard=(0, 2), progress=False)  # the record: 6 pairs, 1 of 2 shards
        m = read_manifest(data)["sets"]["test"]
        assert (m["n_pairs"], m["complete"], m["shards_present"]) == (6, False, 1)
        before = snapshot(data)
        with pytest.raises(ValueError, match="would shrink"):
            generate(CFG, data, sets=["test"], limit=4, progress=False)
        assert snapshot(data) == before

    def test_limit_as_large_as_the_set_is_a_no_op(self, data):
        before = snapshot(data)
        summary = generate(CFG, data, limit=8, progress=False)
        assert summary["written"] == 0 and summary["manifest"] == "unchanged"
        assert snapshot(data) == before

    def test_a_limited_set_grows(self, tmp_path):
        out = tmp_path / "d"
        generate(CFG, out, sets=["test"], limit=2, progress=False)
        grown = generate(CFG, out, sets=["test"], limit=5, progress=False)
        assert grown["written"] == 2 and grown["sets"]["test"]["n_pairs"] == 5
        assert load_set(out, "test")["index"].tolist() == list(range(5))

    def test_other_sets_are_kept(self, reference, data):
        summary = generate(CFG, data, sets=["test"], progress=False)
        assert summary["written"] == 0 and list(summary["sets"]) == ["test"]
        m = read_manifest(data)
        assert m == read_manifest(reference)
        assert load_set(data, "train")["index"].tolist() == list(range(8))

    def test_sets_added_one_by_one(self, reference, tmp_path):
        out = tmp_path / "d"
        generate(CFG, out, sets=["test"], progress=False)
        generate(CFG, out, sets=["train"], progress=False)
        assert sorted(read_manifest(out)["sets"]) == ["test", "train"]
        assert read_manifest(out)["sets"] == read_manifest(reference)["sets"]
        generate(CFG, out, sets=["test"], progress=False)
        assert "train" in read_manifest(out)["sets"]


# ---------------------------------------------------------------------------------- lock

_HOLD_LOCK = """\
import sys, time
from pathlib import Path
from lensdist_torch.data.locks import share_lock
with share_lock(Path(sys.argv[1]), (int(sys.argv[2]), int(sys.argv[3]))):
    print("locked", flush=True)
    time.sleep(120)
"""


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.bad_input
class TestLock:
    def test_second_concurrent_run_is_refused_then_takes_over(self, data, capsys):
        """Another process holds the share's lock: refused, nothing written; once it died
        (killed, its lock left behind), the lock is taken over."""
        shard_path(data, "test", 1).unlink()
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        holder = subprocess.Popen(
            [sys.executable, "-c", _HOLD_LOCK, str(data), "0", "1"], stdout=subprocess.PIPE, text=True, env=env
        )
        try:
            assert holder.stdout.readline() == "locked\n"
            before = snapshot(data)
            with pytest.raises(DataSetLocked, match=rf"pid {holder.pid} on .*delete .*\.lock-0-of-1") as exc:
                generate(CFG, data, progress=False)
            one_line(exc)
            with pytest.raises(DataSetLocked):  # an overlapping share too
                generate(CFG, data, shard=(1, 2), progress=False)
            assert snapshot(data) == before
        finally:
            holder.kill()
            holder.wait()
            holder.stdout.close()
        assert (data / ".lock-0-of-1").exists()  # killed: left behind
        capsys.readouterr()
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 1
        assert "taking over the stale lock" in capsys.readouterr().err
        assert not list(data.glob(".*lock*"))

    def test_stale_lock_is_taken_over(self, data):
        shard_path(data, "train", 0).unlink()
        (data / ".lock-0-of-1").write_text(f"{_dead_pid()} {socket.gethostname()}\n")
        assert generate(CFG, data, progress=False)["written"] == 1
        assert not (data / ".lock-0-of-1").exists()

    def test_own_pid_in_a_left_lock_is_stale(self, data):
        """A pid reused after a crash (e.g. in a restarted container) does not block forever."""
        shard_path(data, "train", 0).unlink()
        (data / ".lock-0-of-1").write_text(f"{os.getpid()} {socket.gethostname()}\n")
        assert generate(CFG, data, progress=False)["written"] == 1

    def test_live_lock_of_another_share(self, data):
        """Array-job shares that do not overlap run side by side; overlapping ones are refused."""
        for k in (0, 1):
            shard_path(data, "train", k).unlink()
        live = os.getppid()
        (data / ".lock-0-of-2").write_text(f"{live} {socket.gethostname()}\n")
        with pytest.raises(DataSetLocked, match=r"\.lock-0-of-2"):
            generate(CFG, data, progress=False)  # 0/1 overlaps every share
        with pytest.raises(DataSetLocked, match=r"\.lock-0-of-2"):
            generate(CFG, data, shard=(2, 4), progress=False)  # 2 = 0 mod gcd(2, 4)
        summary = generate(CFG, data, shard=(1, 2), progress=False)
        assert summary["written"] == 1  # train 1 (test 1 is there)
        assert (data / ".lock-0-of-2").exists()  # the other run's lock is left alone
        assert not (data / ".lock-1-of-2").exists()

    def test_lock_of_another_host_is_not_taken_over(self, data):
        shard_path(data, "train", 0).unlink()
        (data / ".lock-0-of-1").write_text(f"{_dead_pid()} some-other-node\n")
        with pytest.raises(DataSetLocked, match="on some-other-node"):
            generate(CFG, data, progress=False)

    def test_lock_released_after_a_failed_run(self, data, monkeypatch):
        shard_path(data, "train", 0).unlink()

        def boom(*args, **kwargs):
            raise RuntimeError("interrupted")

        monkeypatch.setattr(shards, "_run_tasks", boom)
        with pytest.raises(RuntimeError, match="interrupted"):
            generate(CFG, data, progress=False)
        assert not list(data.glob(".*lock*"))


# ---------------------------------------------------------------------------------- workers


class TestWorkers:
    @pytest.mark.bad_input
    def test_thousand_workers_are_capped(self, tmp_path, capsys):
        summary = generate(CFG, tmp_path / "d", sets=["test"], limit=2, workers=1000, progress=False)
        assert summary["workers"] == 1 and summary["written"] == 1
        assert summary["workers_capped"].startswith("--workers 1000 capped to 1 (1 shards to write")
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--workers 1000 capped to 1" in err

    def test_cap_is_the_smallest_of_workers_tasks_cpus(self, monkeypatch):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
        assert shards._cap_workers(1000, 100)[0] == 4
        assert shards._cap_workers(1000, 3)[0] == 3
        assert shards._cap_workers(2, 100) == (2, None)
        assert shards._cap_workers(8, 0) == (1, None)  # nothing to write: no note


# ---------------------------------------------------------------------------------- nothing to do, nothing written


class TestNoOpRerun:
    def test_nothing_written(self, data):
        before = snapshot(data)
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 0 and summary["manifest"] == "unchanged"
        assert summary["sets"]["train"]["complete"] and summary["sets"]["test"]["complete"]
        assert snapshot(data) == before  # manifest bytes and mtime included; no lock left

    def test_read_only_folder(self, data):
        """chmod -w on the folder and its files (root can still write: the snapshot shows that
        nothing was), then a re-check and a load."""
        paths = [data, *data.rglob("*")]
        modes = {p: p.stat().st_mode for p in paths}
        before = snapshot(data)
        try:
            for p in paths:
                p.chmod(stat.S_IMODE(modes[p]) & ~0o222)
            summary = generate(CFG, data, progress=False)
            assert summary["written"] == 0 and summary["manifest"] == "unchanged"
            assert load_set(data, "test")["index"].tolist() == list(range(6))
        finally:
            for p in reversed(paths):
                p.chmod(modes[p])
        assert snapshot(data) == before

    def test_no_write_is_attempted(self, data, monkeypatch):
        """As on a read-only file system: every write of the module fails, and the re-check passes."""

        def refuse(*args, **kwargs):
            raise PermissionError("read-only file system")

        for module, name in [
            (shardfile, "atomic_write_bytes"), (shardfile, "save_versioned"), (manifest, "atomic_write_bytes"), (locks, "_try_lock"),
        ]:
            monkeypatch.setattr(module, name, refuse)
        summary = generate(CFG, data, progress=False)
        assert summary["written"] == 0 and summary["manifest"] == "unchanged"
        # while a run that must write says so
        shard_path(data, "test", 0).unlink()
        with pytest.raises(PermissionError):
            generate(CFG, data, progress=False)
