"""``lensdist analyze --pairs`` (issue 52, item 1): many pairs, one table, resumable, shardable,
each answer file what ``lensdist analyze IMG1 IMG2 --json`` prints for its pair.

Four pairs of small crops of the gravel scene (moved by a few pixels), one pair with an
unreadable image and one of two sizes, analysed once by the default method on one thread;
every test that analyses again compares with that first run.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from lensdist_torch import cli, load_scene
from lensdist_torch.core.png import encode_png, to_uint8
from lensdist_torch.workflows.pair_archive import PAIR_COLUMNS, PairInput, pair_inputs, run_pair_archive

H, W = 240, 320
#: (top, left) of each pair's two crops: views moved by (dy, dx) pixels
MOVES = (((0, 0), (6, 0)), ((40, 20), (40, 27)), ((100, 60), (105, 64)), ((200, 150), (196, 158)))


def _write(path: Path, image) -> str:
    path.write_bytes(encode_png(to_uint8(image[0])))
    return path.name


@pytest.fixture(scope="module")
def pairs_file(tmp_path_factory, one_thread_module) -> Path:
    """A CSV list of the six pairs, relative to its folder; the last two broken."""
    root = tmp_path_factory.mktemp("pairs")
    scene = load_scene("gravel")
    lines = ["img1,img2,camera"]
    for k, ((y1, x1), (y2, x2)) in enumerate(MOVES):
        a = _write(root / f"p{k}_a.png", scene[..., y1:y1 + H, x1:x1 + W])
        b = _write(root / f"p{k}_b.png", scene[..., y2:y2 + H, x2:x2 + W])
        lines.append(f"{a},{b},{'A' if k < 2 else 'B'}")
    (root / "junk.png").write_bytes(b"not a png")
    _write(root / "small.png", scene[..., : H // 2, : W // 2])
    lines += ["junk.png,p0_b.png,A", "p0_a.png,small.png,A"]
    (root / "pairs.csv").write_text("\n".join(lines) + "\n")
    return root / "pairs.csv"


@pytest.fixture(scope="module")
def full(pairs_file, tmp_path_factory) -> Path:
    """The pairs run of the list through the command line; its output folder."""
    out = tmp_path_factory.mktemp("full") / "out"
    assert cli.main(["analyze", "--pairs", str(pairs_file), "--out", str(out), "--quiet"]) == 0
    return out


def _table(out: Path, drop=("seconds",)) -> list[dict]:
    with open(out / "answers.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


def _answers(out: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted((out / "answers").glob("*.json"))}


def test_rows_are_the_single_runs_answers(full, pairs_file, capsys):
    capsys.readouterr()
    rows = _table(full, drop=())
    pairs = pair_inputs(pairs_file)
    assert [(r["img1"], r["img2"]) for r in rows] == [(p.img1, p.img2) for p in pairs] and list(rows[0]) == list(
        PAIR_COLUMNS
    )
    for row in rows[:4]:
        assert row["ok"] == "True", row
        assert cli.main(["analyze", row["img1"], row["img2"], "--json"]) == 0
        single = capsys.readouterr().out.encode()
        assert (full / row["answer"]).read_bytes() == single  # byte for byte what --json prints
        answer = json.loads(single)
        assert row["class"] == (answer["class"] or "") and row["method"] == "selfcal"
        assert row["reason"] == ";".join(answer["cannot_tell_reasons"])
        for col, key in (("delta_avg_user_px", "delta_avg_user_px"), ("delta_max_user_px", "delta_max_user_px"),
                         ("delta_avg", "delta_avg"), ("confidence", "confidence")):
            assert row[col] == ("" if answer[key] is None else repr(answer[key]))
        low, high = answer.get("delta_avg_interval") or (None, None)
        assert (row["delta_avg_low"], row["delta_avg_high"]) == tuple("" if v is None else repr(v) for v in (low, high))
        assert (row["height"], row["width"]) == (str(H), str(W))
    assert [r["camera"] for r in rows] == ["A", "A", "B", "B", "A", "A"]


def test_broken_pairs_are_rows_with_their_reasons(full):
    junk, sizes = _table(full)[4:]
    assert junk["ok"] == "False" and "is not a PNG file" in junk["reason"] and junk["answer"] == ""
    assert sizes["ok"] == "False" and "must have the same size" in sizes["reason"]
    assert len(_answers(full)) == 4  # no answer file for the broken ones


def test_a_second_run_computes_nothing(full, pairs_file, capsys, monkeypatch):
    import lensdist_torch.workflows.pair_archive as pair_archive

    def never(*args, **kwargs):
        raise AssertionError("a pair was analysed again")

    monkeypatch.setattr(pair_archive, "analyze_pair", never)
    before = {f: f.stat().st_mtime_ns for f in [*(full / "answers").glob("*.json"), *(full / "rows").glob("*.json")]}
    table = (full / "answers.csv").read_bytes()
    assert cli.main(["analyze", "--pairs", str(pairs_file), "--out", str(full)]) == 0
    assert "6 pairs: 0 analysed, 6 reused" in capsys.readouterr().out
    assert {f: f.stat().st_mtime_ns for f in before} == before and (full / "answers.csv").read_bytes() == table
    run = run_pair_archive(pair_inputs(pairs_file), full, method="selfcal")
    assert (run.computed, run.reused, run.failed) == (0, 6, 2)


def test_two_shards_make_the_full_table(full, pairs_file, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["analyze", "--pairs", str(pairs_file), "--out", str(out), "--quiet", "--shard", "0/2"]) == 0
    assert [r["img1"] for r in _table(out)] == [r["img1"] for r in _table(full)][0::2]
    assert "(3 in this share): 3 analysed" in capsys.readouterr().out
    assert (
        cli.main(["analyze", "--pairs", str(pairs_file), "--out", str(out), "--quiet", "--shard", "1/2", "--json"]) == 0
    )
    res = json.loads(capsys.readouterr().out)
    assert (res["pairs"], res["selected"], res["computed"], res["failed"]) == (6, 3, 3, 2)
    assert _table(out) == _table(full) and _answers(out) == _answers(full)


def test_a_file_of_two_paths_per_line_reuses_the_answers(full, pairs_file, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(full, out)
    listed = pair_inputs(pairs_file)
    text = pairs_file.parent / "pairs.txt"
    text.write_text("# img1 img2\n\n" + "".join(f"{Path(p.img1).name}\t{Path(p.img2).name}\n" for p in listed[:4]))
    assert pair_inputs(text) == [PairInput(img1=p.img1, img2=p.img2) for p in listed[:4]]
    run = run_pair_archive(pair_inputs(text), out)
    assert (run.computed, run.reused) == (0, 4) and [r.camera for r in run.rows] == [None] * 4


@pytest.mark.bad_input
@pytest.mark.parametrize("content, argv, wanted", [
    ("img1,camera\na.png,A\n", [], "its header has no img2 column"),
    ("a.png b.png c.png\n", [], "line 1: expected two image paths"),
    ("# nothing\n", [], "lists no pair"),
    (None, [], "pairs file not found"),
    ("a.png b.png\n", ["{d}/a.png", "{d}/b.png"], "give no IMG1 IMG2 with it"),
    ("a.png b.png\n", ["--strict"], "--strict is for one pair"),
    ("a.png b.png\n", ["--checkpoint", "{d}/m.pt"], "not used by method 'selfcal'"),
])
def test_a_bad_pairs_file_is_one_line(tmp_path, capsys, content, argv, wanted):
    if content is not None:
        (tmp_path / "pairs.txt").write_text(content)
    args = ["analyze", "--pairs", str(tmp_path / "pairs.txt"), "--out", str(tmp_path / "o"), *argv]
    assert cli.main([a.format(d=tmp_path) for a in args]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and wanted in err, err
    assert not (tmp_path / "o" / "answers.csv").exists()


@pytest.mark.bad_input
@pytest.mark.parametrize("argv, wanted", [
    (["analyze", "a.png"], "the following arguments are required: img2"),
    (["analyze", "a.png", "b.png", "--out", "o"], "--out is for --pairs FILE"),
    (["analyze", "--pairs", "p.txt"], "--out DIR is needed with --pairs"),
])
def test_pairs_options_are_checked_first(capsys, argv, wanted):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and wanted in err, err
