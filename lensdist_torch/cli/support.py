"""The parser class, the argument types and the stdout guard of the ``lensdist`` command line.

Only the standard library at import (``lensdist --help`` stays fast); torch is imported only to
check a CUDA device that was asked for.

Contracts:

- A usage error (an unknown option, a value its type refuses) is one line
  ``lensdist CMD: error: argument --OPT: ...`` on stderr and exit status 2. A mistyped option or
  command gets the nearest one (difflib): ``unrecognized arguments: --jsn (did you mean
  --json?)``, under the subcommand's name (argparse's own ``suggest_on_error`` comes with Python
  3.14 only).
- A negative number in any notation (``-3``, ``-.5``, ``-1e-3``, ``-1.5E-9``) is an option's
  value, not an option: ``--k2 -1e-3`` works as ``--k2=-1e-3`` does.
- Numbers are finite ('nan' and 'inf', which Python's ``float`` accepts, are refused) and in the
  range the option states.
- An error of the library names its Python parameters in backticks (`` `out_dir` ``,
  `` `overwrite=True` ``); the command line prints their flags instead (:func:`as_flags`).
- The result cannot be written to stdout (closed, EBADF, disk full): one line on stderr, exit
  2. A broken pipe (``lensdist ... | head``) ends quietly with exit 1 (Python's convention).
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import re
import sys

__all__ = [
    "no_bars",
    "existing",
    "CONFIG_HELP",
    "DEVICE_HELP",
    "Formatter",
    "Parser",
    "debug_parent",
    "StdoutError",
    "as_flags",
    "device",
    "finite_float",
    "float_in",
    "fmt",
    "guarded_stdout",
    "note",
    "positive_float",
    "positive_int",
    "print_json",
    "shard",
    "silence_stdout",
]

#: The help of every command's ``--config`` and ``--device``.
CONFIG_HELP = "TOML config (the defaults of docs/method.md when omitted)"
DEVICE_HELP = "where the tensors go: cpu, cuda or cuda:N (N below the number of CUDA devices)"

#: A negative number as a value: argparse's own pattern (``^-\d+$|^-\d*\.\d+$``) misses
#: exponents; 'inf' and 'nan' are matched so that their type refuses them by name.
_NEGATIVE_NUMBER = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE)


#: Python parameters whose flag is not ``--`` and the name with dashes (a value: the flag alone).
FLAGS = {"out_dir": "--out", "from_json": "--from", "overwrite=True": "--overwrite"}
#: a Python parameter named in an error, in backticks, with an optional ``=value``
_PARAMETER = re.compile(r"`([A-Za-z_][A-Za-z0-9_]*)(=[^`\s]+)?`")


def as_flags(message: str) -> str:
    """``message`` with each Python parameter in backticks written as its command-line flag.

    ``name`` becomes ``--name`` (underscores as dashes), ``name=value`` ``--name value``; the
    exceptions are in :data:`FLAGS`. Text in backticks that is not one identifier stays as it is.

    Example:
        >>> as_flags("choose an empty `out_dir` or pass `overwrite=True`; `checkpoint_max` or `alpha=0.5`")
        'choose an empty --out or pass --overwrite; --checkpoint-max or --alpha 0.5'
        >>> as_flags("run `lensdist generate --out DIR` first")
        'run `lensdist generate --out DIR` first'
    """

    def flag(match: re.Match) -> str:
        name, value = match.group(1), match.group(2) or ""
        if name + value in FLAGS:
            return FLAGS[name + value]
        dashed = FLAGS.get(name, "--" + name.replace("_", "-"))
        return dashed + (" " + value[1:] if value else "")

    return _PARAMETER.sub(flag, message)


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every option's help; the description's and the epilog's lines kept as written.

    An option whose default is None or a flag's False says in its own words what happens when
    it is omitted, so "(default: None)" is not appended to it.
    """

    def _get_help_string(self, action):
        if action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


