"""The one check of a one-line error, shared by the tests (bad input gets one line naming the argument).

Imported by name (``from one_line import one_line``): ``tests/`` is on the path the way pytest
loads its conftest.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest


def one_line(info: pytest.ExceptionInfo, *words: str) -> str:
    """The message of a raised error, checked to be one line holding every one of ``words``."""
    msg = str(info.value)
    assert "\n" not in msg, msg
    for w in words:
        assert w in msg, (w, msg)
    return msg


def one_line_error(exc: type[BaseException], call: Callable[[], object], *words: str) -> str:
    """``call()`` raises ``exc`` with a one-line message holding every one of ``words``; the message."""
    with pytest.raises(exc) as info:
        call()
    return one_line(info, *words)


def one_line_usage(code: int, err: str, command: str) -> str:
    """A command's usage error: status 2 and one line ``lensdist COMMAND: error: ...`` on stderr, no internal error."""
    assert code == 2 and err.startswith(f"lensdist {command}: error: ") and "\n" not in err.rstrip("\n"), (code, err)
    assert "internal error" not in err
    return err
