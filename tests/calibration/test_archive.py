"""An archive run (issue 52): many inputs, one table, resumable, shardable, the same answers as single runs.

Five tiny inputs rendered once (a barrel lens, no lens, a still camera, two frames, a folder of
unreadable files), run with the direct path on one thread; every test that calibrates again
compares with that first run.
"""

from __future__ import annotations

import csv
import json
import shutil
import sys
from pathlib import Path

import pytest

import lensdist_torch.calibration.controllers.archive as archive
from lensdist_torch import cli
from lensdist_torch.calibration.controllers.archive import ArchiveInput, archive_inputs, run_archive
from lensdist_torch.calibration.controllers.archive_table import ROW_COLUMNS
from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
from lensdist_torch.core.png import encode_png, to_uint8

SIZE = (120, 160)
NAMES = ("barrel", "none", "broken", "two", "still")


def _write(folder: Path, frames) -> None:
    folder.mkdir(parents=True)
    for i, f in enumerate(frames):
        (folder / f"f{i:02d}.png").write_bytes(encode_png(to_uint8(f)))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, one_thread_module) -> list[str]:
    root = tmp_path_factory.mktemp("archive")
    _write(root / "barrel", synthetic_sequence(8, 2e-5, 0.0, size=SIZE, seed=1)[0])
    _write(root / "none", synthetic_sequence(8, 0.0, 0.0, size=SIZE, seed=2)[0])
    (root / "broken").mkdir()
    for i in range(3):
        (root / "broken" / f"f{i}.png").write_bytes(b"not a png")
    _write(root / "two", synthetic_sequence(2, 2e-5, 0.0, size=SIZE, seed=3)[0])
    _write(root / "still", synthetic_sequence(6, 2e-5, 0.0, size=SIZE, seed=4, step_px=(0.0, 0.0), jitter_px=0.0,
                                              rotation_deg=0.0)[0])
    return [str(root / n) for n in NAMES]


@pytest.fixture(scope="module")
def full(inputs, tmp_path_factory) -> Path:
    """The archive run of the five inputs through the command line; its output folder."""
    out = tmp_path_factory.mktemp("full") / "out"
    assert cli.main(["calibrate", *inputs, "--out", str(out), "--method", "direct", "--quiet"]) == 0
    return out


def _table(out: Path, drop=("seconds",)) -> list[dict]:
    with open(out / "answers.csv", newline="") as f:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(f)]


def _answers(out: Path) -> dict[str, bytes]:
    return {f.name: f.read_bytes() for f in sorted((out / "answers").glob("*.json"))}