def debug_parent() -> argparse.ArgumentParser:
    """The ``--debug`` option every subcommand takes (as ``lensdist --debug CMD`` does)."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show the traceback of an error (an internal error prints one line without it)")
    return common


def _nearest(word: str, options: list[str]) -> str | None:
    found = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    return found[0] if found else None


_INVALID_CHOICE = re.compile(r"invalid choice: '?([^' ]*)'? \(choose from (.*)\)$")


class Parser(argparse.ArgumentParser):
    """argparse with negative numbers in scientific notation as values and one-line usage errors.

    Subparsers made by ``add_subparsers`` are of this class too (argparse uses the parent's).
    Mistyped options and choices get a suggestion (module docstring).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse (3.8 to 3.13) decides with this private pattern whether '-1e-3' is an option
        # or a value; tests/workflows/test_cli_hostile.py fails if a Python changes that.
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def _options(self) -> list[str]:
        return [s for a in self._actions for s in a.option_strings if s.startswith("--")]

    def _chosen_subparser(self, namespace) -> Parser | None:
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                return action.choices.get(getattr(namespace, action.dest, None) or "")
        return None

    def parse_args(self, args=None, namespace=None):
        """argparse's, with a suggestion for each unrecognised option, under the subcommand's name."""
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            sub = self._chosen_subparser(namespace)
            options = self._options() + (sub._options() if sub is not None else [])
            words = []
            for extra in extras:
                near = _nearest(extra.split("=", 1)[0], options) if extra.startswith("--") else None
                words.append(f"{extra} (did you mean {near}?)" if near else extra)
            (sub or self).error("unrecognized arguments: " + " ".join(words))
        return namespace

    def error(self, message: str):
        """One line ``PROG: error: MESSAGE`` on stderr, exit status 2 (argparse adds the usage)."""
        text = " ".join(str(message).split())
        m = _INVALID_CHOICE.search(text)
        if m:
            near = _nearest(m.group(1), [c.strip(" '") for c in m.group(2).split(",")])
            text += f"; did you mean {near}?" if near else ""
        self.exit(2, f"{self.prog}: error: {text} (see {self.prog} --help)\n")


# ----------------------------------------------------------------------------- argument types
def existing(path, what: str) -> None:
    """A missing input as the library words it (``WHAT not found: PATH``), before a command imports torch.

    The library checks the same and raises the same error; checked here, a missing file costs a
    user no import time before its one-line error. None (an option not given) passes.

    Example:
        >>> existing(None, "image file")
        >>> existing("/no/such/frame.png", "image file")
        Traceback (most recent call last):
        ...
        FileNotFoundError: image file not found: /no/such/frame.png
    """
    if path is not None and not os.path.exists(path):
        raise FileNotFoundError(f"{what} not found: {path}")


def device(text: str) -> str:
    """``--device``: cpu, cuda or cuda:N with N below the number of CUDA devices here."""
    if text == "cpu":
        return text
    m = re.fullmatch(r"cuda(?::(\d+))?", text)
    if m is None:
        raise argparse.ArgumentTypeError(f"unknown device {text!r}: use cpu, cuda or cuda:N (N a CUDA device index)")
    import torch

    if not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"device {text!r} asked for, but CUDA is not available here; use cpu")
    n = torch.cuda.device_count()
    if m.group(1) is None:
        return "cuda"
    if int(m.group(1)) >= n:
        raise argparse.ArgumentTypeError(
            f"device {text!r} asked for, but this machine has {n} CUDA device(s): cuda:0 to cuda:{n - 1}"
        )
    return f"cuda:{int(m.group(1))}"


def _float(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r} (not a finite number)")
    return value


def finite_float(text: str) -> float:
    """A finite number (negative allowed), in any notation float() reads."""
    return _float(text, "a finite number")


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _float(text, "a positive number")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def float_in(low: float, high: float):
    """A type: a finite number in [low, high]."""
    what = f"a number from {low:g} to {high:g}"

    def in_range(text: str) -> float:
        value = _float(text, what)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return in_range


def positive_int(text: str) -> int:
    """An integer >= 1 (a count or a size)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def shard(text: str) -> tuple[int, int]:
    """``generate --shard I/N``: this job's share, 0 <= I < N."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (e.g. 0/4), got {text!r}") from None
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"I/N needs 0 <= I < N, got {text!r}")
    return (i, n)


# ----------------------------------------------------------------------------- output helpers
def note(args: argparse.Namespace, text: str) -> None:
    """A note for the user on stderr (silenced by --quiet)."""
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr)


def no_bars(args: argparse.Namespace) -> bool:
    """Progress bars off: ``--quiet``, or stderr is no terminal (a log would keep every redraw before an error)."""
    return bool(getattr(args, "quiet", False)) or not sys.stderr.isatty()


def print_json(obj) -> None:
    """One strict JSON object on stdout (``workflows.reports.dumps_strict``)."""
    from lensdist_torch.workflows.reports import dumps_strict

    print(dumps_strict(obj, indent=2))


def fmt(value, spec: str = ".1f", unit: str = " px") -> str:
    """A number, or "n/a" where there is no (finite) estimate."""
    return (
        f"{value:{spec}}{unit}"
        if isinstance(value, (int, float)) and value == value and abs(value) != float("inf")
        else "n/a"
    )


# ----------------------------------------------------------------------------- stdout
class StdoutError(Exception):
    """Writing the result to stdout failed (not a broken pipe): the result is lost."""

    def __init__(self, exc: OSError):
        super().__init__(exc.strerror or str(exc) or type(exc).__name__)


class _Guarded:
    """``sys.stdout`` whose write errors, other than a broken pipe, become :class:`StdoutError`."""

    def __init__(self, stream):
        self._stream = stream

    def _call(self, name: str, *args):
        try:
            return getattr(self._stream, name)(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise StdoutError(exc) from exc

    def write(self, text):
        return self._call("write", text)

    def writelines(self, lines):
        return self._call("writelines", lines)

    def flush(self):
        return self._call("flush")

    def __getattr__(self, name):
        return getattr(self._stream, name)


class guarded_stdout:  # noqa: N801 (used as a context manager)
    """Within: a failed write to stdout raises :class:`StdoutError`.

    stdout is flushed at the end, so that a failure of the last buffered write is seen here and
    not lost at exit.
    """

    def __enter__(self):
        self._saved = sys.stdout
        sys.stdout = _Guarded(self._saved)
        return self

    def __exit__(self, kind, exc, tb):
        try:
            if kind is None:
                sys.stdout.flush()
        finally:
            sys.stdout = self._saved
        return False


def silence_stdout() -> None:
    """Point fd 1 at the null device (after a broken pipe or a failed write).

    The interpreter's last flush at exit then neither fails nor prints "Exception ignored".
    """
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return  # not a real file (captured in tests)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, fd)
    os.close(null)
