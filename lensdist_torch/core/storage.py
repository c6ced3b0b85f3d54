"""Files that are never half-written, and versioned checkpoints read with weights_only=True."""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
from pathlib import Path

import torch

__all__ = [
    "CheckpointError",
    "atomic_write_bytes",
    "atomic_write_text",
    "save_versioned",
    "load_versioned",
    "check_compatible",
]


class CheckpointError(ValueError):
    """A checkpoint of another kind or format version, corrupted, or fitted under another config."""


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write to a temporary file beside ``path``, fsync, then ``os.replace``: all or nothing.

    Only a regular file (or nothing) at ``path`` is replaced: a directory, a device such as
    /dev/null, a FIFO or a socket there raises OSError naming it and is left as it was.
    """
    if isinstance(path, str) and path.endswith(("/", os.sep)):
        raise IsADirectoryError(f"{path} names a directory; a file path is needed")
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a directory; a file path is needed")
    if path.exists() and not path.is_file():
        raise OSError(f"{path} exists and is not a regular file (a device, FIFO or socket?): refusing to replace it")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except (FileExistsError, NotADirectoryError):
        raise NotADirectoryError(f"cannot write {path}: a parent of it is not a directory") from None
    except PermissionError:
        raise PermissionError(f"cannot write {path}: permission denied in {path.parent}") from None
    try:
        os.chmod(tmp, 0o644)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_text(path: str | Path, text: str) -> None:
    """:func:`atomic_write_bytes` of UTF-8 text."""
    atomic_write_bytes(path, text.encode())


def save_versioned(path: str | Path, kind: str, version: int, payload: dict) -> str:
    """``torch.save`` of {kind, format_version, **payload}, atomically; returns the sha256 (hex) of the bytes.

    The bytes never depend on the file name (torch.save into memory first).
    """
    buf = io.BytesIO()
    torch.save({"kind": kind, "format_version": version, **payload}, buf)
    data = buf.getvalue()
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def load_versioned(
    path: str | Path, kind: str, version: int, what: str, map_location="cpu", *,
    sha256: str | None = None, error: type[Exception] = CheckpointError, noun: str = "checkpoint",
) -> dict:
    """Load with ``torch.load(weights_only=True)`` and check the kind and format version.

    With ``sha256``, the file's bytes must have that digest (checked before they are unpickled).
    ``error`` is the exception raised and ``noun`` names the file in its one-line message.

    Raises:
        FileNotFoundError: no such file.
        CheckpointError (or ``error``): corrupted, another kind, or another format version
            (the message says which).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{noun} not found: {path}")
    data = path.read_bytes()
    if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
        raise error(f"{noun} {path} is corrupted: its sha256 is not the one recorded when it was written")
    try:
        payload = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several types for truncated or foreign files
        detail = " ".join(str(exc).split("WeightsUnpickler error:")[-1].split())[:160]
        raise error(f"{noun} {path} is corrupted or not a torch file: {detail}") from exc
    if not isinstance(payload, dict) or payload.get("kind") != kind:
        raise error(f"{path} is not a lensdist {what} {noun}")
    if payload.get("format_version") != version:
        raise error(
            f"{noun} {path} has format version {payload.get('format_version')}, this library reads {version}"
        )
    return payload


def check_compatible(have, want, path) -> None:
    """Raise CheckpointError where a checkpoint's config (``have``) differs from ``want``.

    Compared, in order: image size, block size, quality thresholds; the first difference is named.
    """
    checks = [
        ("image size", (have.image.height, have.image.width), (want.image.height, want.image.width)),
        ("block size", have.quality.block_size, want.quality.block_size),
        (
            "quality thresholds (theta_g, theta_e, theta_d)",
            (have.quality.theta_g, have.quality.theta_e, have.quality.theta_d),
            (want.quality.theta_g, want.quality.theta_e, want.quality.theta_d),
        ),
    ]
    for what, a, b in checks:
        if a != b:
            raise CheckpointError(f"checkpoint {path} was fitted with {what} {a}, but {b} is expected")
