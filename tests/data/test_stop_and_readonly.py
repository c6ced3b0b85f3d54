"""`lensdist generate` stopped and re-checked (issue 19): Ctrl-C and SIGTERM with worker
processes end in one line and the right status with no worker left behind, the next run resumes
byte-identical; a complete data set on a read-only file system is re-checked by the command line;
a folder that is neither empty nor a data set (someone's photos) gets no data set written into it.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lensdist_torch.cli import main as cli_main
from lensdist_torch.config import config_from_dict
from lensdist_torch.data import locks, manifest, shardfile
from lensdist_torch.data.shards import generate, load_set, shard_path

pytestmark = pytest.mark.bad_input

ROOT = Path(__file__).resolve().parents[2]
TOML = """[image]
height = 96
width = 128
[protocol]
n_train = 32
n_test_distorted = 4
n_test_undistorted = 2
shard_size = 4
"""
CFG = config_from_dict({
    "image": {"height": 96, "width": 128},
    "protocol": {"n_train": 32, "n_test_distorted": 4, "n_test_undistorted": 2, "shard_size": 4},
})


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stop") / "ref"
    generate(CFG, out, progress=False)
    return out


def _files(out: Path) -> dict[str, bytes]:
    """The data set's files (hidden lock and temporary files aside)."""
    return {
        str(p.relative_to(out)): p.read_bytes()
        for p in sorted(out.rglob("*"))
        if p.is_file() and not p.name.startswith(".")
    }


def _start(tmp_path: Path, out: Path) -> subprocess.Popen:
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TOML)
    cmd = [sys.executable, "-m", "lensdist_torch.cli", "generate", "--config", str(cfg), "--out", str(out), "--workers", "2", "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    # its own session: Ctrl-C is a SIGINT to the whole group (parent and workers), as a terminal sends it
    # SIGINT at its default, as a terminal's foreground job has it: a test run started in the
    # background of a non-interactive shell (nohup bash -c '... &') ignores SIGINT, and an ignored
    # signal stays ignored across exec
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def _wait_for(cond, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, f"the run ended first: {proc.communicate()}"
        assert time.monotonic() - t0 < timeout
        time.sleep(0.02)


def _group_gone(pgid: int, timeout: float = 15.0) -> bool:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.05)
    os.killpg(pgid, signal.SIGKILL)  # do not leave them running after a failed test
    return False


def _first_shard(out: Path):
    return lambda: any((out / "train").glob("shard-*.pt.sha256"))


@pytest.mark.parametrize("when", ["while the workers start", "mid-run"])
def test_ctrl_c(reference, tmp_path, when):
    out = tmp_path / "d"
    proc = _start(tmp_path, out)
    _wait_for((lambda: (out / ".lock-0-of-1").exists()) if when == "while the workers start" else _first_shard(out), proc)
    if when == "while the workers start":
        time.sleep(0.3)  # the workers are importing torch
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert err == "lensdist generate: interrupted\n"  # nothing from the workers
    assert _group_gone(proc.pid), "a worker outlived the run"
    summary = generate(CFG, out, progress=False)  # resume
    assert summary["sets"]["train"]["complete"]
    assert _files(out) == _files(reference)


def test_sigterm_to_the_main_process(reference, tmp_path):
    """The audit's case: orphaned workers printed 66 lines of BrokenPipeError."""
    out = tmp_path / "d"
    proc = _start(tmp_path, out)
    _wait_for(_first_shard(out), proc)
    os.kill(proc.pid, signal.SIGTERM)  # the main process only
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert err.count("\n") == 1 and err.startswith("lensdist generate: terminated (SIGTERM)"), err
    assert _group_gone(proc.pid), "a worker outlived the run"
    assert not (out / ".lock-0-of-1").exists()  # released on the way out
    generate(CFG, out, progress=False)
    assert _files(out) == _files(reference)


# ------------------------------------------------------------------ a read-only data set
def test_read_only_data_set_is_rechecked_by_the_command_line(reference, tmp_path, monkeypatch, capsys):
    """As on a read-only mount (which root cannot simulate with chmod): access() says no and every write fails."""
    data = tmp_path / "ro"
    shutil.copytree(reference, data)
    (tmp_path / "tiny.toml").write_text(TOML)
    before = _files(data)
    real_access = os.access

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and Path(path).absolute().is_relative_to(data.absolute()):
            return False
        return real_access(path, mode, *args, **kwargs)

    def refuse(*args, **kwargs):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(os, "access", access)
    for module, name in [(shardfile, "atomic_write_bytes"), (shardfile, "save_versioned"), (manifest, "atomic_write_bytes"),
                         (locks, "_try_lock")]:
        monkeypatch.setattr(module, name, refuse)
    code = cli_main(["generate", "--config", str(tmp_path / "tiny.toml"), "--out", str(data), "--quiet"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "0 shards written" in out and "train: 32 pairs, complete" in out
    assert _files(data) == before
    # a set that needs a shard cannot be finished there: one line, exit 2, nothing changed
    shard_path(data, "train", 3).unlink()
    code = cli_main(["generate", "--config", str(tmp_path / "tiny.toml"), "--out", str(data), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Read-only file system" in err, err
    assert load_set(reference, "train")["index"].numel() == 32


# ------------------------------------------------------------------ someone else's folder
def _someones_folder(tmp_path: Path) -> tuple[Path, dict[str, bytes]]:
    folder = tmp_path / "photos"
    (folder / "2024").mkdir(parents=True)
    (folder / "IMG_0001.jpg").write_bytes(b"\xff\xd8 a photo")
    (folder / "2024" / "IMG_0002.jpg").write_bytes(b"\xff\xd8 another")
    (folder / "test").mkdir()  # a set's name, but not shards
    (folder / "test" / "notes.txt").write_text("mine")
    return folder, {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_a_folder_that_is_not_a_data_set_is_refused(tmp_path, capsys):
    """Issue 19 audit: generate --out into a folder of photos wrote its manifest and shards among them (exit 0)."""
    folder, before = _someones_folder(tmp_path)
    (tmp_path / "tiny.toml").write_text(TOML)
    code = cli_main(["generate", "--config", str(tmp_path / "tiny.toml"), "--out", str(folder), "--sets", "test", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"lensdist generate: error: --out {folder} holds files that are not a lensdist data set "
                          "(2024, IMG_0001.jpg, test; no manifest.json)"), err
    with pytest.raises(ValueError, match="not a lensdist data set"):
        generate(CFG, folder, sets=["test"], progress=False)
    after = {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert after == before  # not a file added (no lock, no manifest), none changed


def test_an_empty_folder_and_a_run_stopped_before_its_manifest_are_written(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert generate(CFG, empty, sets=["test"], limit=2, progress=False)["written"] == 1
    # a run killed before it wrote its manifest: its (stale) lock and a partial shard are its own files
    stopped = tmp_path / "stopped"
    (stopped / "test").mkdir(parents=True)
    (stopped / ".lock-0-of-1").write_text(f"999999999 {socket.gethostname()}\n")
    (stopped / "test" / ".shard-00000.pt.k1ll3d.tmp").write_bytes(b"partial")
    assert generate(CFG, stopped, sets=["test"], limit=2, progress=False)["written"] == 1
    assert _files(stopped) == _files(empty)
