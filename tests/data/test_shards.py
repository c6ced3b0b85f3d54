"""Tests of generated data sets on disk (docs/method.md; `lensdist generate`) in lensdist_torch/data/shards.py.

One tiny reference data set (96 x 128 views, 8 training and 4 + 2 test pairs, shards of 4) is
generated once per module; array-job shares, resumed runs, worker processes and the command
line must all reproduce its files byte for byte.
"""

from __future__ import annotations

import filecmp
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from generated_sets import TINY, generate_once
from generated_sets import TINY_CFG as CFG

from lensdist_torch.cli import main as cli_main
from lensdist_torch.config import config_from_dict, config_to_dict
from lensdist_torch.data.shards import (
    FORMAT_VERSION,
    ShardError,
    checksum_path,
    config_fingerprint,
    generate,
    load_scenes,
    load_set,
    load_shard,
    read_manifest,
    shard_path,
    shard_ranges,
    write_shard,
)
from lensdist_torch.data.synthesis import make_pairs
from lensdist_torch.geometry.distortion import REJECT

TINY_TOML = """\
[image]
height = 96
width = 128

[protocol]
n_train = 8
n_test_distorted = 4
n_test_undistorted = 2
shard_size = 4
"""
SHARDS = [("train", 0), ("train", 1), ("test", 0), ("test", 1)]


def data_files(out: Path) -> list[str]:
    """Every file of a data set folder, relative, sorted (hidden temporary files included)."""
    return sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())


def assert_same_shards(a: Path, b: Path, shards=SHARDS) -> None:
    for s, k in shards:
        pa, pb = shard_path(a, s, k), shard_path(b, s, k)
        assert pb.exists(), pb
        assert filecmp.cmp(pa, pb, shallow=False), f"{s}/{pb.name} differs"


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, dict]:
    """The tiny data set and generate's summary of it."""
    return generate_once(tmp_path_factory, "data")


def png(path: Path, img: torch.Tensor) -> Path:
    """Write a (H, W) uint8 image as PNG."""
    from kornia.io import write_image

    write_image(path, img[None].contiguous())
    return path


# ---------------------------------------------------------------------------------- layout


class TestLayout:
    def test_files_and_summary(self, reference):
        out, summary = reference
        assert data_files(out) == [
            "manifest.json",
            "test/shard-00000.pt",
            "test/shard-00000.pt.sha256",
            "test/shard-00001.pt",
            "test/shard-00001.pt.sha256",
            "train/shard-00000.pt",
            "train/shard-00000.pt.sha256",
            "train/shard-00001.pt",
            "train/shard-00001.pt.sha256",
        ]
        assert summary["written"] == 4 and summary["pairs_generated"] == 14
        assert summary["regenerated"] == [] and summary["manifest"] == "written" and summary["workers"] == 1
        tr, te = summary["sets"]["train"], summary["sets"]["test"]
        assert tr["complete"] and te["complete"]
        assert (tr["n_pairs"], tr["n_shards"], te["n_pairs"], te["n_shards"]) == (8, 2, 6, 2)
        assert sum(tr["pairs_per_class_avg"]) == 8 and tr["pairs_per_class_avg"][REJECT] == 0
        assert te["pairs_per_class_avg"][REJECT] == 2 and te["pairs_per_class_max"][REJECT] == 2
        assert 0 <= tr["registration_failed"] <= 8

    def test_manifest(self, reference):
        out, summary = reference
        m = read_manifest(out)
        assert m == json.loads((out / "manifest.json").read_text())
        assert m["format_version"] == FORMAT_VERSION
        assert m["config"] == config_to_dict(CFG)
        assert m["scenes"] == ["gravel", "grass"]
        assert m["fingerprint"] == config_fingerprint(CFG, ["gravel", "grass"])
        assert m["sets"] == summary["sets"]

    def test_shard_records(self, reference):
        out, _ = reference
        fp = read_manifest(out)["fingerprint"]
        for (s, k), (a, b) in zip(SHARDS, shard_ranges(8, 4) + shard_ranges(6, 4)):
            rec = load_shard(shard_path(out, s, k), fp)
            assert (rec["set"], rec["start"], rec["end"]) == (s, a, b)
            assert rec["index"].tolist() == list(range(a, b))
            assert rec["counts"].shape == (b - a, 1, 12, 16) and rec["counts"].dtype == torch.uint8
            # plain tensors and containers only: loads with weights_only=True
            torch.load(shard_path(out, s, k), weights_only=True)
            # the checksum file is one `sha256sum` line
            digest = hashlib.sha256(shard_path(out, s, k).read_bytes()).hexdigest()
            assert checksum_path(shard_path(out, s, k)).read_text() == f"{digest}  shard-{k:05d}.pt\n"

    def test_shard_ranges(self):
        assert shard_ranges(10, 4) == [(0, 4), (4, 8), (8, 10)]
        assert shard_ranges(0, 4) == []


