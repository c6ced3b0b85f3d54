"""The candidates of the multi-view comparison fitted side by side, in worker processes.

Every candidate (a COLMAP camera model, or another path's camera held on the tracks) is a dozen
bundle adjustments on the same tracks (:mod:`~lensdist_torch.calibration.multiview_fits`).
pycolmap holds Python's lock while Ceres solves, and Ceres' Schur solver gains little from a
second thread, so threads do not run two candidates at once: processes do. Where the tracks hold
at least :data:`PROCESSES_FROM` observations, :func:`candidate_fits` writes them once to a
temporary folder and starts ``processes`` workers (``python -m`` this module, the same package:
no caller's script runs again in them, as it would in a spawned ``multiprocessing`` pool), each
reading the tracks once and fitting the candidates it is handed; below it (where a worker's
imports, a few seconds, cost more than the fits) they are fitted here, one after the other.
Either way a candidate's fit is the same code on the same tracks (docs/method.md, section 11).
"""

from __future__ import annotations

import contextlib
import os
import pickle
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

from lensdist_torch.calibration.multiview_fits import fit_held_camera, fit_model, pycolmap_or_error, quiet_log

__all__ = ["PROCESSES_FROM", "candidate_fits"]

#: Observations from which the candidates are fitted in worker processes (below it, starting a worker costs more
#: than it saves: its imports take seconds, a candidate's adjustments on so few tracks a second or less).
PROCESSES_FROM = 20_000


def _fit(rec, kind: str, kwargs: dict) -> dict:
    """One candidate: ``kind`` "model" (:func:`fit_model` with ``kwargs``) or "held" (:func:`fit_held_camera`)."""
    if kind == "model":
        return fit_model(rec, **kwargs)
    if kind == "held":
        return fit_held_camera(rec, kwargs["camera"], kwargs["n_blocks"])
    raise ValueError(f"kind must be 'model' or 'held', got {kind!r}")


class _Worker:
    """One worker process (this module's ``__main__``) on the tracks in ``folder``, fed one candidate at a time."""

    def __init__(self, folder: str):
        root = str(Path(__file__).resolve().parents[2])  # the lensdist_torch this process runs, first on the path
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p))
        self.proc = subprocess.Popen([sys.executable, "-m", __name__, folder], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=env)

    def run(self, kind: str, kwargs: dict) -> dict:
        pickle.dump((kind, kwargs), self.proc.stdin)
        self.proc.stdin.flush()
        try:
            ok, value = pickle.load(self.proc.stdout)
        except EOFError:
            raise RuntimeError(f"a worker fitting the candidates ended (exit status {self.proc.wait()})") from None
        if not ok:
            raise value
        return value

    def close(self) -> None:
        with contextlib.suppress(OSError):  # a worker killed already has no pipe to close
            self.proc.stdin.close()
        self.proc.wait()


@contextlib.contextmanager
def candidate_fits(rec, observations: int, *, processes: int) -> Iterator:
    """A ``submit(kind, **kwargs) -> Future`` that fits one candidate on ``rec``'s tracks (module docstring).

    ``kind`` "model": :func:`~lensdist_torch.calibration.multiview_fits.fit_model` with ``kwargs``;
    "held": :func:`~lensdist_torch.calibration.multiview_fits.fit_held_camera` with ``camera`` and
    ``n_blocks``. In ``processes`` workers where ``processes`` > 1 and ``observations`` >=
    :data:`PROCESSES_FROM`, else here when submitted. The workers and the folder go when the block ends.

    Example:
        >>> with candidate_fits(None, 0, processes=2) as submit:  # too few observations: fitted here
        ...     print(submit("other").exception())
        kind must be 'model' or 'held', got 'other'
    """
    if processes < 2 or observations < PROCESSES_FROM:
        def here(kind: str, **kwargs) -> Future:
            done = Future()
            try:
                done.set_result(_fit(rec, kind, kwargs))
            except Exception as exc:  # noqa: BLE001 (handed over in the future, as a worker's error is)
                done.set_exception(exc)
            return done

        yield here
        return
    workers, local = [], threading.local()
    with tempfile.TemporaryDirectory(prefix="lensdist-tracks-") as tmp, ThreadPoolExecutor(processes) as feeders:
        rec.write(tmp)

        def run(kind: str, kwargs: dict) -> dict:  # in a feeder thread, on that thread's own worker
            if not hasattr(local, "worker"):
                local.worker = _Worker(tmp)
                workers.append(local.worker)
            return local.worker.run(kind, kwargs)

        try:
            yield lambda kind, **kwargs: feeders.submit(run, kind, kwargs)
        except BaseException:  # failed or interrupted: the workers stop now, not after their candidates
            for worker in workers:
                worker.proc.kill()
            raise
        finally:
            feeders.shutdown(wait=True, cancel_futures=True)
            for worker in workers:
                worker.close()


def _serve(folder: str) -> None:
    """A worker's loop: read the tracks once, then fit each (kind, kwargs) read from stdin, answering on stdout."""
    import torch

    torch.set_num_threads(1)  # the workers share the cores
    answers = os.fdopen(os.dup(1), "wb")  # the answers' own channel: anything printed goes to stderr
    os.dup2(2, 1)
    with quiet_log():
        rec = pycolmap_or_error().Reconstruction(folder)
    tasks = sys.stdin.buffer
    while True:
        try:
            kind, kwargs = pickle.load(tasks)
        except EOFError:
            return
        try:
            with quiet_log():
                answer = (True, _fit(rec, kind, kwargs))
        except Exception as exc:  # noqa: BLE001 (raised again in the caller)
            answer = (False, exc)
        pickle.dump(answer, answers)
        answers.flush()


if __name__ == "__main__":
    _serve(sys.argv[1])
