"""Lock files of a data set folder: one run at a time writes a share of the shards.

A lock is a file created with O_CREAT | O_EXCL holding the pid and host of its run. A lock
left by a dead process of this host is taken over (with a note on stderr); one of another host
cannot be checked and stays live until deleted. ``share_lock`` holds ``.lock-I-of-N`` for the
share I/N of ``lensdist generate --shard`` and refuses to run beside a live overlapping share
(the shares of one array job do not overlap and run side by side); ``lock`` is the plain lock,
optionally waiting for a short critical section such as the manifest's read-merge-write.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import socket
import sys
import time
from pathlib import Path

__all__ = ["DataSetLocked", "lock", "share_lock"]

_LOCK_NAME = re.compile(r"\.lock-(\d+)-of-(\d+)")
_HELD: set[Path] = set()  # the lock files this process holds
STALE_UNREADABLE_S = 60.0  # a lock file still empty or unreadable after this long is stale


class DataSetLocked(ValueError):
    """Another run is writing the same shards of the data set folder (the message names its lock file)."""


def _lock_holder(path: Path) -> tuple[int, str] | None:
    """(pid, host) written in a lock file; None if it cannot be read (being written, or damaged)."""
    try:
        parts = path.read_text().split()
    except (OSError, UnicodeDecodeError):
        return None
    if len(parts) != 2 or not parts[0].isdigit() or int(parts[0]) < 1:
        return None
    return int(parts[0]), parts[1]


def _is_stale(path: Path) -> bool:
    """A lock left by a dead process of this host (or unreadable for a minute).

    A lock of another host cannot be checked: it is live until deleted.
    """
    holder = _lock_holder(path)
    if holder is None:
        try:
            return time.time() - path.stat().st_mtime > STALE_UNREADABLE_S
        except FileNotFoundError:
            return True
    pid, host = holder
    if host != socket.gethostname():
        return False
    if pid == os.getpid():
        return path not in _HELD  # our pid, but not our lock: a dead run's pid reused
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False  # alive, another user's
    return False


def _try_lock(path: Path) -> bool:
    """Create ``path`` exclusively (O_CREAT | O_EXCL) with our pid and host; False if it exists."""
    try:
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
    except FileExistsError:
        return False
    with os.fdopen(fd, "w") as f:
        f.write(f"{os.getpid()} {socket.gethostname()}\n")
    _HELD.add(path)
    return True


def _take(path: Path) -> bool:
    """Lock ``path``, taking over a stale lock; False while a live run holds it."""
    if _try_lock(path):
        return True
    if not _is_stale(path):
        return False
    holder = _lock_holder(path)
    print(f"lensdist: taking over the stale lock {path} (held by {holder or 'nobody readable'})", file=sys.stderr)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    return _try_lock(path)


def _release(path: Path) -> None:
    _HELD.discard(path)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


def _busy(out: Path, path: Path) -> str:
    pid, host = _lock_holder(path) or ("?", "?")
    return (
        f"another `lensdist generate` (pid {pid} on {host}) is writing shards of {out}: wait for it to "
        f"finish, or delete {path} if no such run is going"
    )


@contextlib.contextmanager
def lock(path: Path, wait_s: float = 0.0):
    """Hold the lock file ``path``; waits up to ``wait_s`` for a live holder, then DataSetLocked."""
    path = Path(path)
    deadline = time.monotonic() + wait_s
    while not _take(path):
        if time.monotonic() >= deadline:
            raise DataSetLocked(_busy(path.parent, path))
        time.sleep(0.05)
    try:
        yield
    finally:
        _release(path)


@contextlib.contextmanager
def share_lock(out: Path, shard: tuple[int, int]):
    """Hold ``out/.lock-I-of-N`` while a run writes; DataSetLocked if a live run holds an overlapping share.

    Shares I/N and J/M have shards in common iff I = J mod gcd(N, M).
    """
    out = Path(out)
    i, n = shard
    out.mkdir(parents=True, exist_ok=True)
    with lock(out / f".lock-{i}-of-{n}"):
        for other in out.glob(".lock-*-of-*"):
            name = _LOCK_NAME.fullmatch(other.name)
            if name is None or other.name == f".lock-{i}-of-{n}":
                continue
            j, m = int(name[1]), int(name[2])
            if m >= 1 and (i - j) % math.gcd(n, m) == 0 and not _is_stale(other):
                raise DataSetLocked(_busy(out, other))
        yield
