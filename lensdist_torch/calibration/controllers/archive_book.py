"""An archive run's books, whatever its items are: keys, row files, resuming, the table of every share.

``lensdist calibrate`` over many inputs (:mod:`~lensdist_torch.calibration.controllers.archive`,
an item a folder or a video) and ``lensdist analyze --pairs`` (:mod:`~lensdist_torch.workflows.pair_archive`,
an item a pair of images) keep the same books in their output folder::

    answers/NAME-KEY.json   each item's answer, where it has one
    rows/NAME-KEY.json      each item's row and its key: {"key", "final", "row"}

KEY (:func:`archive_key`) is the SHA-256 of the item's identity (its path or paths as given), the
digest of its bytes and the settings' digest; NAME-KEY (:func:`archive_stem`) its name and the
key's first 8 hex digits. An item's files are written atomically as soon as it finishes, the
answer before the row, so an interrupted run loses at most the items in flight; a rerun reuses
every item whose row file holds the same key, is final and whose answer file exists
(:meth:`ArchiveBook.pending`). :meth:`ArchiveBook.table` gives the table of every item with a row
under these settings: this run's and the other shares'.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob
import hashlib
import json
import re
from pathlib import Path

from lensdist_torch.config.checks import one_line
from lensdist_torch.core.storage import atomic_write_text
from lensdist_torch.data.locks import DataSetLocked, share_lock

__all__ = ["ArchiveBook", "payload_digest", "archive_key", "archive_stem", "check_shard", "read_row_file", "share_of"]


def payload_digest(payload: dict) -> str:
    """SHA-256 (hex) of a run's settings as canonical strict JSON (keys sorted): one digest for every archive.

    Example:
        >>> payload_digest({"b": 1, "a": [2.0]}) == payload_digest({"a": [2.0], "b": 1})
        True
    """
    return hashlib.sha256(json.dumps(payload, sort_keys=True, allow_nan=False).encode()).hexdigest()


def archive_key(ident: str, digest: str | None, settings: str) -> str:
    """SHA-256 (hex) of an item's identity, its digest (None: it could not be read) and the settings' digest.

    Example:
        >>> archive_key("dive.mp4", "ab", "cd") == archive_key("dive.mp4", "ab", "ce")  # other settings
        False
        >>> archive_key("dive.mp4", None, "cd") == archive_key("dive.mp4", "", "cd")
        True
    """
    return hashlib.sha256(f"{ident}\0{digest or ''}\0{settings}".encode()).hexdigest()


def _safe(name: str) -> str:
    """``name`` with characters other than letters, digits, ``._-`` as ``_``, at most 80 of them."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)[:80] or "input"


def archive_stem(name: str, key: str) -> str:
    """NAME-KEY8, the stem of an item's answer and row files (``name`` kept to letters, digits and ``._-``).

    Example:
        >>> archive_stem("dive 01.mp4", "0123456789abcdef")
        'dive_01.mp4-01234567'
    """
    return f"{_safe(name)}-{key[:8]}"


