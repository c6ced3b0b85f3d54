"""Data sets changed consistently by hand (issue 19): a shard changed together with its
checksum file, a manifest whose counts were edited, arguments that would silently drop pairs.

The tiny data set of tests/generated_sets.py (8 training and 6 test pairs, shards of 4), from
tests/data/conftest.py.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import torch
from generated_sets import TINY_CFG as CFG
from one_line import one_line

from lensdist_torch.data.shards import (
    ShardError,
    checksum_path,
    generate,
    load_set,
    load_shard,
    read_manifest,
    shard_path,
    write_shard,
)

pytestmark = pytest.mark.bad_input



def files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def _edit_manifest(out: Path, fn) -> None:
    path = out / "manifest.json"
    m = json.loads(path.read_text())
    fn(m)
    path.write_text(json.dumps(m, indent=2))


def _tamper_shard(out: Path, set_name: str, k: int) -> None:
    """Change one pair's class in a shard and rewrite its checksum file to match (write_shard)."""
    path = shard_path(out, set_name, k)
    rec = load_shard(path)
    rec["class_avg"] = rec["class_avg"].clone()
    rec["class_avg"][0] = (rec["class_avg"][0] + 1) % 4
    write_shard(path, rec)
    assert load_shard(path)["class_avg"][0] == rec["class_avg"][0]  # consistent on its own


# ------------------------------------------------------------------ shard digests in the manifest
def test_manifest_records_every_shard_digest(reference):
    m = read_manifest(reference)
    for name, n in (("train", 2), ("test", 2)):
        digests = m["sets"][name]["shard_sha256"]
        assert len(digests) == n
        for k, d in enumerate(digests):
            assert d == hashlib.sha256(shard_path(reference, name, k).read_bytes()).hexdigest()
            assert checksum_path(shard_path(reference, name, k)).read_text().startswith(d)


def test_shard_with_recomputed_checksum_is_refused(data):
    """The audit's case: a changed shard with its .sha256 recomputed loaded with changed counts."""
    _tamper_shard(data, "train", 1)
    with pytest.raises(ShardError, match=r"train/shard-00001\.pt is not the one recorded in manifest\.json") as info:
        load_set(data, "train")
    one_line(info)


def test_generate_regenerates_it_byte_identical(reference, data, capsys):
    _tamper_shard(data, "test", 0)
    summary = generate(CFG, data, progress=False)
    assert summary["written"] == 1 and "not the one recorded in manifest.json" in summary["regenerated"][0]
    assert files(data) == files(reference)
    assert load_set(data, "test")["class_avg"].tolist() == load_set(reference, "test")["class_avg"].tolist()


def test_edited_shard_digest_in_the_manifest(data):
    _edit_manifest(data, lambda m: m["sets"]["test"]["shard_sha256"].__setitem__(1, "0" * 64))
    with pytest.raises(ShardError, match=r"test/shard-00001\.pt is not the one recorded"):
        load_set(data, "test")
    _edit_manifest(data, lambda m: m["sets"]["test"].__setitem__("shard_sha256", ["xyz"]))
    with pytest.raises(ShardError, match=r"manifest\.json is not a valid lensdist manifest: sets\.test: shard_sha256 must list 2"):
        load_set(data, "test")


def test_a_manifest_saved_with_the_retired_relief_threshold_still_reads(reference, data):
    """Data made before issue 20 record analysis.relief_z in their config: a decision of the
    analysis, never part of the pairs, so the data set reads as it was."""
    _edit_manifest(data, lambda m: m["config"]["analysis"].__setitem__("relief_z", 4.0))
    assert load_set(data, "test")["class_avg"].tolist() == load_set(reference, "test")["class_avg"].tolist()
    _edit_manifest(data, lambda m: m["config"]["protocol"].__setitem__("parallax_px", 1.5))
    with pytest.raises(ShardError, match=r"earlier version of the pair protocol \(protocol\.parallax_px\)"):
        load_set(data, "test")


# ------------------------------------------------------------------ the manifest's counts against the shards
def _shrink_test_set(m: dict, counts: dict) -> None:
    """The test set recorded as its first 4 pairs, consistently: size, shards, counts, digests."""
    rec = m["sets"]["test"]
    rec.update(n_pairs=4, n_shards=1, shard_sha256=rec["shard_sha256"][:1], **counts)