class TestLoadSet:
    def test_merged_by_index(self, reference):
        out, _ = reference
        fp = read_manifest(out)["fingerprint"]
        for s, n in (("train", 8), ("test", 6)):
            data = load_set(out, s)
            assert data["index"].tolist() == list(range(n))
            assert data["config"] == CFG
            recs = [load_shard(shard_path(out, s, k), fp) for k in (0, 1)]
            for key in ("counts", "H", "k2", "class_avg", "converged"):
                assert torch.equal(data[key], torch.cat([r[key] for r in recs]))
        test = load_set(out, "test")
        assert test["perturbed"].tolist() == [False] * 4 + [True] * 2
        assert test["class_avg"][4:].tolist() == [REJECT, REJECT]
        assert bool((test["k2"][4:] == 0).all())

    def test_rows_are_the_pairs(self, reference):
        out, _ = reference
        test = load_set(out, "test")
        scenes, _ = load_scenes(CFG)
        n = torch.get_num_threads()
        torch.set_num_threads(1)  # speed only (two shared cores)
        try:
            direct = make_pairs(scenes, config=CFG, set_name="test", indices=[3, 4])
        finally:
            torch.set_num_threads(n)
        for j, i in enumerate((3, 4)):
            assert torch.equal(test["counts"][i], direct.counts[j])
            assert torch.equal(test["M"][i], direct.params.M[j])
            torch.testing.assert_close(test["H"][i], direct.H[j], atol=1e-5, rtol=0)

    def test_limit(self, reference):
        out, _ = reference
        data = load_set(out, "train", limit=5)
        assert data["index"].tolist() == [0, 1, 2, 3, 4] and data["counts"].shape[0] == 5

    def test_errors(self, reference, tmp_path):
        out, _ = reference
        with pytest.raises(FileNotFoundError, match="manifest"):
            load_set(tmp_path, "train")
        only_test = tmp_path / "only"
        only_test.mkdir()
        m = read_manifest(out)
        del m["sets"]["train"]
        (only_test / "manifest.json").write_text(json.dumps(m))
        with pytest.raises(ValueError, match="no 'train' set"):
            load_set(only_test, "train")

    def test_misplaced_shard_is_not_merged(self, reference, tmp_path):
        """A shard file under another shard's name must not merge as duplicate pairs."""
        out = tmp_path / "d"
        shutil.copytree(reference[0], out)
        shutil.copyfile(shard_path(out, "train", 0), shard_path(out, "train", 1))
        with pytest.raises(ShardError, match=r"shard-00001\.pt is corrupted"):
            load_set(out, "train")
        # with its checksum file too: the shard holds the wrong pairs
        shutil.copyfile(checksum_path(shard_path(out, "train", 0)), checksum_path(shard_path(out, "train", 1)))
        checksum_path(shard_path(out, "train", 1)).write_text(
            checksum_path(shard_path(out, "train", 0)).read_text().replace("00000", "00001"))
        with pytest.raises(ShardError, match=r"holds 'train' pairs \[0, 4\), expected 'train' pairs \[4, 8\)"):
            load_set(out, "train")


# ---------------------------------------------------------------------------------- reproducibility