def read_row_file(file: str | Path, row_type) -> tuple[dict, object] | None:
    """A row file's (bookkeeping, row of ``row_type``), None where it is missing or unreadable (the item runs again).

    Example:
        >>> from lensdist_torch.calibration.controllers.archive_table import ArchiveRow
        >>> read_row_file("/no/such/rows/a-01234567.json", ArchiveRow) is None
        True
    """
    try:
        data = json.loads(Path(file).read_text())
        return data, row_type.from_columns(data["row"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def check_shard(shard) -> tuple[int, int]:
    """``shard`` as (I, N), two ints with 0 <= I < N (the items k with k % N == I), else a one-line ValueError.

    Example:
        >>> check_shard((1, 4))
        (1, 4)
        >>> check_shard((4, 4))
        Traceback (most recent call last):
        ...
        ValueError: shard must be (I, N), two ints with 0 <= I < N, got (4, 4)
    """
    if not (isinstance(shard, (tuple, list)) and len(shard) == 2 and all(type(v) is int for v in shard)
            and 0 <= shard[0] < shard[1]):
        raise ValueError(f"shard must be (I, N), two ints with 0 <= I < N, got {shard!r}")
    return (shard[0], shard[1])


@contextlib.contextmanager
def share_of(out: str | Path, shard: tuple[int, int]):
    """Hold share I of N of the folder ``out`` while a run writes it; another run holding it: a one-line ValueError.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp, share_of(tmp, (0, 2)):
        ...     try:
        ...         with share_of(tmp, (0, 2)):
        ...             pass
        ...     except ValueError as err:
        ...         print(str(err).split(" of ")[0])
        another run is writing share 0/2
    """
    out = Path(out)
    try:
        with share_lock(out, tuple(shard)):
            yield
    except DataSetLocked:
        raise ValueError(
            f"another run is writing share {shard[0]}/{shard[1]} of {out} (its lock file is "
            f"{out}/.lock-{shard[0]}-of-{shard[1]}): wait for it, or delete the lock if no such run is going"
        ) from None


class ArchiveBook:
    """One run's books: which items need an answer, each finished item's files, the table in the items' order.

    A subclass says what its items are: ``row_type`` (a frozen dataclass with ``columns()``,
    ``from_columns()`` and the fields ``camera``, ``settings`` and ``answer``), :meth:`digest`
    and :meth:`failed_row`, and, where an item is not one ``path``, :meth:`ident` and
    :meth:`name`. Items carry a ``camera``: not part of the key, so regrouping reuses every
    answer. ``bar``: a tqdm bar over the items (None: none); ``computed`` and ``reused`` count
    this run's items.

    Example:
        >>> import tempfile
        >>> from lensdist_torch.calibration.controllers.archive import ArchiveInput, input_digest
        >>> from lensdist_torch.calibration.controllers.archive_table import ArchiveRow, failed_row
        >>> class Book(ArchiveBook):
        ...     row_type = ArchiveRow
        ...     def digest(self, item):
        ...         return input_digest(item.path)
        ...     def failed_row(self, item, reason, *, seconds=None, digest=None):
        ...         return failed_row(path=item.path, camera=item.camera, reason=reason, version="0", seconds=seconds,
        ...                           digest=digest, settings=self.settings)
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     book, item = Book(Path(tmp), "settings"), ArchiveInput(path=str(Path(tmp) / "missing.mp4"))
        ...     todo = list(book.pending([item]))  # unreadable: its row at once, nothing to compute
        ...     rows = book.table([item])
        >>> todo, rows[0].reason.startswith("path not found"), book.computed
        ([], True, 0)
    """

    row_type: type

    def __init__(self, out: Path, settings: str, bar=None):
        self.out, self.settings, self.bar = Path(out), settings, bar
        self.rows: dict[str, object] = {}
        self.computed = self.reused = 0

    def ident(self, obj) -> str:
        """An item's identity (part of its key), the same for the item and its row: its path as given."""
        return obj.path

    def name(self, item) -> str:
        """The NAME of an item's files: its file or folder name."""
        return Path(item.path).name

    def digest(self, item) -> str:
        """SHA-256 (hex) over the bytes the item's answer reads; OSError or ValueError where they cannot be read."""
        raise NotImplementedError

    def failed_row(self, item, reason: str, *, seconds: float | None = None, digest: str | None = None):
        """The row of an item without an answer, with its reason."""
        raise NotImplementedError

    def stem(self, item, key: str) -> str:
        """NAME-KEY8 of the item's files; its answer file is ``answers/STEM.json`` below the output folder."""
        return archive_stem(self.name(item), key)

    def _step(self) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def pending(self, selected):
        """Yield (item, key, digest) of the items to compute; the others reused, or recorded as failed (unreadable)."""
        for item in selected:
            if self.bar is not None:
                self.bar.set_postfix_str(self.name(item), refresh=False)
            try:
                digest = self.digest(item)
            except (OSError, ValueError) as exc:
                self.record(item, archive_key(self.ident(item), None, self.settings), None,
                            self.failed_row(item, one_line(exc, 500)), final=False)
                continue
            key = archive_key(self.ident(item), digest, self.settings)
            found = read_row_file(self.out / "rows" / f"{self.stem(item, key)}.json", self.row_type)
            if found is not None and found[0].get("key") == key and found[0].get("final") and (
                    found[1].answer is None or (self.out / found[1].answer).is_file()):
                self.rows[self.ident(item)] = dataclasses.replace(found[1], camera=item.camera)
                self.reused += 1
                self._step()
                continue
            yield item, key, digest

    def record(self, item, key: str, digest: str | None, row, *, final: bool, answer: str | None = None) -> None:
        """Write the item's answer file (``answer``, its text, if it has one), then its row file; the row in the table.

        ``final``: a rerun reuses the row (False: the item is tried again, as where it could not be
        read to a ``digest``, which is None then and the item not counted as computed).
        """
        stem = self.stem(item, key)
        if answer is not None:
            atomic_write_text(self.out / "answers" / f"{stem}.json", answer)
        atomic_write_text(
            self.out / "rows" / f"{stem}.json",
            json.dumps({"key": key, "final": final, "row": row.columns()}, indent=1, allow_nan=False) + "\n",
        )
        self.rows[self.ident(item)] = row
        self.computed += digest is not None
        self._step()

    def table(self, items) -> list:
        """Every item's row, in order: this run's, else the newest row file of its identity under these settings."""
        out = []
        for item in items:
            row = self.rows.get(self.ident(item))
            if row is None:
                files = sorted(self.out.glob(f"rows/{glob.escape(_safe(self.name(item)))}-*.json"),
                               key=lambda f: f.stat().st_mtime, reverse=True)
                rows = (read_row_file(f, self.row_type) for f in files)
                row = next((r for _, r in filter(None, rows)
                            if self.ident(r) == self.ident(item) and r.settings == self.settings), None)
            if row is not None:
                out.append(dataclasses.replace(row, camera=item.camera))
        return out