def test_manifest_edited_to_fewer_pairs(reference, data):
    """The audit's case: n_pairs edited (12 -> 8 there) made load_set return fewer pairs."""
    first = load_set(reference, "test")
    counts = {
        "registration_failed": int((~first["converged"][:4]).sum()),
        "pairs_per_class_avg": torch.bincount(first["class_avg"][:4], minlength=5).tolist(),
        "pairs_per_class_max": torch.bincount(first["class_max"][:4], minlength=5).tolist(),
    }
    _edit_manifest(data, lambda m: _shrink_test_set(m, counts))
    assert read_manifest(data)["sets"]["test"]["n_pairs"] == 4  # a valid manifest on its own
    with pytest.raises(ShardError, match=r"test/shard-00001\.pt lies beyond the 1 shards \(4 pairs\)") as info:
        load_set(data, "test")
    one_line(info)


@pytest.mark.parametrize("key", ["pairs_per_class_avg", "pairs_per_class_max", "registration_failed"])
def test_manifest_counts_edited(data, key):
    def edit(m):
        rec = m["sets"]["train"]
        if key == "registration_failed":
            rec[key] = (rec[key] + 1) % (rec["n_pairs"] + 1)
        else:
            i = next(i for i, c in enumerate(rec[key]) if c > 0)
            rec[key][i] -= 1
            rec[key][(i + 1) % 5] += 1  # the sum still n_pairs

    _edit_manifest(data, edit)
    with pytest.raises(ShardError, match=rf"manifest\.json records {key} .* for the 'train' set, but its shards hold") as info:
        load_set(data, "train")
    one_line(info)


def test_set_recorded_incomplete_is_refused(data):
    _edit_manifest(data, lambda m: m["sets"]["test"].update(
        complete=False, shards_present=2, **{k: None for k in ("registration_failed", "pairs_per_class_avg",
                                                              "pairs_per_class_max", "shard_sha256")}))
    with pytest.raises(ShardError, match=r"records the 'test' set as incomplete; run `lensdist generate"):
        load_set(data, "test")


def test_record_without_digests_is_rechecked_by_generate(reference, data):
    """A manifest of an older lensdist (no digests): load_set asks for a re-check, generate records them."""
    _edit_manifest(data, lambda m: [rec.pop("shard_sha256") for rec in m["sets"].values()])
    with pytest.raises(ShardError, match="records no shard digests for the 'train' set"):
        load_set(data, "train")
    summary = generate(CFG, data, progress=False)
    assert summary["written"] == 0 and summary["manifest"] == "written"
    assert read_manifest(data) == read_manifest(reference)
    assert load_set(data, "train")["index"].tolist() == list(range(8))


# ------------------------------------------------------------------ arguments that drop pairs
@pytest.mark.parametrize("limit", [-1, 0, 2.5, True, "3", float("nan")])
def test_load_set_limit(reference, limit):
    """The audit's case: limit=-1 returned 11 of 12 pairs."""
    with pytest.raises(ValueError, match=r"limit must be None or a positive int, got") as info:
        load_set(reference, "test", limit=limit)
    one_line(info)


def test_load_set_good_limits(reference):
    assert load_set(reference, "test", limit=3)["index"].tolist() == [0, 1, 2]
    assert load_set(reference, "test", limit=100)["index"].tolist() == list(range(6))


@pytest.mark.parametrize("shard", [(0.5, 2), (True, 2), ("0", "2"), (0, 2.0), "01", (0, 1, 2)])
def test_generate_shard_argument(tmp_path, shard):
    """(0.5, 2) used to pass the check and write nothing."""
    with pytest.raises(ValueError, match=r"shard must be \(I, N\), two ints"):
        generate(CFG, tmp_path / "x", shard=shard, progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("sets", ["train", [], ()])
def test_generate_sets_argument(tmp_path, sets):
    with pytest.raises(ValueError, match="sets must be a non-empty list of set names"):
        generate(CFG, tmp_path / "x", sets=sets, progress=False)
    assert not (tmp_path / "x").exists()
