"""Output paths checked before a long computation, so that a bad path fails in a second.

Only the standard library: the command line imports this before torch.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_output_file", "check_output_dir"]


def check_output_file(path: str | Path, option: str, suffixes: tuple[str, ...], shown: str | None = None) -> Path:
    """Validate an output file before any long computation.

    It must be a file path (not a directory) with one of ``suffixes`` (``shown`` in the message),
    with nothing but a regular file there, in a folder that can be written.
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
    _check_writable(p.parent, option, path)
    return p


def check_output_dir(path: str | Path, option: str) -> Path:
    """Validate an output folder: a folder or nothing at ``path``, below a folder that can be written."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise ValueError(f"{option} must be a folder, but {path} exists and is not one")
    _check_writable(p, option, path)
    return p


def _check_writable(folder: Path, option: str, path: str) -> None:
    """The nearest existing ancestor of ``folder`` must be a folder we may write in."""
    here = folder.absolute()
    while not here.exists() and here != here.parent:
        here = here.parent
    if not here.is_dir():
        raise ValueError(f"cannot write {option} {path}: {here} is not a folder")
    if not os.access(here, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {option} {path}: permission denied in {here}")
