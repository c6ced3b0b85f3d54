"""Files that are never half-written, and versioned checkpoints read with weights_only=True.

A versioned file written with ``digest=True`` (the default) carries ``content_sha256``, the
SHA-256 of a canonical encoding of everything else in it (:func:`content_digest`): dict keys
sorted, every value tagged with its type, each tensor by dtype, shape, stride, storage offset
and the bytes of its storage (each storage once). One changed value, key or tensor byte is a
CheckpointError on load; a file that must carry the digest and does not is refused too.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import shutil
import struct
import tempfile
from pathlib import Path

import torch

__all__ = [
    "CheckpointError",
    "atomic_write_bytes",
    "atomic_write_text",
    "staged_folder",
    "DIGEST_KEY",
    "content_digest",
    "check_replaceable",
    "save_versioned",
    "load_versioned",
    "check_compatible",
]


class CheckpointError(ValueError):
    """A checkpoint of another kind or format version, corrupted, or fitted under another config.

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     _ = save_versioned(Path(tmp) / "old.pt", "demo", 1, {})
        ...     try:
        ...         load_versioned(Path(tmp) / "old.pt", kind="demo", version=2, what="demo")
        ...     except CheckpointError as err:
        ...         reason = str(err).split(" has ")[-1]
        >>> reason, issubclass(CheckpointError, ValueError)
        ('format version 1, this library reads 2', True)
    """


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write to a temporary file beside ``path``, fsync, then ``os.replace``: all or nothing.

    Only a regular file (or nothing) at ``path`` is replaced: a directory, a device such as
    /dev/null, a FIFO or a socket there raises OSError naming it and is left as it was.

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     atomic_write_bytes(Path(tmp) / "new" / "a.bin", b"abc")  # the folder is created
        ...     written, left = (Path(tmp) / "new" / "a.bin").read_bytes(), os.listdir(Path(tmp) / "new")
        >>> written, left  # no temporary file left beside it
        (b'abc', ['a.bin'])
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
    """:func:`atomic_write_bytes` of UTF-8 text.

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     atomic_write_text(Path(tmp) / "note.txt", "first")
        ...     atomic_write_text(Path(tmp) / "note.txt", "Delta = 3 px")  # replaced whole
        ...     text = (Path(tmp) / "note.txt").read_text(encoding="utf-8")
        >>> text
        'Delta = 3 px'
    """
    atomic_write_bytes(path, text.encode())


#: The entry of a versioned file that holds its content digest.
DIGEST_KEY = "content_sha256"


@contextlib.contextmanager
def staged_folder(out: str | Path):
    """Files written into a staging folder beside ``out`` land in ``out`` only when the block ends without error.

    Yields the staging folder (a hidden one beside ``out``, on its file system); at the end of
    the block each file under it moves into ``out`` (its subfolders too) by ``os.replace``, and
    the staging folder is removed. Where the block raises, nothing reaches ``out`` and the
    staging folder is removed: a run that fails half way leaves ``out`` as it was.

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     out = Path(tmp) / "out"
        ...     try:
        ...         with staged_folder(out) as stage:
        ...             _ = (stage / "a.txt").write_text("a")
        ...             raise ValueError("frame 2 is broken")
        ...     except ValueError:
        ...         pass
        ...     failed = out.exists(), os.listdir(tmp)
        ...     with staged_folder(out) as stage:
        ...         (stage / "sub").mkdir()
        ...         _ = (stage / "sub" / "b.txt").write_text("b")
        ...     done = sorted(str(q.relative_to(out)) for q in out.rglob("*")), os.listdir(tmp)
        >>> failed, done
        ((False, []), (['sub', 'sub/b.txt'], ['out']))
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staged-", dir=out.parent))
    try:
        yield stage
        for f in sorted(stage.rglob("*")):
            if f.is_file():
                target = out / f.relative_to(stage)
                target.parent.mkdir(parents=True, exist_ok=True)
                os.replace(f, target)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _encode(value, h, storages: dict, error: type[Exception]) -> None:
    """Feed a canonical, typed encoding of ``value`` to the hash ``h``."""

    def tag(t: bytes, body: bytes = b"") -> None:
        h.update(t + struct.pack("<Q", len(body)) + body)

    if value is None:
        tag(b"N")
    elif isinstance(value, bool):
        tag(b"B", b"1" if value else b"0")
    elif isinstance(value, int):
        tag(b"I", str(value).encode())
    elif isinstance(value, float):
        tag(b"F", value.hex().encode())
    elif isinstance(value, complex):
        tag(b"C", f"{value.real.hex()},{value.imag.hex()}".encode())
    elif isinstance(value, str):
        tag(b"S", value.encode("utf-8", "surrogatepass"))
    elif isinstance(value, (bytes, bytearray)):
        tag(b"Y", bytes(value))
    elif isinstance(value, torch.dtype):
        tag(b"D", str(value).encode())
    elif isinstance(value, torch.Tensor):
        if value.layout != torch.strided:
            raise error(f"holds a tensor of layout {value.layout}; only dense tensors are stored")
        storage = value.untyped_storage()
        key = (storage.device.type, storage.data_ptr(), storage.nbytes())
        first = key not in storages
        index = storages.setdefault(key, len(storages))
        head = f"{value.dtype}|{tuple(value.shape)}|{value.stride()}|{value.storage_offset()}|{index}".encode()
        tag(b"T", head)
        if first:  # each storage's bytes once: never more than the file holds
            raw = torch.empty(0, dtype=torch.uint8, device=storage.device).set_(storage).cpu()
            tag(b"M", struct.pack("<Q", storage.nbytes()))
            h.update(raw.numpy())
    elif isinstance(value, dict):
        items = []
        for k, v in value.items():
            kh = hashlib.sha256()
            _encode(k, kh, {}, error)
            items.append((kh.digest(), k, v))
        items.sort(key=lambda item: item[0])
        tag(b"{", struct.pack("<Q", len(items)))
        for kd, _, v in items:
            h.update(kd)
            _encode(v, h, storages, error)
    elif isinstance(value, (list, tuple)):
        tag(b"(" if isinstance(value, tuple) else b"[", struct.pack("<Q", len(value)))
        for v in value:
            _encode(v, h, storages, error)
    else:
        raise error(f"holds a value of type {type(value).__name__}, which has no canonical encoding")


