"""An archive's table: one row per input (:class:`ArchiveRow`), and the answer per camera.

The columns of ``answers.csv`` (and ``answers.parquet``) are :data:`ROW_COLUMNS`, the fields of
:class:`ArchiveRow` in order (its ``class_label`` is the column ``class``); those of
``cameras.csv`` are :data:`CAMERA_COLUMNS`, the fields of :class:`CameraSummary`. A row is
built from the answer of :func:`~lensdist_torch.calibration.controllers.calibrate.calibrate_path`
(:func:`answer_row`) or from the reason an input failed (:func:`failed_row`).

Per camera (:func:`camera_summaries`): the rows of one ``camera`` (the manifest's column, empty
for none) and one frame size form a group; its pooled Delta_avg is the inverse-variance mean of
its answered rows (a class, and a two-sided interval: std = half-width / 1.96), with the 95 %
interval of that mean. A row whose own interval does not hold the pooled value disagrees with it
(a lens changed, a zoom, a bad video): the one furthest out, in its own stds, is set aside and
the mean taken again over the others, until every row left holds it. The set-aside rows are the
group's ``disagreeing``: one changed lens never drags the camera's answer away from the rest.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from pathlib import Path

from lensdist_torch.core.storage import atomic_write_bytes, atomic_write_text

__all__ = ["ArchiveRow", "ROW_COLUMNS", "CameraSummary", "CAMERA_COLUMNS", "answer_row", "failed_row",
           "pool_delta_avg", "camera_summaries", "row_columns", "write_rows", "write_tables"]

#: The normal quantile of a 95 % interval: an interval's half-width / Z is its std.
Z95 = 1.959963984540054


@dataclasses.dataclass(frozen=True)
class ArchiveRow:
    """One input of an archive: its answer or why there is none (the columns of ``answers.csv``).

    ``ok``: the calibration ran to an answer (its JSON is ``answer``, relative to the output
    folder); ``class_label`` None with ``ok`` is "cannot tell" (``reason`` says why). ``digest``
    is the input's (:func:`~lensdist_torch.calibration.controllers.archive.input_digest`),
    ``settings`` the settings' digest; ``seconds`` the calibration's wall time, the only column
    that changes from one run of the same input to the next.

    Example:
        >>> row = failed_row(path="dive.mp4", camera="A", reason="path not found: dive.mp4", version="0")
        >>> row.ok, row.class_label, ROW_COLUMNS[:4]
        (False, None, ('path', 'camera', 'ok', 'class'))
    """

    path: str
    camera: str | None
    ok: bool
    class_label: str | None
    delta_avg_user_px: float | None
    delta_avg_low_px: float | None
    delta_avg_high_px: float | None
    delta_max_user_px: float | None
    delta_max_low_px: float | None
    delta_max_high_px: float | None
    k2_user: float | None
    k4_user: float | None
    frames: int | None
    height: int | None
    width: int | None
    method: str | None
    reason: str | None
    seconds: float | None
    digest: str | None
    settings: str | None
    answer: str | None
    version: str

    def columns(self) -> dict:
        """The row as {column: value}, in :data:`ROW_COLUMNS`' order.

        Example:
            >>> list(failed_row(path="a", camera=None, reason="r", version="0").columns())[3]
            'class'
        """
        return {"class" if f.name == "class_label" else f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_columns(cls, values: dict) -> ArchiveRow:
        """The row of :meth:`columns`' dict (a row file read back).

        Example:
            >>> row = failed_row(path="a", camera=None, reason="r", version="0")
            >>> ArchiveRow.from_columns(row.columns()) == row
            True
        """
        return cls(**{f.name: values["class" if f.name == "class_label" else f.name] for f in dataclasses.fields(cls)})


def row_columns(row_type) -> tuple[str, ...]:
    """A table's columns, in order: the fields of the dataclass ``row_type``, ``class_label`` as ``class``.

    Example:
        >>> row_columns(ArchiveRow) == ROW_COLUMNS
        True
    """
    return tuple("class" if f.name == "class_label" else f.name for f in dataclasses.fields(row_type))


#: The columns of ``answers.csv``, in order (:class:`ArchiveRow`'s fields, ``class_label`` as ``class``).
ROW_COLUMNS = row_columns(ArchiveRow)


def _interval(answer: dict, key: str) -> tuple:
    iv = answer.get(key) or (None, None)
    return (iv[0], iv[1]) if len(iv) == 2 else (None, None)


def answer_row(answer: dict, *, camera: str | None, seconds: float, digest: str, settings: str, answer_file: str,
               version: str) -> ArchiveRow:
    """The row of a :func:`~lensdist_torch.calibration.controllers.calibrate.calibrate_path` answer.

    Example:
        >>> ans = {"path": "d/", "class": "2", "delta_avg_user_px": 3.0, "delta_avg_user_interval": [2.5, 3.5],
        ...        "delta_max_user_px": 6.0, "delta_max_user_interval": [5.0, 7.0], "k2_user": 1e-6, "k4_user": 0.0,
        ...        "frames": 8, "image_size": [120, 160], "method": "direct", "reason": None}
        >>> row = answer_row(ans, camera=None, seconds=1.0, digest="ab", settings="cd", answer_file="answers/d.json",
        ...                  version="0")
        >>> row.ok, row.class_label, row.delta_avg_low_px, (row.height, row.width)
        (True, '2', 2.5, (120, 160))
    """
    (alo, ahi), (mlo, mhi) = _interval(answer, "delta_avg_user_interval"), _interval(answer, "delta_max_user_interval")
    h, w = answer.get("image_size") or (None, None)
    return ArchiveRow(path=str(answer["path"]), camera=camera, ok=True, class_label=answer.get("class"),
                      delta_avg_user_px=answer.get("delta_avg_user_px"), delta_avg_low_px=alo, delta_avg_high_px=ahi,
                      delta_max_user_px=answer.get("delta_max_user_px"), delta_max_low_px=mlo, delta_max_high_px=mhi,
                      k2_user=answer.get("k2_user"), k4_user=answer.get("k4_user"), frames=answer.get("frames"),
                      height=h, width=w, method=answer.get("method"), reason=answer.get("reason"), seconds=seconds,
                      digest=digest, settings=settings, answer=answer_file, version=version)


def failed_row(*, path: str, camera: str | None, reason: str, version: str, seconds: float | None = None,
               digest: str | None = None, settings: str | None = None) -> ArchiveRow:
    """The row of an input that gave no answer (unreadable, too few frames, ...): its reason.

    Example:
        >>> failed_row(path="two/", camera=None, reason="path two/ must hold at least 2 frames", version="0").reason
        'path two/ must hold at least 2 frames'
    """
    return ArchiveRow(path=path, camera=camera, ok=False, class_label=None, delta_avg_user_px=None,
                      delta_avg_low_px=None, delta_avg_high_px=None, delta_max_user_px=None, delta_max_low_px=None,
                      delta_max_high_px=None, k2_user=None, k4_user=None, frames=None, height=None, width=None,
                      method=None, reason=reason, seconds=seconds, digest=digest, settings=settings, answer=None,
                      version=version)


@dataclasses.dataclass(frozen=True)
class CameraSummary:
    """One camera group of an archive: its inputs, the pooled Delta_avg and who disagrees with it.

    ``camera``: the manifest's camera (None: not given); ``size``: "W x H" of its frames;
    ``answered``: its rows with a class and a two-sided interval, ``pooled`` of them in the
    pooled Delta_avg and its 95 % interval (None where none is answered); ``disagreeing``: the
    paths of the others, whose intervals do not hold it (module docstring).

    Example:
        >>> CAMERA_COLUMNS[:3]
        ('camera', 'size', 'inputs')
    """

    camera: str | None
    size: str
    inputs: int
    answered: int
    pooled: int
    delta_avg_px: float | None
    delta_avg_low_px: float | None
    delta_avg_high_px: float | None
    disagreeing: tuple[str, ...]

    def columns(self) -> dict:
        """The summary as {column: value} (``disagreeing`` joined by ``;``).

        Example:
            >>> CameraSummary(camera=None, size="160 x 120", inputs=1, answered=0, pooled=0, delta_avg_px=None,
            ...               delta_avg_low_px=None, delta_avg_high_px=None, disagreeing=()).columns()["disagreeing"]
            ''
        """
        out = dataclasses.asdict(self)
        out["disagreeing"] = ";".join(self.disagreeing)
        return out


#: The columns of ``cameras.csv``, in order (:class:`CameraSummary`'s fields).
CAMERA_COLUMNS = tuple(f.name for f in dataclasses.fields(CameraSummary))


def pool_delta_avg(values) -> tuple[float, float, float]:
    """The inverse-variance mean of (Delta_avg, low, high) triples and its 95 % interval.

    Each triple's std is its interval's half-width / 1.96; the mean's std is 1 / sqrt(sum of
    the weights); the interval stops at 0 (a Delta is a length).

    Example:
        >>> [round(v, 3) for v in pool_delta_avg([(2.0, 1.0, 3.0), (4.0, 3.0, 5.0)])]  # equal weights
        [3.0, 2.293, 3.707]
        >>> round(pool_delta_avg([(2.0, 1.0, 3.0), (4.0, 3.5, 4.5)])[0], 3)  # the narrower weighs 4 times more
        3.6
    """
    weights = [(2 * Z95 / (hi - lo)) ** 2 for _, lo, hi in values]
    if not weights:
        raise ValueError("pool_delta_avg needs at least one (Delta_avg, low, high) triple")
    total = sum(weights)
    mean = sum(w * d for w, (d, _, _) in zip(weights, values)) / total
    half = Z95 / math.sqrt(total)
    return mean, max(mean - half, 0.0), mean + half


def _answered(row: ArchiveRow) -> bool:
    d, lo, hi = row.delta_avg_user_px, row.delta_avg_low_px, row.delta_avg_high_px
    return row.ok and row.class_label is not None and None not in (d, lo, hi) and hi > lo


def _agreeing(rows: list[ArchiveRow]) -> tuple[list[ArchiveRow], tuple]:
    """The rows left once the furthest out is set aside while one's interval misses the pooled value; their pool."""
    kept = list(rows)
    while True:
        pooled = pool_delta_avg([(r.delta_avg_user_px, r.delta_avg_low_px, r.delta_avg_high_px) for r in kept])
        off = [r for r in kept if not r.delta_avg_low_px <= pooled[0] <= r.delta_avg_high_px]
        if not off or len(kept) == 1:
            return kept, pooled
        kept.remove(max(off, key=lambda r: abs(r.delta_avg_user_px - pooled[0]) * 2 * Z95
                        / (r.delta_avg_high_px - r.delta_avg_low_px)))


