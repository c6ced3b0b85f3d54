"""TOML files and ``--set`` overrides: read, merge, override, check the keys.

The one reader of configuration files: :func:`~lensdist_torch.config.load_config` builds the
package's :class:`~lensdist_torch.config.LensdistConfig` with it, and the training scripts
(``train/``) build their tables with it (defaults <- a TOML file <- ``--set key=value``). Every
error is a one-line ``ValueError`` (``FileNotFoundError`` for a missing file) naming the file,
the section or the key.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import tomllib  # Python >= 3.11 (pyproject.toml says why)

from lensdist_torch.config.checks import one_line, show

__all__ = ["apply_overrides", "check_tables", "layered_tables", "merge_tables", "parse_overrides", "read_toml"]


def read_toml(path: str | Path) -> dict[str, Any]:
    """A TOML file's tables (a UTF-8 byte-order mark is skipped, as Python's utf-8-sig does).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: not a file, not UTF-8, not valid TOML, or unreadable; the message names the file.

    Example:
        >>> import tempfile, pathlib
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "run.toml"
        >>> _ = path.write_text("[train]" + chr(10) + "steps = 20" + chr(10))
        >>> read_toml(path)
        {'train': {'steps': 20}}
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"config file not found: {path}")
    if not path.is_file():
        raise ValueError(f"config path {path} is not a file")
    try:
        raw = path.read_bytes()
        if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
            raise ValueError(f"config file {path} starts with a UTF-16 byte-order mark: save it as UTF-8")
        return tomllib.loads(raw.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"config file {path} is not valid TOML: {one_line(exc)}") from exc
    except UnicodeDecodeError as exc:
        raise ValueError(f"config file {path} is not UTF-8 text: {one_line(exc)}") from exc
    except OSError as exc:
        raise ValueError(f"cannot read config file {path}: {exc.strerror or one_line(exc)}") from exc


def check_tables(data: Any, keys: dict[str, Any]) -> None:
    """Refuse what ``keys`` (section -> its allowed keys) does not name: a typo must not fall back to a default.

    Raises:
        TypeError: ``data`` is not a dict.
        ValueError: a key outside any section, an unknown section, a section that is not a
            table, or an unknown key in a section.

    Example:
        >>> check_tables({"train": {"stpes": 3}}, {"train": {"steps"}})
        Traceback (most recent call last):
        ...
        ValueError: unknown key(s) ['stpes'] in config section [train]
    """
    if not isinstance(data, dict):
        raise TypeError(f"config data must be a dict, got {type(data).__name__}")
    for name, values in data.items():
        if name not in keys and not isinstance(values, dict):
            raise ValueError(f"config key {name!r} is outside any section; the sections are {list(keys)}")
    unknown = sorted(set(data) - set(keys))
    if unknown:
        raise ValueError(f"unknown config section(s) {unknown}; expected {sorted(keys)}")
    for name, values in data.items():
        if not isinstance(values, dict):
            raise ValueError(f"config section [{name}] must be a table of key = value pairs, got {show(values)}")
        bad = set(values) - set(keys[name])
        if bad:
            raise ValueError(f"unknown key(s) {sorted(bad)} in config section [{name}]")


def merge_tables(base: dict, over: dict) -> dict:
    """A copy of ``base`` with ``over`` merged in, table by table (``over`` wins).

    Example:
        >>> merge_tables({"train": {"steps": 800, "lr": 0.002}}, {"train": {"steps": 20}})
        {'train': {'steps': 20, 'lr': 0.002}}
    """
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_tables(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _parse_value(text: str) -> Any:
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` items as dotted keys and TOML values (a bare word stays a string).

    Raises:
        ValueError: an item without ``=`` or without a key.

    Example:
        >>> parse_overrides(["train.steps=20", "data.scenes=['gravel']", "model.kind=stacked"])
        {'train.steps': 20, 'data.scenes': ['gravel'], 'model.kind': 'stacked'}
    """
    overrides = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        overrides[key.strip()] = _parse_value(value.strip())
    return overrides


def apply_overrides(data: dict, overrides: dict[str, Any] | None) -> dict:
    """A copy of ``data`` with each dotted key (``"train.steps"``) set to its value.

    Example:
        >>> apply_overrides({"train": {"steps": 800}}, {"train.steps": 20, "arms.l1.lambda_quality": 0.5})
        {'train': {'steps': 20}, 'arms': {'l1': {'lambda_quality': 0.5}}}
    """
    out = copy.deepcopy(data)
    _set_dotted(out, overrides)
    return out


def layered_tables(defaults: dict, path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                   replaced: tuple[str, ...] = ()) -> dict:
    """``defaults`` <- the TOML file at ``path`` <- ``overrides`` (dotted keys), as one new dict.

    The file's tables merge into the defaults' key by key, except those named in ``replaced``,
    which replace the default table whole where the file has one. Keys are not checked here
    (:func:`check_tables`).

    Example:
        >>> layered_tables({"train": {"steps": 800, "lr": 0.002}, "arms": {"l1": {}}}, None, {"train.steps": 20})
        {'train': {'steps': 20, 'lr': 0.002}, 'arms': {'l1': {}}}
    """
    data = read_toml(path) if path is not None else {}
    base = {k: ({} if k in replaced and k in data else v) for k, v in defaults.items()}
    out = merge_tables(base, data)  # a deep copy: the defaults stay as they are
    _set_dotted(out, overrides)
    return out


def _set_dotted(out: dict, overrides: dict[str, Any] | None) -> None:
    for dotted, value in (overrides or {}).items():
        node = out
        *parents, leaf = dotted.split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {dotted}: {p} is a value, not a table")
        node[leaf] = value
