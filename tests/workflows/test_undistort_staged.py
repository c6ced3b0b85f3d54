"""``lensdist undistort`` writes all of its frames or none: a frame that fails leaves the output as it was."""

import os

import torch
from one_line import one_line_usage

from lensdist_torch import cli
from lensdist_torch.core.png import encode_png


def _folder(tmp_path, broken: int | None = None, n: int = 5):
    folder = tmp_path / "in"
    folder.mkdir()
    g = torch.Generator().manual_seed(0)
    for i in range(n):
        frame = (torch.rand(1, 24, 32, generator=g) * 255).to(torch.uint8)
        (folder / f"f{i}.png").write_bytes(b"not an image" if i == broken else encode_png(frame))
    return folder


def _run(capsys, *argv) -> tuple[int, str]:
    rc = cli.main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def test_a_broken_third_frame_writes_nothing_and_the_rerun_needs_no_overwrite(tmp_path, capsys):
    folder, out = _folder(tmp_path, broken=2), tmp_path / "out"
    rc, err = _run(capsys, "undistort", folder, "--out", out, "--k2", "1e-4", "--quiet")
    one_line_usage(rc, err, "undistort")
    assert "f2.png" in err
    assert not out.exists() and sorted(os.listdir(tmp_path)) == ["in"]  # no frame, no mask, no staging folder left
    (tmp_path / "fixed").mkdir()
    _folder(tmp_path / "fixed")
    (folder / "f2.png").write_bytes((tmp_path / "fixed" / "in" / "f2.png").read_bytes())
    rc, err = _run(capsys, "undistort", folder, "--out", out, "--k2", "1e-4", "--quiet")
    assert rc == 0, err
    assert sorted(os.listdir(out)) == ["f0.png", "f1.png", "f2.png", "f3.png", "f4.png", "masks", "undistortion.json"]
    assert sorted(os.listdir(out / "masks")) == [f"f{i}.png" for i in range(5)]
    assert sorted(os.listdir(tmp_path)) == ["fixed", "in", "out"]


def test_a_failed_overwrite_keeps_the_previous_run(tmp_path, capsys):
    folder, out = _folder(tmp_path), tmp_path / "out"
    assert _run(capsys, "undistort", folder, "--out", out, "--k2", "1e-4", "--quiet")[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    (folder / "f3.png").write_bytes(b"truncated")
    rc, err = _run(capsys, "undistort", folder, "--out", out, "--k2", "-1e-4", "--overwrite", "--quiet")
    one_line_usage(rc, err, "undistort")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # the k2 = 1e-4 frames, untouched