class TestReproducible:
    def test_array_job_shares(self, reference, tmp_path):
        ref, _ = reference
        out = tmp_path / "d"
        first = generate(CFG, out, shard=(0, 2), progress=False)
        assert first["written"] == 2
        assert not first["sets"]["train"]["complete"] and first["sets"]["train"]["shards_present"] == 1
        assert shard_path(out, "train", 0).exists() and not shard_path(out, "train", 1).exists()
        second = generate(CFG, out, shard=(1, 2), progress=False)
        assert second["written"] == 2 and second["sets"]["test"]["complete"]
        assert data_files(out) == data_files(ref)
        assert_same_shards(ref, out)
        assert filecmp.cmp(ref / "manifest.json", out / "manifest.json", shallow=False)

    def test_resume_after_a_killed_run(self, reference, tmp_path):
        ref, _ = reference
        out = tmp_path / "d"
        shutil.copytree(ref, out)
        fp = read_manifest(out)["fingerprint"]
        # killed while writing train shard 1: the shard is absent, a partial temporary file is left
        shard_path(out, "train", 1).unlink()
        stray = out / "train" / ".shard-00001.pt.k1ll3d.tmp"
        stray.write_bytes(shard_path(ref, "train", 1).read_bytes()[:1000])
        # a shard overwritten with garbage, and one truncated
        shard_path(out, "test", 0).write_bytes(os.urandom(3000))
        shard_path(out, "test", 1).write_bytes(shard_path(ref, "test", 1).read_bytes()[:-200])
        for k in (0, 1):
            with pytest.raises(ShardError, match="corrupted"):
                load_shard(shard_path(out, "test", k), fp)
        intact = shard_path(out, "train", 0)
        os.utime(intact, (1_000_000, 1_000_000))
        summary = generate(CFG, out, progress=False)
        assert summary["written"] == 3 and summary["pairs_generated"] == 4 + 6
        # the two damaged shards are reported (the missing one is just written)
        assert len(summary["regenerated"]) == 2 and all("corrupted" in r for r in summary["regenerated"])
        assert intact.stat().st_mtime == 1_000_000  # skipped, not rewritten
        assert_same_shards(ref, out)
        assert filecmp.cmp(ref / "manifest.json", out / "manifest.json", shallow=False)
        # nothing left to do the next time
        again = generate(CFG, out, progress=False)
        assert again["written"] == 0 and again["pairs_generated"] == 0
        assert_same_shards(ref, out)

    def test_limit_then_full_run(self, reference, tmp_path):
        """A --limit run leaves a shorter last shard; the full run must replace it, not skip it."""
        ref, _ = reference
        out = tmp_path / "d"
        part = generate(CFG, out, sets=["test"], limit=3, progress=False)
        assert part["sets"]["test"]["n_pairs"] == 3 and part["sets"]["test"]["complete"]
        assert load_set(out, "test")["index"].tolist() == [0, 1, 2]
        full = generate(CFG, out, sets=["test"], progress=False)
        assert full["written"] == 2
        assert full["regenerated"] == [f"shard {shard_path(out, 'test', 0)} holds 'test' pairs [0, 3), expected 'test' "
                                       "pairs [0, 4) (a shard copied over another, or left by a shorter --limit run)"]
        assert load_set(out, "test")["index"].tolist() == list(range(6))
        assert_same_shards(ref, out, [("test", 0), ("test", 1)])

    def test_foreign_shard_is_regenerated(self, reference, tmp_path):
        ref, _ = reference
        out = tmp_path / "d"
        shutil.copytree(ref, out)
        rec = load_shard(shard_path(out, "test", 1))
        rec["fingerprint"] = "0123456789abcdef"
        write_shard(shard_path(out, "test", 1), rec)
        torch.save({"a": 1}, shard_path(out, "train", 1))
        summary = generate(CFG, out, progress=False)
        assert summary["written"] == 2
        assert_same_shards(ref, out)

    def test_workers(self, reference, tmp_path):
        """Two worker processes (spawned, one thread each) write the same bytes as one process."""
        ref, _ = reference
        out = tmp_path / "d"
        summary = generate(CFG, out, sets=["test"], workers=2, progress=False)
        assert summary["written"] == 2 and summary["sets"]["test"]["complete"]
        assert_same_shards(ref, out, [("test", 0), ("test", 1)])

    def test_thread_count_is_restored(self, tmp_path):
        n = torch.get_num_threads()
        generate(CFG, tmp_path / "d", sets=["test"], limit=1, progress=False)
        assert torch.get_num_threads() == n


# ---------------------------------------------------------------------------------- shard checks