def content_digest(payload: dict, error: type[Exception] = TypeError) -> str:
    """SHA-256 (hex) of a canonical encoding of ``payload`` without its ``content_sha256`` entry.

    Independent of dict order and of the file's bytes (zip layout, pickle protocol): it is the
    digest of the values. ``error`` is raised for a value with no canonical encoding.
    """
    if not isinstance(payload, dict):
        raise error(f"a payload must be a dict, got {type(payload).__name__}")
    h = hashlib.sha256(b"lensdist-content-v1")
    _encode({k: v for k, v in payload.items() if k != DIGEST_KEY}, h, {}, error)
    return h.hexdigest()


def check_replaceable(path: str | Path, kind: str) -> None:
    """FileExistsError unless ``path`` is free or holds a versioned file of ``kind`` (any version).

    What a checkpoint may overwrite: an earlier checkpoint of its kind, never an image, a data
    set's shard or any other file.
    """
    path = Path(path)
    if not path.is_file():
        return
    try:
        old = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # not a torch file, truncated, foreign objects
        old = None
    if not (isinstance(old, dict) and old.get("kind") == kind):
        raise FileExistsError(
            f"refusing to overwrite {path}: it is not a {kind} checkpoint (delete it first or choose another path)"
        )


def save_versioned(
    path: str | Path,
    kind: str,
    version: int,
    payload: dict,
    *,
    digest: bool = True,
    replace_same_kind_only: bool = False,
) -> str:
    """``torch.save`` of {kind, format_version, **payload}, atomically; returns the sha256 (hex) of the bytes.

    With ``digest`` (the default), the payload's :func:`content_digest` is stored in it as
    ``content_sha256``. With ``replace_same_kind_only``, an existing file is replaced only if
    it is a file of ``kind`` (:func:`check_replaceable`). The bytes never depend on the file
    name (torch.save into memory first).

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     sha = save_versioned(Path(tmp) / "m.pt", "demo", 1, {"w": torch.arange(3)})
        ...     same = sha == hashlib.sha256((Path(tmp) / "m.pt").read_bytes()).hexdigest()
        >>> len(sha), same
        (64, True)
    """
    if replace_same_kind_only:
        check_replaceable(path, kind)
    full = {"kind": kind, "format_version": version, **payload}
    if digest:
        full[DIGEST_KEY] = content_digest(full)
    buf = io.BytesIO()
    torch.save(full, buf)
    data = buf.getvalue()
    atomic_write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def load_versioned(
    path: str | Path, *, kind: str, version: int, what: str, map_location="cpu",
    sha256: str | None = None, error: type[Exception] = CheckpointError, noun: str = "checkpoint",
    digest: bool = False,
) -> dict:
    """Load with ``torch.load(weights_only=True)`` and check the kind, format version and content digest.

    With ``sha256``, the file's bytes must have that digest (checked before they are unpickled).
    A stored ``content_sha256`` is always verified (and removed from the returned dict); with
    ``digest`` the file must carry one. ``error`` is the exception raised and ``noun`` names
    the file in its one-line message.

    Raises:
        FileNotFoundError: no such file.
        CheckpointError (or ``error``): corrupted, another kind, or another format version
            (the message says which).

    Example:
        >>> with tempfile.TemporaryDirectory() as tmp:
        ...     sha = save_versioned(Path(tmp) / "m.pt", "demo", 1, {"w": torch.arange(3)})
        ...     payload = load_versioned(Path(tmp) / "m.pt", kind="demo", version=1, what="demo", sha256=sha,
        ...                              digest=True)
        >>> sorted(payload), payload["w"].tolist()  # the digest checked and removed
        (['format_version', 'kind', 'w'], [0, 1, 2])
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
    stored = payload.pop(DIGEST_KEY, None)
    if stored is None and digest:
        raise error(f"{noun} {path} carries no content digest ({DIGEST_KEY}): damaged or edited")
    if stored is not None:
        try:
            actual = content_digest(payload, error)
        except error as exc:
            raise error(f"{noun} {path} {exc}") from None
        except RecursionError:
            raise error(f"{noun} {path} is nested too deeply to be a lensdist file") from None
        if not isinstance(stored, str) or stored != actual:
            raise error(
                f"{noun} {path} is corrupted or edited: "
                "its content does not match the digest recorded when it was written"
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
