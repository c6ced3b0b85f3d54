"""The atomic writer replaces a regular file or nothing: never a directory, a device, a FIFO or a
socket, and every refusal is an OSError naming the path."""

from __future__ import annotations

import os
import socket
import stat
import tempfile

import pytest

from lensdist_torch.core.storage import atomic_write_bytes, atomic_write_text


def test_writes_and_replaces_a_regular_file(tmp_path):
    p = tmp_path / "sub" / "a.txt"
    atomic_write_text(p, "one")
    atomic_write_text(p, "two")
    assert p.read_text() == "two"
    assert [q.name for q in p.parent.iterdir()] == ["a.txt"]  # no temporary left behind


@pytest.mark.bad_input
def test_fifo_is_refused_and_left_alone(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="pipe.*not a regular file"):
        atomic_write_bytes(fifo, b"\x89PNG")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["pipe"]


@pytest.mark.bad_input
def test_symlink_to_a_fifo_is_refused(tmp_path):
    """A /dev/null-like target reached through a link (as /dev/stdout is)."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "out.png"
    link.symlink_to(fifo)
    with pytest.raises(OSError, match="not a regular file"):
        atomic_write_bytes(link, b"x")
    assert link.is_symlink() and stat.S_ISFIFO(os.stat(link).st_mode)


@pytest.mark.bad_input
def test_socket_is_refused(tmp_path):
    d = tempfile.mkdtemp(dir="/tmp")  # AF_UNIX paths are limited to ~100 characters
    path = os.path.join(d, "s")
    srv = socket.socket(socket.AF_UNIX)
    try:
        srv.bind(path)
        with pytest.raises(OSError, match="not a regular file"):
            atomic_write_bytes(path, b"x")
        assert stat.S_ISSOCK(os.stat(path).st_mode)
    finally:
        srv.close()
        os.unlink(path)
        os.rmdir(d)


@pytest.mark.bad_input
def test_device_node_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    """/dev/null itself: refused from its stat alone; mkstemp must never be reached."""
    import lensdist_torch.core.storage as storage

    def boom(*a, **k):
        raise AssertionError("a temporary file was created for a device target")

    monkeypatch.setattr(storage.tempfile, "mkstemp", boom)
    with pytest.raises(OSError, match="/dev/null.*not a regular file"):
        atomic_write_bytes("/dev/null", b"x")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.bad_input
@pytest.mark.parametrize("trailing_slash", [False, True])
def test_directory_as_a_file_is_refused(tmp_path, trailing_slash):
    d = tmp_path / "d"
    d.mkdir()
    (d / "keep").write_text("k")
    with pytest.raises(IsADirectoryError, match="directory"):
        atomic_write_bytes(str(d) + ("/" if trailing_slash else ""), b"x")
    assert d.is_dir() and (d / "keep").read_text() == "k"
    # a new name with a trailing slash is a directory too, not a file called "new"
    with pytest.raises(IsADirectoryError):
        atomic_write_bytes(str(tmp_path / "new") + "/", b"x")
    assert not (tmp_path / "new").exists()


@pytest.mark.bad_input
def test_unwritable_path_is_one_clear_error(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(NotADirectoryError, match="file/out.png"):
        atomic_write_bytes(f / "out.png", b"x")
    with pytest.raises(NotADirectoryError):
        atomic_write_bytes(f / "deeper" / "out.png", b"x")
    assert f.read_text() == "x"


@pytest.mark.bad_input
@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(PermissionError, match="ro/out.png"):
            atomic_write_bytes(ro / "out.png", b"x")
    finally:
        ro.chmod(0o755)


@pytest.mark.bad_input
def test_output_paths_checked_up_front(tmp_path):
    """core.outputs: what the CLI checks before a long computation."""
    from lensdist_torch.core.outputs import check_output_dir, check_output_file

    (tmp_path / "f").write_text("x")
    os.mkfifo(tmp_path / "p.pt")
    assert check_output_file(tmp_path / "new" / "m.pt", "--out", suffixes=(".pt",)) == tmp_path / "new" / "m.pt"
    for bad, match in [
        (str(tmp_path / "d") + "/", "got the directory"),
        (tmp_path, "got the directory"),
        (tmp_path / "p.pt", "not a regular file"),
        (tmp_path / "m.pth", "ending in .pt"),
        (tmp_path / "f" / "m.pt", "is not a folder"),
    ]:
        with pytest.raises(ValueError, match=match):
            check_output_file(bad, "--out", suffixes=(".pt",))
    assert check_output_dir(tmp_path / "a" / "b", "--out") == tmp_path / "a" / "b"
    with pytest.raises(ValueError, match="exists and is not one"):
        check_output_dir(tmp_path / "f", "--out")
    assert not (tmp_path / "a").exists() and not (tmp_path / "d").exists()


# ------------------------------------------------------------------ versioned files and their content digest
@pytest.mark.bad_input
def test_content_digest_covers_every_value(tmp_path):
    """One changed value, key, type, dtype, stride or tensor byte changes the digest; dict order does not."""
    import torch

    from lensdist_torch.core.storage import DIGEST_KEY, content_digest

    base = {"a": torch.arange(6.0).reshape(2, 3), "b": [1, 2.5, "x", None, True], "c": {"k": 3}}
    d0 = content_digest(base)
    assert content_digest(dict(reversed(list(base.items())))) == d0
    assert content_digest({**base, DIGEST_KEY: "anything"}) == d0  # the digest never covers itself
    variants = [
        {**base, "a": base["a"].clone().index_put_((torch.tensor([1]), torch.tensor([2])), torch.tensor(5.0001))},
        {**base, "a": base["a"].double()},
        {**base, "a": base["a"].t().contiguous().t()},  # same values, other strides
        {**base, "b": [1, 2.5, "x", None, 1]},  # True and 1 differ
        {**base, "b": (1, 2.5, "x", None, True)},
        {**base, "c": {"k": 3.0}},
        {**base, "d": None},
        {"A": base["a"], "b": base["b"], "c": base["c"]},
    ]
    assert len({content_digest(v) for v in variants} | {d0}) == len(variants) + 1
    with pytest.raises(TypeError, match="no canonical encoding"):
        content_digest({"f": object()})


@pytest.mark.bad_input
def test_load_versioned_verifies_the_digest(tmp_path):
    import torch

    from lensdist_torch.core.storage import DIGEST_KEY, CheckpointError, load_versioned, save_versioned

    path = tmp_path / "m.pt"
    save_versioned(path, "k", 3, {"w": torch.ones(4), "name": "n"})
    back = load_versioned(path, kind="k", version=3, what="test", digest=True)
    assert DIGEST_KEY not in back and torch.equal(back["w"], torch.ones(4))
    raw = torch.load(path, weights_only=True)
    raw["w"][2] = 1.5
    torch.save(raw, tmp_path / "edited.pt")
    for digest in (False, True):  # a stored digest is always verified
        with pytest.raises(CheckpointError, match=r"edited\.pt is corrupted or edited"):
            load_versioned(tmp_path / "edited.pt", kind="k", version=3, what="test", digest=digest)
    del raw[DIGEST_KEY]
    torch.save(raw, tmp_path / "bare.pt")
    with pytest.raises(CheckpointError, match=r"bare\.pt carries no content digest"):
        load_versioned(tmp_path / "bare.pt", kind="k", version=3, what="test", digest=True)
    assert (
        load_versioned(tmp_path / "bare.pt", kind="k", version=3, what="test")["w"][2] == 1.5
    )  # not required: as before
    save_versioned(tmp_path / "plain.pt", "k", 3, {"w": torch.ones(1)}, digest=False)
    assert DIGEST_KEY not in torch.load(tmp_path / "plain.pt", weights_only=True)
