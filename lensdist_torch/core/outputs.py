"""Output paths checked before a long computation, so that a bad path fails in a second.

The one place that refuses an output path: a directory where a file is wanted, a device, an
unwritable folder, and an output that is one of the command's own inputs (the same file by
resolved path or ``os.path.samefile``: symlinks and hard links included), so that nothing a
command reads is overwritten, and an output inside an input folder (a data set gets no foreign
files). Only the standard library: the command line imports this before torch.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

#: The command's inputs by the option that names them (a path, a list of paths, or None).
Inputs = Mapping[str, "str | os.PathLike | Iterable[str | os.PathLike] | None"]

__all__ = ["check_output_file", "check_output_dir", "refuse_inputs", "refuse_inside", "refuse_data_sets",
           "refuse_foreign_folder"]


def check_output_file(
    path: str | Path, option: str, *, suffixes: tuple[str, ...], shown: str | None = None, inputs: Inputs | None = None
) -> Path:
    """Validate an output file before any long computation.

    It must be a file path (not a directory) with one of ``suffixes`` (``shown`` in the message),
    with nothing but a regular file there, in a folder that can be written, and none of
    ``inputs`` (the command's input paths by the option or argument that names them).
    """
    path = os.fspath(path)
    p = Path(path)
    want = shown or " or ".join(suffixes)
    if path.endswith(("/", os.sep)) or p.is_dir():
        raise ValueError(f"{option} must be a file path ending in {want}, got the directory {path!r}")
    if p.exists() and not p.is_file():
        raise ValueError(f"{option} {path} exists and is not a regular file (a device, FIFO or socket?)")
    if p.suffix.lower() not in suffixes:
        raise ValueError(f"{option} must be a file path ending in {want}, got {path!r}")
    refuse_inputs(p, option, inputs)
    refuse_data_sets(p.parent, option, path)
    _check_writable(p.parent, option, path)
    return p


def check_output_dir(path: str | Path, option: str, inputs: Inputs | None = None, *, writes: Iterable[str] = (),
                     data_set: bool = False) -> Path:
    """Validate an output folder: a folder or nothing at ``path``, below a folder that can be written.

    Neither the folder nor the files the command writes in it (``writes``, names relative to it)
    may be one of ``inputs``, and it may not lie in a lensdist data set (a folder holding the
    data set's manifest.json); ``data_set``: the folder is itself one (``lensdist generate``).
    """
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{option} must be a folder, but {path} exists and is not one")
    refuse_data_sets(p.parent if data_set else p, option, path)
    refuse_inputs(p, option, inputs)
    for name in writes:
        refuse_inputs(p / name, option, inputs, written=True)
    _check_writable(p, option, path)
    return p


def refuse_data_sets(folder: Path, option: str, path: str | Path) -> None:
    """Refuse (ValueError) writing in ``folder`` where it or an ancestor is a lensdist data set.

    A data set is a folder whose manifest.json is a JSON object with a ``fingerprint`` and
    ``sets`` (what ``lensdist generate`` writes): it gets no foreign files.
    """
    try:
        here = folder.resolve()
    except (OSError, RuntimeError):
        return
    for top in (here, *here.parents):
        manifest = top / "manifest.json"
        try:
            m = json.loads(manifest.read_text()) if manifest.is_file() else None
        except (OSError, ValueError):
            m = None
        if isinstance(m, dict) and "fingerprint" in m and "sets" in m:
            raise ValueError(f"{option} {os.fspath(path)} is inside the lensdist data set {top}: refusing to write "
                             "there (a data set gets no foreign files), give a path outside it")


#: The files ``lensdist generate`` writes at the top of a data set folder (its manifest, its locks,
#: their atomic writes' temporary files) and in a set's folder (shards, checksums, temporary files).
_DATA_SET_FILES = re.compile(r"manifest\.json|\.manifest\.lock|\.lock-\d+-of-\d+|\.manifest\.json\..+\.tmp")
_SHARD_FILES = re.compile(r"\.?shard-\d+\.pt(\.sha256)?(\..+\.tmp)?")


def refuse_foreign_folder(folder: str | Path, option: str, sets: Iterable[str]) -> None:
    """Refuse (ValueError) writing a data set into an existing folder that is neither empty nor a data set.

    A data set: a folder with a manifest.json (whose content the data set's own checks read),
    or one holding only what ``lensdist generate`` writes (a run stopped before its manifest: its
    locks, temporary files, and the folders of ``sets`` with shards in them). Anything else is
    someone's folder: generating into it would mix the data set with its files.
    """
    p = Path(folder)
    if not p.is_dir() or (p / "manifest.json").is_file():
        return
    sets = set(sets)

    def own(e: Path) -> bool:
        if e.is_dir() and not e.is_symlink():
            return e.name in sets and all(f.is_file() and _SHARD_FILES.fullmatch(f.name) for f in e.iterdir())
        return e.is_file() and bool(_DATA_SET_FILES.fullmatch(e.name))

    foreign = sorted(e.name for e in p.iterdir() if not own(e))
    if foreign:
        shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise ValueError(f"{option} {os.fspath(folder)} holds files that are not a lensdist data set ({shown}; no "
                         "manifest.json): refusing to write a data set among them, give an empty or new folder")


def _check_writable(folder: Path, option: str, path: str) -> None:
    """The nearest existing ancestor of ``folder`` must be a folder we may write in."""
    here = folder.absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        raise ValueError(f"cannot write {option} {path}: {here} is not a folder")
    if not os.access(here, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {option} {path}: permission denied in {here}")


def refuse_inputs(path: str | Path, option: str, inputs: Inputs | None, written: bool = False) -> None:
    """Refuse (ValueError) an output ``path`` that is one of ``inputs``.

    ``written``: ``path`` is a file the command writes inside the folder ``option`` names.
    """
    out = Path(path)
    for name, value in (inputs or {}).items():
        values = [value] if value is None or isinstance(value, (str, os.PathLike)) else list(value)
        for v in values:
            if v is not None and _same_path(out, Path(v)):
                what = f"{option} would overwrite {out}, which is" if written else f"{option} {os.fspath(path)} is"
                raise ValueError(
                    f"{what} the input {name} {os.fspath(v)}: refusing to overwrite an input, give another path"
                )


def refuse_inside(path: str | Path, option: str, folder: str | os.PathLike | None, folder_option: str) -> None:
    """Refuse (ValueError) an output ``path`` inside the input folder ``folder`` (a data set gets no foreign files).

    Inside: below the folder once both are resolved (symlinks followed), or, where ``path``
    exists, the same file as one in the folder (a hard link).
    """
    if folder is None:
        return
    out, top = Path(path), Path(folder)
    try:
        inside = top.resolve() in out.resolve().parents
    except (OSError, RuntimeError):  # a symlink loop: not provably inside
        inside = False
    if not inside and out.is_file() and top.is_dir():
        inside = any(_same_path(out, f) for f in top.rglob("*") if f.is_file())
    if inside:
        raise ValueError(f"{option} {os.fspath(path)} is inside the input {folder_option} folder {os.fspath(folder)}: "
                         "refusing to write there (a data set gets no foreign files), give a path outside it")


def _same_path(a: Path, b: Path) -> bool:
    """The same file or folder: the same resolved path, or (both existing) the same inode."""
    try:
        if a.resolve() == b.resolve():
            return True
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except (OSError, RuntimeError):  # unreadable, a symlink loop: not provably the same
        return False