def camera_summaries(rows) -> list[CameraSummary]:
    """The rows grouped by camera and frame size (rows without a size left out), each group summarised.

    Example:
        >>> def row(path, d, lo, hi, camera="A"):
        ...     return answer_row({"path": path, "class": "2", "delta_avg_user_px": d,
        ...                        "delta_avg_user_interval": [lo, hi], "image_size": [120, 160]},
        ...                       camera=camera, seconds=0.0, digest="", settings="", answer_file="", version="0")
        >>> rows = [row("a", 3.0, 2.5, 3.5), row("b", 3.2, 2.8, 3.6), row("c", 3.1, 2.9, 3.3), row("d", 6.0, 5.5, 6.5)]
        >>> [s] = camera_summaries(rows)  # d's lens changed: set aside, the camera's answer from a, b, c
        >>> s.camera, s.size, s.answered, s.pooled, round(s.delta_avg_px, 2), s.disagreeing
        ('A', '160 x 120', 4, 3, 3.11, ('d',))
    """
    groups: dict[tuple, list[ArchiveRow]] = {}
    for row in rows:
        if row.height is not None and row.width is not None:
            groups.setdefault((row.camera, f"{row.width} x {row.height}"), []).append(row)
    out = []
    for (camera, size), members in groups.items():
        answered = [r for r in members if _answered(r)]
        kept, pooled = _agreeing(answered) if answered else ([], (None, None, None))
        out.append(
            CameraSummary(
                camera=camera,
                size=size,
                inputs=len(members),
                answered=len(answered),
                pooled=len(kept),
                delta_avg_px=pooled[0],
                delta_avg_low_px=pooled[1],
                delta_avg_high_px=pooled[2],
                disagreeing=tuple(r.path for r in answered if r not in kept),
            )
        )
    return out


