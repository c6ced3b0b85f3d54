"""The worker processes of ``lensdist generate --workers N``, and how a run stops.

* Ctrl-C reaches the whole process group. The workers are started with SIGINT ignored (set in
  the parent while the pool starts, so that it holds from the first instruction of the new
  interpreter, imports included): only the parent sees KeyboardInterrupt, and leaving the
  pool terminates the workers (SIGTERM, silent).
* SIGTERM to the parent (``stop_on_sigterm``) prints one line and raises SystemExit(143): the
  pool terminates its workers, the lock is released, the shards written so far are kept.
* A worker whose parent died anyway (SIGKILL) exits at once and quietly (a watcher thread
  polls its parent pid), instead of finishing its shard and failing on the broken pipe.

Shards are written atomically, so a stopped run leaves whole shards or none; the next run
resumes byte-identical.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import sys
import threading
import time

__all__ = ["worker_pool", "stop_on_sigterm", "parent_alive"]

_PARENT: int | None = None
_POLL_S = 0.2


def parent_alive() -> bool:
    """Whether the process that started this worker still runs (always True outside a worker)."""
    return _PARENT is None or os.getppid() == _PARENT


def _watch_parent() -> None:
    while parent_alive():
        time.sleep(_POLL_S)
    os._exit(0)  # the parent is gone: nobody reads our result, say nothing


def _init_worker(parent: int) -> None:
    global _PARENT
    _PARENT = parent
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_watch_parent, name="lensdist-parent-watch", daemon=True).start()


@contextlib.contextmanager
def _sigint_ignored():
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def worker_pool(workers: int):
    """A spawn pool of ``workers`` processes that ignore SIGINT and exit quietly if this process dies."""
    ctx = mp.get_context("spawn")
    with _sigint_ignored():
        pool = ctx.Pool(workers, initializer=_init_worker, initargs=(os.getpid(),))
    with pool:  # leaving it (normally or by an exception) terminates the workers
        yield pool


def _on_sigterm(signum, frame):
    print("lensdist generate: terminated (SIGTERM); the shards written so far are kept, rerun to resume", file=sys.stderr)
    raise SystemExit(128 + signal.SIGTERM)


@contextlib.contextmanager
def stop_on_sigterm():
    """While the block runs, SIGTERM stops it cleanly: one line on stderr, then SystemExit(143)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