def seal(path: Path) -> Path:
    """Write the checksum file of ``path`` (a file not written by write_shard)."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    checksum_path(path).write_text(f"{digest}  {path.name}\n")
    return path


class TestShardErrors:
    def test_foreign_torch_file(self, tmp_path):
        p = tmp_path / "x.pt"
        torch.save({"a": 1}, p)
        with pytest.raises(ShardError, match="no checksum file"):
            load_shard(p)
        seal(p)
        with pytest.raises(ShardError, match="not a lensdist data-set shard"):
            load_shard(p)
        torch.save(torch.zeros(3), p)
        seal(p)
        with pytest.raises(ShardError, match="not a lensdist data-set shard"):
            load_shard(p)

    def test_pickled_object_is_refused(self, tmp_path):
        """weights_only: a pickle of an arbitrary object is never unpickled."""
        p = tmp_path / "x.pt"
        torch.save({"kind": "lensdist-shard", "obj": Path("/")}, p)
        seal(p)
        with pytest.raises(ShardError, match="corrupted or not a torch file") as exc:
            load_shard(p)
        assert "\n" not in str(exc.value)  # one line

    def test_garbage_and_missing(self, tmp_path):
        p = tmp_path / "x.pt"
        p.write_bytes(b"not a zip file at all" * 10)
        with pytest.raises(ShardError, match=r"x\.pt"):
            load_shard(p)
        seal(p)
        with pytest.raises(ShardError, match=r"x\.pt is corrupted or not a torch file"):
            load_shard(p)
        with pytest.raises(FileNotFoundError):
            load_shard(tmp_path / "missing.pt")

    def test_other_config(self, reference):
        out, _ = reference
        with pytest.raises(ShardError, match="another config"):
            load_shard(shard_path(out, "train", 0), fingerprint="ffffffffffffffff")

    def test_other_format_version_and_bad_records(self, reference, tmp_path):
        out, _ = reference
        rec = load_shard(shard_path(out, "train", 0))
        p = tmp_path / "s.pt"
        write_shard(p, {**rec, "format_version": FORMAT_VERSION + 1})
        with pytest.raises(ShardError, match="format version"):
            load_shard(p)
        write_shard(p, {k: v for k, v in rec.items() if k != "counts"})
        with pytest.raises(ShardError, match="lacks"):
            load_shard(p)
        write_shard(p, {**rec, "counts": rec["counts"][:2]})
        with pytest.raises(ShardError, match="inconsistent"):
            load_shard(p)
        write_shard(p, {**rec, "start": 1, "end": 5})
        with pytest.raises(ShardError, match="inconsistent"):
            load_shard(p)

    def test_write_shard_bytes_do_not_depend_on_the_name(self, reference, tmp_path):
        out, _ = reference
        rec = load_shard(shard_path(out, "train", 0))
        write_shard(tmp_path / "a" / "one.pt", rec)
        write_shard(tmp_path / "b" / "two.pt", rec)
        assert (tmp_path / "a" / "one.pt").read_bytes() == (tmp_path / "b" / "two.pt").read_bytes()
        assert (tmp_path / "a" / "one.pt").read_bytes() == shard_path(out, "train", 0).read_bytes()
        # no temporary file left
        assert data_files(tmp_path) == ["a/one.pt", "a/one.pt.sha256", "b/two.pt", "b/two.pt.sha256"]


# ---------------------------------------------------------------------------------- config checks


class TestConfig:
    def test_other_config_in_the_folder(self, reference, tmp_path):
        out = tmp_path / "d"
        out.mkdir()
        shutil.copyfile(reference[0] / "manifest.json", out / "manifest.json")
        other = config_from_dict({**TINY, "protocol": {**TINY["protocol"], "seed": 1}})
        with pytest.raises(ValueError, match="another config"):
            generate(other, out, progress=False)
        assert data_files(out) == ["manifest.json"]  # nothing written
        assert filecmp.cmp(reference[0] / "manifest.json", out / "manifest.json", shallow=False)

    def test_other_shard_size_in_the_folder(self, reference, tmp_path):
        """The shard size fixes which pairs a file holds: another one is another data set."""
        out = tmp_path / "d"
        shutil.copytree(reference[0], out)
        other = config_from_dict({**TINY, "protocol": {**TINY["protocol"], "shard_size": 3}})
        with pytest.raises(ValueError, match="another config"):
            generate(other, out, progress=False)

    def test_fingerprint(self):
        fp = config_fingerprint(CFG, ["gravel", "grass"])
        assert fp == config_fingerprint(config_from_dict(TINY), ["gravel", "grass"])
        assert fp != config_fingerprint(CFG, ["grass", "gravel"])
        faster = config_from_dict({**TINY, "quality": {"chunk_size": 7}})
        assert config_fingerprint(faster, ["gravel", "grass"]) == fp  # speed only
        other = config_from_dict({**TINY, "quality": {"theta_e": 0.4}})
        assert config_fingerprint(other, ["gravel", "grass"]) != fp

    @pytest.mark.parametrize(
        "kwargs,match",
        [({"sets": ["val"]}, "sets"), ({"workers": 0}, "workers"), ({"batch_size": 0}, "batch_size")],
    )
    def test_bad_arguments(self, tmp_path, kwargs, match):
        with pytest.raises(ValueError, match=match):
            generate(CFG, tmp_path / "d", progress=False, **kwargs)


# ---------------------------------------------------------------------------------- scenes


class TestScenes:
    def test_unreadable_file(self, tmp_path):
        folder = tmp_path / "scenes"
        folder.mkdir()
        (folder / "broken.png").write_bytes(os.urandom(500))
        with pytest.raises(ValueError, match="broken.png"):
            generate(CFG, tmp_path / "d", scenes_dir=folder, progress=False)
        assert not (tmp_path / "d").exists()

    def test_too_small(self, tmp_path):
        folder = tmp_path / "scenes"
        folder.mkdir()
        png(folder / "big.png", torch.randint(0, 256, (200, 260), dtype=torch.uint8))
        png(folder / "tiny.png", torch.randint(0, 256, (20, 20), dtype=torch.uint8))
        with pytest.raises(ValueError, match=r"tiny\.png.*too small"):
            generate(CFG, tmp_path / "d", scenes_dir=folder, progress=False)

    def test_folder_errors(self, tmp_path):
        with pytest.raises(FileNotFoundError):
            load_scenes(CFG, tmp_path / "nowhere")
        (tmp_path / "empty").mkdir()
        (tmp_path / "empty" / "notes.txt").write_text("no images here")
        with pytest.raises(ValueError, match="no image files"):
            load_scenes(CFG, tmp_path / "empty")

    def test_scene_ids_hash_the_content(self, tmp_path):
        folder = tmp_path / "scenes"
        folder.mkdir()
        png(folder / "a.png", torch.randint(0, 256, (200, 260), dtype=torch.uint8))
        scenes, ids = load_scenes(CFG, folder)
        assert scenes[0].shape == (1, 1, 200, 260) and ids[0].startswith("a.png:")
        png(folder / "a.png", torch.randint(0, 256, (200, 260), dtype=torch.uint8))
        assert load_scenes(CFG, folder)[1] != ids

    def test_textureless_scene_fails_registration(self, tmp_path):
        """A constant scene cannot be registered: the shard says so (converged False)."""
        folder = tmp_path / "scenes"
        folder.mkdir()
        png(folder / "flat.png", torch.full((200, 260), 128, dtype=torch.uint8))
        out = tmp_path / "d"
        summary = generate(CFG, out, sets=["test"], scenes_dir=folder, limit=3, progress=False)
        assert summary["sets"]["test"]["registration_failed"] == 3
        data = load_set(out, "test")
        assert not bool(data["converged"].any())
        assert read_manifest(out)["scenes"][0].startswith("flat.png:")


# ---------------------------------------------------------------------------------- command line


class TestCommandLine:
    def test_generate(self, reference, tmp_path):
        cfg = tmp_path / "tiny.toml"
        cfg.write_text(TINY_TOML)
        out = tmp_path / "d"
        res = subprocess.run(
            [sys.executable, "-m", "lensdist_torch.cli", "generate", "--config", str(cfg), "--out", str(out), "--quiet", "--json"],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert res.returncode == 0, res.stderr
        summary = json.loads(res.stdout)
        assert summary["written"] == 4 and summary["sets"]["train"]["complete"]
        assert_same_shards(reference[0], out)

    @pytest.mark.parametrize("bad", ["3/2", "2/2", "-1/2", "1/0", "x", "1/2/3"])
    def test_bad_shard(self, tmp_path, bad, capsys):
        code = cli_main(["generate", "--out", str(tmp_path / "d"), f"--shard={bad}"])
        err = capsys.readouterr().err
        assert code == 2 and "--shard" in err and err.count("\n") == 1
        assert not (tmp_path / "d").exists()

    def test_error_exit_code(self, tmp_path, capsys):
        (tmp_path / "scenes").mkdir()
        code = cli_main(["generate", "--out", str(tmp_path / "d"), "--scenes", str(tmp_path / "scenes"), "--quiet"])
        assert code == 2
        assert "no image files" in capsys.readouterr().err