def _csv(columns: tuple[str, ...], records: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for rec in records:
        writer.writerow(["" if rec[c] is None else rec[c] for c in columns])
    return buf.getvalue()


def write_rows(out: str | Path, rows, row_type=ArchiveRow) -> list[Path]:
    """Write a table of ``rows`` (``row_type``'s, with ``columns()``) as ``answers.csv`` in ``out``, atomically.

    Also as ``answers.parquet`` where pyarrow imports. The columns are ``row_type``'s fields in
    order (``class_label`` as ``class``), the table's header even without a row. Returns the
    files written.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     files = write_rows(tmp, [failed_row(path="a", camera=None, reason="path not found: a", version="0")])
        ...     lines = (Path(tmp) / "answers.csv").read_text().splitlines()
        >>> [f.name for f in files][0], lines[1][:9]
        ('answers.csv', 'a,,False,')
    """
    out = Path(out)
    columns = row_columns(row_type)
    records = [r.columns() for r in rows]
    atomic_write_text(out / "answers.csv", _csv(columns, records))
    written = [out / "answers.csv"]
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        pa = None
    if pa is not None:
        buf = io.BytesIO()
        pq.write_table(pa.Table.from_pylist(records, schema=_schema(pa, row_type)), buf)
        atomic_write_bytes(out / "answers.parquet", buf.getvalue())
        written.append(out / "answers.parquet")
    return written


def write_tables(out: str | Path, rows, cameras) -> list[Path]:
    """Write ``answers.csv``, ``answers.parquet`` (where pyarrow imports) and ``cameras.csv`` in ``out``, atomically.

    Returns the files written.

    Example:
        >>> import tempfile
        >>> rows = [failed_row(path="a", camera=None, reason="path not found: a", version="0")]
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     files = write_tables(tmp, rows, camera_summaries(rows))
        ...     header = (Path(tmp) / "answers.csv").read_text().splitlines()[0]
        >>> header.startswith("path,camera,ok,class,delta_avg_user_px"), [f.name for f in files][-1]
        (True, 'cameras.csv')
    """
    written = write_rows(out, rows)
    atomic_write_text(Path(out) / "cameras.csv", _csv(CAMERA_COLUMNS, [c.columns() for c in cameras]))
    return written + [Path(out) / "cameras.csv"]


def _schema(pa, row_type):
    """The Parquet columns' types, from ``row_type``'s annotations (a column of nulls keeps its type)."""
    kinds = {"str": pa.string(), "bool": pa.bool_(), "float": pa.float64(), "int": pa.int64()}
    return pa.schema(
        [(c, kinds[str(f.type).split(" ")[0]]) for c, f in zip(row_columns(row_type), dataclasses.fields(row_type))]
    )
