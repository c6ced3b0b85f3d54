"""Many pairs analysed in one run: one answer file per pair, one table, resumable (``lensdist analyze --pairs``).

:func:`run_pair_archive` runs :func:`~lensdist_torch.workflows.analyze.analyze_pair` on each pair
of a list (:func:`pair_inputs` reads it from a file) and writes, in ``out``, the books of a
calibrate archive (:mod:`~lensdist_torch.calibration.controllers.archive_book`)::

    answers/NAME-KEY.json   each pair's answer, byte for byte what `lensdist analyze IMG1 IMG2 --json` prints
    rows/NAME-KEY.json      each pair's row (PairRow) and its key: the run's bookkeeping
    answers.csv             one row per pair, in the list's order (answers.parquet where pyarrow imports)

NAME is the two images' name stems joined by ``__``; KEY the first 8 hex digits of the SHA-256
of the two paths as given, the pair's digest (:func:`pair_digest`: both files' bytes) and the
settings' (:func:`pair_settings_digest`: the method, the checkpoints' bytes, every setting, the
device's kind, the library's version). A rerun skips every pair whose row exists for its key. A
pair that fails (an unreadable image, two sizes) is a row with its reason, never the end of the
run; a pair whose images could not be read to a digest (a missing file) is tried again by a
rerun. ``shard=(I, N)`` runs the pairs k with k % N == I; the last share to finish writes the
whole table.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import time
from pathlib import Path

from lensdist_torch import __version__
from lensdist_torch.calibration.controllers.archive import input_digest
from lensdist_torch.calibration.controllers.archive_book import ArchiveBook, check_shard, payload_digest, share_of
from lensdist_torch.calibration.controllers.archive_table import row_columns, write_rows
from lensdist_torch.config import LensdistConfig, config_to_dict
from lensdist_torch.config.checks import one_line, or_defaults
from lensdist_torch.data.locks import lock
from lensdist_torch.workflows.analyze import analysis_config, analyze_pair
from lensdist_torch.workflows.reports import dumps_strict

__all__ = ["PairInput", "PairRow", "PAIR_COLUMNS", "PairArchiveRun", "pair_inputs", "pair_digest",
           "pair_settings_digest", "pair_row", "run_pair_archive"]


@dataclasses.dataclass(frozen=True, kw_only=True)
class PairInput:
    """One pair of a list: its two images and its camera group (None: none given).

    Example:
        >>> PairInput(img1="a.png", img2="b.png", camera="A").camera
        'A'
    """

    img1: str
    img2: str
    camera: str | None = None


@dataclasses.dataclass(frozen=True, kw_only=True)
class PairRow:
    """One pair of a pairs run: its answer or why there is none (the columns of its ``answers.csv``).

    ``ok``: the analysis ran to an answer (its JSON is ``answer``, relative to the output folder);
    ``class_label`` None with ``ok`` is "cannot tell", ``reason`` its codes (``cannot_tell_reasons``
    joined by ``;``); without ``ok``, ``reason`` is the error. As in the JSON, ``delta_avg`` and
    its 95 % interval ``delta_avg_low``, ``delta_avg_high`` are in analysis pixels, the
    ``*_user_px`` columns over the user's whole frame; ``height``, ``width`` the images' size.
    ``digest`` is the pair's (:func:`pair_digest`), ``settings`` the settings' digest,
    ``seconds`` the analysis's wall time, the only column that changes between two runs.

    Example:
        >>> row = PairRow(img1="a.png", img2="b.png", camera=None, ok=False, class_label=None, delta_avg_user_px=None,
        ...               delta_max_user_px=None, delta_avg=None, delta_avg_low=None, delta_avg_high=None,
        ...               confidence=None, reason="image file not found: a.png", method=None, height=None,
        ...               width=None, seconds=None, digest=None, settings=None, answer=None, version="0")
        >>> PairRow.from_columns(row.columns()) == row, PAIR_COLUMNS[:5]
        (True, ('img1', 'img2', 'camera', 'ok', 'class'))
    """

    img1: str
    img2: str
    camera: str | None
    ok: bool
    class_label: str | None
    delta_avg_user_px: float | None
    delta_max_user_px: float | None
    delta_avg: float | None
    delta_avg_low: float | None
    delta_avg_high: float | None
    confidence: float | None
    reason: str | None
    method: str | None
    height: int | None
    width: int | None
    seconds: float | None
    digest: str | None
    settings: str | None
    answer: str | None
    version: str

    def columns(self) -> dict:
        """The row as {column: value}, in :data:`PAIR_COLUMNS`' order.

        Example:
            >>> row = PairRow.from_columns({c: None for c in PAIR_COLUMNS} | {"class": "2"})
            >>> row.class_label, row.columns()["class"]
            ('2', '2')
        """
        return dict(zip(PAIR_COLUMNS, (getattr(self, f.name) for f in dataclasses.fields(self))))

    @classmethod
    def from_columns(cls, values: dict) -> PairRow:
        """The row of :meth:`columns`' dict (a row file read back).

        Example:
            >>> PairRow.from_columns({c: None for c in PAIR_COLUMNS} | {"img1": "a.png"}).img1
            'a.png'
        """
        return cls(**{f.name: values[c] for f, c in zip(dataclasses.fields(cls), PAIR_COLUMNS)})


#: The columns of a pairs run's ``answers.csv``, in order (:class:`PairRow`'s fields, ``class_label`` as ``class``).
PAIR_COLUMNS = row_columns(PairRow)


@dataclasses.dataclass(frozen=True, kw_only=True)
class PairArchiveRun:
    """What :func:`run_pair_archive` did: its counts, the table's rows and the files written.

    ``pairs``: all of the list's; ``selected``: this share's; ``computed``: analysed by this run;
    ``reused``: rows of an earlier run for the same key; ``rows``: the table (every pair with a
    row, other shares' too), ``failed`` of them without an answer.

    Example:
        >>> PairArchiveRun(out="o", pairs=2, selected=2, computed=2, reused=0, failed=0, rows=(), files=()).computed
        2
    """

    out: str
    pairs: int
    selected: int
    computed: int
    reused: int
    failed: int
    rows: tuple[PairRow, ...]
    files: tuple[str, ...]


def _fields(path: Path, number: int, line: str, header: list[str] | None) -> dict:
    """One line's {img1, img2, camera}: CSV under ``header``, else two paths separated by whitespace."""
    where = f"pairs file {path}, line {number}"
    if header is None:
        values = line.split()
        if len(values) != 2:
            raise ValueError(f"{where}: expected two image paths separated by whitespace (or a CSV file with an "
                             f"img1,img2 header), got {len(values)} field(s)")
        return {"img1": values[0], "img2": values[1]}
    row = dict(zip(header, (v.strip() for v in next(csv.reader([line]), []))))
    if not row.get("img1") or not row.get("img2"):
        raise ValueError(f"{where}: img1 and img2 must both be given")
    return row


def pair_inputs(file: str | Path) -> list[PairInput]:
    """The pairs listed in ``file``: CSV with columns ``img1``, ``img2`` (optionally ``camera``), or two paths per line.

    Blank lines and ``#`` comments are skipped; a CSV file is one whose first line names
    ``img1`` or ``img2`` (case aside), and then both must be columns; relative paths are
    relative to the file's folder. The same pair listed twice runs once. A file that is missing,
    lists nothing or has a line of another form: a one-line error naming it.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     _ = (Path(tmp) / "pairs.csv").write_text("img1,img2,camera" + chr(10) + "a.png,b.png,A" + chr(10))
        ...     _ = (Path(tmp) / "pairs.txt").write_text("# left right" + chr(10) + "a.png  b.png" + chr(10))
        ...     found = pair_inputs(Path(tmp) / "pairs.csv") + pair_inputs(Path(tmp) / "pairs.txt")
        >>> [(Path(p.img1).name, Path(p.img2).name, p.camera) for p in found]
        [('a.png', 'b.png', 'A'), ('a.png', 'b.png', None)]
    """
    path = Path(file)
    if not path.is_file():
        raise FileNotFoundError(f"pairs file not found: {path}")
    lines = [(n, line) for n, line in enumerate(path.read_text(encoding="utf-8-sig").splitlines(), 1)
             if line.strip() and not line.lstrip().startswith("#")]
    header = [c.strip().lower() for c in next(csv.reader([lines[0][1]]), [])] if lines else []
    if {"img1", "img2"} & set(header):
        missing = [c for c in ("img1", "img2") if c not in header]
        if missing:
            raise ValueError(f"pairs file {path}: its header has no {missing[0]} column (CSV needs img1,img2 and "
                             "optionally camera)")
        lines = lines[1:]
    else:
        header = None
    found, seen = [], set()
    for number, line in lines:
        row = _fields(path, number, line, header)
        pair = PairInput(img1=str(path.parent / row["img1"]), img2=str(path.parent / row["img2"]),
                         camera=(row.get("camera") or "").strip() or None)
        if (pair.img1, pair.img2) not in seen:
            seen.add((pair.img1, pair.img2))
            found.append(pair)
    if not found:
        raise ValueError(f"pairs file {path} lists no pair")
    return found


def pair_digest(img1: str | Path, img2: str | Path) -> str:
    """SHA-256 (hex) of a pair: each image's name, size and bytes, in order.

    Each image's digest is :func:`~lensdist_torch.calibration.controllers.archive.input_digest`.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     a, b = Path(tmp) / "a.png", Path(tmp) / "b.png"
        ...     _, _ = a.write_bytes(b"left"), b.write_bytes(b"right")
        ...     forward, backward = pair_digest(a, b), pair_digest(b, a)
        >>> len(forward), forward == backward
        (64, False)
    """
    h = hashlib.sha256(b"lensdist-pair-v1")
    for image in (img1, img2):
        h.update(bytes.fromhex(input_digest(image)))
    return h.hexdigest()


def pair_settings_digest(*, method: str = "selfcal", checkpoint=None, checkpoint_max=None, device=None,
                         settings: LensdistConfig | None = None) -> str:
    """SHA-256 (hex) of what decides a pair's answer besides its images: the method, checkpoint bytes, every setting.

    Also the device's kind and the library's version; a checkpoint is a path (None: the shipped one).

    Example:
        >>> pair_settings_digest() == pair_settings_digest(device="cpu")
        True
        >>> pair_settings_digest() == pair_settings_digest(method="regression")
        False
    """
    def file(path):
        return None if path is None else [str(path), input_digest(path)]

    payload = {
        "analysis": "pair",
        "method": method,
        "checkpoint": file(checkpoint),
        "checkpoint_max": file(checkpoint_max),
        "device": str(device or "cpu").split(":")[0],
        "config": config_to_dict(or_defaults(settings, LensdistConfig, "settings")),
        "version": __version__,
    }
    return payload_digest(payload)


def pair_row(answer: dict, *, pair: PairInput, seconds: float, digest: str, settings: str, answer_file: str,
             version: str) -> PairRow:
    """The row of a pair's answer: ``to_json()`` of its :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`.

    Example:
        >>> answer = {"method": "selfcal", "class": None, "delta_avg": None, "delta_avg_interval": None,
        ...           "confidence": 0.4, "cannot_tell_reasons": ["motion", "low_confidence"], "delta_avg_user_px": None,
        ...           "delta_max_user_px": None, "input_size": [320, 424]}
        >>> row = pair_row(answer, pair=PairInput(img1="a.png", img2="b.png"), seconds=1.0, digest="ab", settings="cd",
        ...                answer_file="answers/a__b-01234567.json", version="0")
        >>> row.ok, row.class_label, row.reason, (row.height, row.width)
        (True, None, 'motion;low_confidence', (320, 424))
    """
    low, high = answer.get("delta_avg_interval") or (None, None)
    height, width = answer.get("input_size") or (None, None)
    return PairRow(
        img1=pair.img1,
        img2=pair.img2,
        camera=pair.camera,
        ok=True,
        class_label=answer.get("class"),
        delta_avg_user_px=answer.get("delta_avg_user_px"),
        delta_max_user_px=answer.get("delta_max_user_px"),
        delta_avg=answer.get("delta_avg"),
        delta_avg_low=low,
        delta_avg_high=high,
        confidence=answer.get("confidence"),
        reason=";".join(answer.get("cannot_tell_reasons") or []) or None,
        method=answer.get("method"),
        height=height,
        width=width,
        seconds=seconds,
        digest=digest,
        settings=settings,
        answer=answer_file,
        version=version,
    )


class _Pairs(ArchiveBook):
    """The books of a pairs run: an item is a :class:`PairInput`, its row a :class:`PairRow`."""

    row_type = PairRow

    def ident(self, obj) -> str:
        return f"{obj.img1}\0{obj.img2}"

    def name(self, item: PairInput) -> str:
        return f"{Path(item.img1).stem}__{Path(item.img2).stem}"

    def digest(self, item: PairInput) -> str:
        return pair_digest(item.img1, item.img2)

    def failed_row(self, item: PairInput, reason: str, *, seconds: float | None = None,
                   digest: str | None = None) -> PairRow:
        return PairRow(img1=item.img1, img2=item.img2, camera=item.camera, ok=False, class_label=None,
                       delta_avg_user_px=None, delta_max_user_px=None, delta_avg=None, delta_avg_low=None,
                       delta_avg_high=None, confidence=None, reason=reason, method=None, height=None, width=None,
                       seconds=seconds, digest=digest, settings=self.settings, answer=None, version=__version__)

    def analyse(self, pair: PairInput, key: str, digest: str, kwargs: dict) -> None:
        """Analyse one pair as ``lensdist analyze IMG1 IMG2 --json`` does, and record its answer or its reason."""
        t0 = time.perf_counter()
        try:
            answer = analyze_pair(pair.img1, pair.img2, **kwargs).to_json()
        except Exception as exc:  # the pair's failure is its row, never the end of the run
            self.record(pair, key, digest, self.failed_row(pair, one_line(exc, 500), seconds=time.perf_counter() - t0,
                                                           digest=digest), final=not isinstance(exc, MemoryError))
            return
        seconds = time.perf_counter() - t0
        answer_file = f"answers/{self.stem(pair, key)}.json"
        row = pair_row(answer, pair=pair, seconds=seconds, digest=digest, settings=self.settings,
                       answer_file=answer_file, version=__version__)
        # what the command prints: cli.support.print_json, one object and its newline
        self.record(pair, key, digest, row, final=True, answer=dumps_strict(answer, indent=2) + "\n")


def run_pair_archive(
    pairs,
    out: str | Path,
    *,
    method: str = "selfcal",
    checkpoint=None,
    checkpoint_max=None,
    settings: LensdistConfig | None = None,
    device=None,
    shard: tuple[int, int] = (0, 1),
    quiet: bool = True,
) -> PairArchiveRun:
    """Analyse every pair into ``out`` (module docstring): answers, rows, ``answers.csv``.

    Args:
        pairs: :class:`PairInput` or (img1, img2) paths (:func:`pair_inputs` reads a file of them).
        out: the output folder (made where missing; a rerun into it resumes).
        method: "selfcal", "regression" or "eigenspace", as :func:`~lensdist_torch.workflows.analyze.analyze_pair`
            takes it, for every pair.
        checkpoint: the learned methods' checkpoint, a path (None: the shipped one).
        checkpoint_max: the eigen-space's Delta_max checkpoint, a path (None: the shipped one).
        settings: the library's :class:`~lensdist_torch.config.LensdistConfig` (None: the defaults).
        device: where the analysis runs.
        shard: (I, N): this run's share of the pairs, those k with k % N == I.
        quiet: no progress bar.

    Returns:
        A :class:`PairArchiveRun`; a pair that fails is a row with its reason, never an exception.
        The options are checked (and the checkpoints loaded) before any pair.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     run = run_pair_archive([(Path(tmp) / "a.png", Path(tmp) / "b.png")], Path(tmp) / "out")
        ...     header = (Path(tmp) / "out" / "answers.csv").read_text().split(",")[:4]
        >>> run.failed, run.rows[0].reason.startswith("path not found"), header
        (1, True, ['img1', 'img2', 'camera', 'ok'])
    """
    from tqdm import tqdm

    shard = check_shard(shard)
    items = [p if isinstance(p, PairInput) else PairInput(img1=str(p[0]), img2=str(p[1])) for p in pairs]
    if not items:
        raise ValueError("a pairs run needs at least one pair")
    analysis_config(method=method, checkpoint=checkpoint, checkpoint_max=checkpoint_max, config=settings)
    sdigest = pair_settings_digest(method=method, checkpoint=checkpoint, checkpoint_max=checkpoint_max, device=device,
                                   settings=settings)
    kwargs = {"method": method, "checkpoint": checkpoint, "checkpoint_max": checkpoint_max, "config": settings,
              "device": device}
    selected = items[shard[0]::shard[1]]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with share_of(out, shard), tqdm(total=len(selected), disable=quiet, desc="pairs", unit="pair") as bar:
        book = _Pairs(out, sdigest, bar)
        try:
            for pair, key, digest in book.pending(selected):
                book.analyse(pair, key, digest, kwargs)
        finally:  # also on Ctrl-C: the table of every finished pair
            with lock(out / ".table.lock", wait_s=120.0):
                rows = book.table(items)
                files = write_rows(out, rows, PairRow)
    return PairArchiveRun(out=str(out), pairs=len(items), selected=len(selected), computed=book.computed,
                          reused=book.reused, failed=sum(not r.ok for r in rows), rows=tuple(rows),
                          files=tuple(str(f) for f in files))
