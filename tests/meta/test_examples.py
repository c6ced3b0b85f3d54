"""Every public name shows a runnable example (issue 21, item 5): a ``>>>`` in its docstring,
which the doctests (``pytest --doctest-modules``, as CI runs them) execute.

Plain constants (tuples, strings, numbers, ...) cannot carry a docstring of their own and are
skipped; ``CLASS_LABELS`` is shown in the example of its module, ``geometry/distortion.py``.
"""

from __future__ import annotations

import inspect
from types import SimpleNamespace

import lensdist_torch

#: Values that carry no docstring of their own (``inspect.getdoc`` would give their type's).
CONSTANT_TYPES = (tuple, list, dict, set, frozenset, str, bytes, int, float, complex, type(None))

#: Public names whose example waits on a module that this change did not edit: name -> why. An
#: entry must still lack its example (the last test), so it is removed once the example is there.
PENDING: dict[str, str] = {}  # name -> why it has no example yet (each entry must still lack one)


def missing_examples(names, namespace) -> list[str]:
    """The names of ``namespace`` whose docstring (``inspect.getdoc``) shows no ``>>>``, constants skipped."""
    out = []
    for name in names:
        obj = getattr(namespace, name)
        if isinstance(obj, CONSTANT_TYPES):
            continue
        if ">>>" not in (inspect.getdoc(obj) or ""):
            out.append(name)
    return sorted(out)


def test_every_public_name_has_an_example():
    missing = [n for n in missing_examples(lensdist_torch.__all__, lensdist_torch) if n not in PENDING]
    assert not missing, f"{len(missing)} public name(s) without a runnable example (>>> in the docstring): {missing}"


def test_the_rule_flags_a_name_without_an_example():
    def bare():
        """Documented, but no example."""

    def shown():
        """Documented, with an example.

        Example:
            >>> 1 + 1
            2
        """

    ns = SimpleNamespace(bare=bare, shown=shown, undocumented=lambda: None, LABELS=("a", "b"), LIMIT=450)
    assert missing_examples(["bare", "shown", "undocumented", "LABELS", "LIMIT"], ns) == ["bare", "undocumented"]


def test_pending_names_still_lack_their_example():
    assert set(PENDING) <= set(lensdist_torch.__all__)
    stale = [n for n in PENDING if n not in missing_examples([n], lensdist_torch)]
    assert not stale, f"these names have an example now: remove them from PENDING: {stale}"