def _close(a, b, rel: float) -> bool:
    """Equal JSON values, floats to ``rel`` relative."""
    if isinstance(a, float) and isinstance(b, float):
        return a == pytest.approx(b, rel=rel, abs=1e-12)
    if isinstance(a, dict) and isinstance(b, dict):
        return list(a) == list(b) and all(_close(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y, rel) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def same_answers(a: dict[str, bytes], b: dict[str, bytes]) -> bool:
    """The same answer files: byte for byte, where the library repeats itself bit for bit.

    It does not quite: OpenCV's coefficients are a least-squares fit (MKL's gelsy) whose last
    bits change from one call to the next in one process, and the 8 rational ones of a frame
    with almost no distortion are so ill-determined that they change in their 7th digit. A file
    that differs in its bytes must parse to the same values: floats to 1e-9, those of
    ``opencv_rational`` to 1e-4.
    """
    def values(text: bytes) -> tuple[dict, dict]:
        res = json.loads(text)
        return res, res.pop("opencv_rational")

    def same(x: bytes, y: bytes) -> bool:
        (rx, cx), (ry, cy) = values(x), values(y)
        return _close(rx, ry, 1e-9) and _close(cx, cy, 1e-4)

    return list(a) == list(b) and all(a[k] == b[k] or same(a[k], b[k]) for k in a)


def test_rows_are_the_single_runs_answers(full, inputs, capsys):
    capsys.readouterr()
    rows = _table(full, drop=())
    assert [r["path"] for r in rows] == inputs and list(rows[0]) == list(ROW_COLUMNS)
    for path, row in zip(inputs, rows):
        if row["ok"] != "True":
            continue
        assert cli.main(["calibrate", path, "--json", "--method", "direct", "--quiet"]) == 0
        single = capsys.readouterr().out.encode()
        assert same_answers({"a": (full / row["answer"]).read_bytes()}, {"a": single})  # what --json prints
        answer = json.loads(single)
        assert row["class"] == (answer["class"] or "") and row["reason"] == (answer["reason"] or "")
        for col, key in (("delta_avg_user_px", "delta_avg_user_px"), ("k2_user", "k2_user")):
            assert row[col] == ("" if answer[key] is None else repr(answer[key]))
        lo, hi = answer["delta_avg_user_interval"]
        assert (row["delta_avg_low_px"], row["delta_avg_high_px"]) == tuple(
            "" if v is None else repr(v) for v in (lo, hi)
        )


def test_broken_inputs_are_rows_with_their_reasons(full):
    rows = {Path(r["path"]).name: r for r in _table(full)}
    assert rows["broken"]["ok"] == "False" and "is not a PNG file" in rows["broken"]["reason"]
    assert rows["still"]["ok"] == "True" and rows["still"]["reason"].startswith("too little motion")
    assert rows["two"]["reason"] and rows["two"]["class"] == ""
    assert rows["barrel"]["ok"] == "True" and float(rows["barrel"]["delta_avg_user_px"]) > 1.0
    assert len(list((full / "answers").glob("*.json"))) == 4  # no answer file for the broken one
    assert (full / "cameras.csv").read_text().splitlines()[1].startswith(",160 x 120,4,")


def test_a_second_run_does_nothing(full, inputs):
    before = {f: f.stat().st_mtime_ns for f in (full / "answers").glob("*.json")}
    before |= {f: f.stat().st_mtime_ns for f in (full / "rows").glob("*.json")}
    table = (full / "answers.csv").read_bytes()
    run = run_archive(inputs, full, method="direct")
    assert (run.computed, run.reused, run.failed) == (0, 5, 1)
    after = {f: f.stat().st_mtime_ns for f in before}
    assert after == before and (full / "answers.csv").read_bytes() == table  # timings too: the first run's


def test_an_interrupted_run_resumes_to_the_same_table(full, inputs, tmp_path, monkeypatch):
    calls, real = [], archive.calibrate_path

    def third_is_interrupted(path, **kwargs):
        calls.append(path)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(path, **kwargs)

    monkeypatch.setattr(archive, "calibrate_path", third_is_interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_archive(inputs, tmp_path / "out", method="direct")
    assert [r["path"] for r in _table(tmp_path / "out")] == inputs[:2]  # the table of the finished ones
    monkeypatch.setattr(archive, "calibrate_path", real)
    run = run_archive(inputs, tmp_path / "out", method="direct")
    assert (run.computed, run.reused) == (3, 2)
    assert _table(tmp_path / "out") == _table(full) and same_answers(_answers(tmp_path / "out"), _answers(full))


def test_two_shards_make_the_full_table(full, inputs, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli.main(["calibrate", *inputs, "--out", str(out), "--method", "direct", "--quiet", "--shard", "0/2"]) == 0
    assert [r["path"] for r in _table(out)] == inputs[0::2]
    assert cli.main(["calibrate", *inputs, "--out", str(out), "--method", "direct", "--quiet", "--shard", "1/2"]) == 0
    assert "(2 in this share)" in capsys.readouterr().out
    assert _table(out) == _table(full) and same_answers(_answers(out), _answers(full))


def test_a_manifest_and_a_glob_reuse_the_answers(full, inputs, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(full, out)
    root = Path(inputs[0]).parent
    manifest = root / "dives.csv"
    manifest.write_text("path,camera\nbarrel,A\nnone,B\nstill,A\nmissing.mp4,B\n")
    assert archive_inputs(manifest=manifest)[0] == ArchiveInput(path=str(root / "barrel"), camera="A")
    assert cli.main(["calibrate", "--manifest", str(manifest), "--out", str(out), "--method", "direct", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert (res["computed"], res["reused"], res["failed"]) == (0, 3, 1)  # a missing path is a row, never computed
    assert [r["camera"] for r in res["rows"]] == ["A", "B", "A", "B"]
    assert res["rows"][3]["reason"].startswith("path not found")
    cams = {(c["camera"], c["size"]): c["inputs"] for c in res["cameras"]}
    assert cams == {("A", "160 x 120"): 2, ("B", "160 x 120"): 1}  # the missing input has no size
    assert cli.main(["calibrate", str(root / "[bnst]*"), "--out", str(out), "--method", "direct"]) == 0
    assert "0 calibrated, 5 reused" in capsys.readouterr().out


def test_per_camera_pooled_by_hand(tmp_path):
    from lensdist_torch.calibration.controllers.archive_table import answer_row, camera_summaries, pool_delta_avg

    def row(path, d, lo, hi, camera, size=SIZE, label="2"):
        answer = {"path": path, "class": label, "delta_avg_user_px": d, "delta_avg_user_interval": [lo, hi],
                  "image_size": list(size)}
        return answer_row(answer, camera=camera, seconds=0.0, digest="", settings="", answer_file="", version="0")

    rows = [row("a", 4.0, 3.0, 5.0, "A"), row("b", 5.0, 4.6, 5.4, "A"), row("c", 9.0, 8.0, 10.0, "A"),
            row("d", 2.0, 1.0, 3.0, "A", label=None),  # cannot tell: not pooled
            row("e", 4.0, 3.0, 5.0, "A", size=(240, 320)), row("f", 1.0, 0.5, 1.5, None)]
    a, big, none = camera_summaries(rows)
    w = [1 / (1 / 1.96) ** 2, 1 / (0.4 / 1.96) ** 2, 1 / (1 / 1.96) ** 2]  # half-width / 1.96 as std
    mean = (w[0] * 4 + w[1] * 5 + w[2] * 9) / sum(w)
    assert mean == pytest.approx(5.364, abs=1e-3)  # in neither a's [3, 5] nor c's [8, 10]: c, 7 stds out, set aside
    mean, half = (w[0] * 4 + w[1] * 5) / (w[0] + w[1]), 1.96 / (w[0] + w[1]) ** 0.5  # 4.86: a and b hold it
    assert (a.camera, a.size, a.inputs, a.answered, a.pooled) == ("A", "160 x 120", 4, 3, 2)
    assert (a.delta_avg_px, a.delta_avg_low_px, a.delta_avg_high_px) == (
        pytest.approx(mean), pytest.approx(mean - half, rel=1e-4), pytest.approx(mean + half, rel=1e-4))
    assert a.disagreeing == ("c",)
    assert (big.size, big.inputs, big.delta_avg_px, big.disagreeing) == ("320 x 240", 1, 4.0, ())
    assert (none.camera, none.delta_avg_px) == (None, pytest.approx(1.0))
    with pytest.raises(ValueError, match="at least one"):
        pool_delta_avg([])


@pytest.mark.bad_input
def test_ray_engine_without_ray_is_one_line(inputs, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray fails
    argv = ["calibrate", *inputs[:2], "--out", str(tmp_path / "out"), "--engine", "ray"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and 'pip install "lensdist_torch[ray]"' in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.bad_input
@pytest.mark.parametrize("argv, wanted", [
    (["calibrate", "a", "b"], "--out DIR is needed"),
    (["calibrate", "{d}/nothing*", "--out", "{d}/o"], "matches no file or folder"),
    (["calibrate", "--manifest", "{d}/m.txt", "--out", "{d}/o"], "lists no input"),
    (["calibrate", "a", "b", "--out", "{d}/o", "--shard", "2/2"], "I/N needs 0 <= I < N"),
    (["calibrate"], "the following arguments are required: path"),
])
def test_archive_options_are_checked_first(tmp_path, capsys, argv, wanted):
    (tmp_path / "m.txt").write_text("# nothing\n\n")
    assert cli.main([a.format(d=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and wanted in err, err
    assert not (tmp_path / "o").exists()


def test_the_parquet_table_has_the_rows(full, inputs):
    pq = pytest.importorskip("pyarrow.parquet")
    table = pq.read_table(full / "answers.parquet").to_pylist()
    assert [r["path"] for r in table] == inputs and tuple(table[0]) == ROW_COLUMNS


def test_a_local_ray_gives_the_same_table(full, inputs, tmp_path):
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        run = run_archive(inputs, tmp_path / "out", method="direct", engine="ray", cpus_per_input=1)
    finally:
        ray.shutdown()
    assert run.computed == 5 and _table(tmp_path / "out") == _table(full)
    assert same_answers(_answers(tmp_path / "out"), _answers(full))
