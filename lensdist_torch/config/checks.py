"""The field checks of the config dataclasses (the modules of ``lensdist_torch.config``).

Each check takes the dataclass being built (in its ``__post_init__``) and a field name, raises a
one-line ``ValueError`` naming ``section.field`` (the section is the class name without
``Config``, lower case: ``ProtocolConfig`` -> ``protocol``), and stores the value's canonical
form with ``object.__setattr__``:

* integer fields take ints only: not floats (``8.0``), not bools;
* number fields take ints or floats, not bools, and store a float; NaN and Inf are refused;
* sequence fields take tuples or lists, never a string (it would iterate as characters), and
  store a tuple.
"""

from __future__ import annotations

import math
import numbers
from typing import Any

__all__ = [
    "or_defaults",
    "one_line",
    "show",
    "real",
    "positive",
    "integer",
    "flag",
    "choice",
    "pair",
    "integers",
    "names",
]


def or_defaults(value: Any, cls: type, name: str = "config") -> Any:
    """``value``, or ``cls()`` (the defaults of docs/method.md) where it is None; anything else a TypeError.

    Example:
        >>> from lensdist_torch.config import SelfCalConfig
        >>> or_defaults(None, SelfCalConfig) == SelfCalConfig()
        True
        >>> or_defaults({"levels": 3}, SelfCalConfig)
        Traceback (most recent call last):
        ...
        TypeError: config must be a SelfCalConfig or None, got dict
    """
    if value is None:
        return cls()
    if not isinstance(value, cls):
        raise TypeError(f"{name} must be a {cls.__name__} or None, got {type(value).__name__}")
    return value


def one_line(exc: BaseException, limit: int | None = None) -> str:
    """An exception's message on one line (its type's name when it has none), cut at ``limit`` characters.

    Example:
        >>> one_line(ValueError("bad" + chr(10) + "  value"))
        'bad value'
        >>> one_line(OSError(), 10), one_line(ValueError("x" * 20), 10)
        ('OSError', 'xxxxxxx...')
    """
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if limit is None or len(text) <= limit else text[: limit - 3] + "..."


def show(value: Any) -> str:
    """The value for an error message: its repr (shortened), and its type when that is not a number."""
    text = repr(value)
    if len(text) > 80:
        text = text[:77] + "..."
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        text += f" ({type(value).__name__})"
    return text


def _fail(obj: Any, name: str, what: str, value: Any) -> None:
    section = type(obj).__name__.removesuffix("Config").lower()
    raise ValueError(f"{section}.{name} must be {what}, got {show(value)}")


def _is_real(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _interval(lo, hi, lo_open, hi_open, hi_name=None) -> str:
    hi_text = hi_name if hi_name is not None else f"{hi:g}" if hi is not None else None
    if lo is not None and hi is not None:
        return f"a number in {']' if lo_open else '['}{lo:g}, {hi_text}{'[' if hi_open else ']'}"
    if lo is not None:
        return f"a finite number {'>' if lo_open else '>='} {lo:g}"
    if hi is not None:
        return f"a finite number {'<' if hi_open else '<='} {hi_text}"
    return "a finite number"


def real(obj, name, *, lo=None, hi=None, lo_open=False, hi_open=False, hi_name=None, why=None) -> None:
    """A finite number in the interval given by ``lo``/``hi`` (open ends with ``*_open``)."""
    value = getattr(obj, name)
    what = _interval(lo, hi, lo_open, hi_open, hi_name) + (f" ({why})" if why else "")
    if not _is_real(value):
        _fail(obj, name, what, value)
    x = float(value)
    if not math.isfinite(x) or (lo is not None and (x <= lo if lo_open else x < lo)) or (
        hi is not None and (x >= hi if hi_open else x > hi)
    ):
        _fail(obj, name, what, value)
    object.__setattr__(obj, name, x)


def positive(name: str, value: Any) -> None:
    """A positive finite number, for a plain argument (not a field)."""
    if not _is_real(value) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {show(value)}")


def integer(obj, name, *, lo: int | None = 1, hi: int | None = None, why: str | None = None) -> None:
    """An int >= ``lo`` (positive by default; ``lo=None``: any int), and <= ``hi`` if given."""
    value = getattr(obj, name)
    what = "an int" if lo is None else "a positive int" if lo == 1 else f"an int >= {lo}"
    if hi is not None:
        what += f" <= {hi}" + (f" ({why})" if why else "")
    if not _is_int(value) or (lo is not None and value < lo) or (hi is not None and value > hi):
        _fail(obj, name, what, value)
    object.__setattr__(obj, name, int(value))


def flag(obj, name) -> None:
    """A bool (TOML ``true`` or ``false``; not 0 or 1)."""
    value = getattr(obj, name)
    if not isinstance(value, bool):
        _fail(obj, name, "true or false", value)


def choice(obj, name, options: tuple[str, ...]) -> None:
    """One of the strings ``options``."""
    value = getattr(obj, name)
    if not isinstance(value, str) or value not in options:
        _fail(obj, name, " or ".join(repr(o) for o in options), value)


def _sequence(obj, name, what: str) -> tuple:
    value = getattr(obj, name)
    if not isinstance(value, (tuple, list)):  # a string is not a list of its characters
        _fail(obj, name, what, value)
    return tuple(value)


def pair(
    obj, name, *, positive: bool = False, within: tuple[float, float] | None = None, integral: bool = False
) -> None:
    """(low, high): two finite (or positive) numbers with low <= high.

    ``within`` = (a, b) also asks a <= low and high <= b; ``integral`` asks for ints (stored as
    ints, floats otherwise).
    """
    kind = "ints" if integral else "numbers"
    if within is not None:
        where = f"two {kind} in {']' if positive else '['}{within[0]:g}, {within[1]:g}]"
    else:
        where = f"two {'positive' if positive else 'finite'} {kind}"
    what = f"(low, high): {where} with low <= high"
    value = _sequence(obj, name, what)
    ok = _is_int if integral else _is_real
    if len(value) != 2 or not all(ok(v) and math.isfinite(v) and (v > 0 or not positive) for v in value):
        _fail(obj, name, what, getattr(obj, name))
    lo, hi = (int(v) if integral else float(v) for v in value)
    if not lo <= hi or (within is not None and not within[0] <= lo <= hi <= within[1]):
        _fail(obj, name, what, getattr(obj, name))
    object.__setattr__(obj, name, (lo, hi))


def integers(obj, name, *, lo: int = 1, n: int | None = None, per: str = "") -> None:
    """A non-empty tuple of ints >= ``lo``; of length ``n`` (one per ``per``) if given."""
    kind = "positive ints" if lo == 1 else f"ints >= {lo}"
    what = f"a tuple of {n} {kind} (one per {per})" if n is not None else f"a non-empty tuple of {kind}"
    value = _sequence(obj, name, what)
    if (n is not None and len(value) != n) or not value or not all(_is_int(v) and v >= lo for v in value):
        _fail(obj, name, what, getattr(obj, name))
    object.__setattr__(obj, name, tuple(int(v) for v in value))


def names(obj, name, empty: bool = False) -> None:
    """A tuple of distinct non-empty strings, non-empty unless ``empty``."""
    what = ("a" if empty else "a non-empty") + " list of distinct non-empty strings"
    value = _sequence(obj, name, what)
    if (
        (not value and not empty)
        or not all(isinstance(v, str) and v.strip() for v in value)
        or len(set(value)) != len(value)
    ):
        _fail(obj, name, what, getattr(obj, name))
    object.__setattr__(obj, name, value)
