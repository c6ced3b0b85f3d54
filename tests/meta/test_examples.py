"""Every public name shows a runnable example (issue 21, item 5): a ``>>>`` in its docstring,
which the doctests (``pytest --doctest-modules``, as CI runs them) execute.

Public names are those of ``lensdist_torch.__all__`` and of its subpackages' ``__all__`` (core,
classify, data, geometry, registration, selfcal, calibration, workflows: :data:`PACKAGES`). Each
example must also be one that the doctests run: in the object's own docstring, found by
:mod:`doctest` in the module that defines it (an inherited docstring, or a ``>>>`` that does not
start a line, would pass the first check only).

Plain constants (tuples, strings, numbers, ...) cannot carry a docstring of their own and are
skipped; ``CLASS_LABELS`` is shown in the example of its module, ``geometry/distortion.py``.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import sys
import textwrap
import types
from types import SimpleNamespace

import pytest

#: The packages whose ``__all__`` is checked: the top level and the subpackages that export names.
PACKAGES = (
    "lensdist_torch",
    "lensdist_torch.core",
    "lensdist_torch.classify",
    "lensdist_torch.data",
    "lensdist_torch.geometry",
    "lensdist_torch.registration",
    "lensdist_torch.selfcal",
    "lensdist_torch.calibration",
    "lensdist_torch.workflows",
)

#: Values that carry no docstring of their own (``inspect.getdoc`` would give their type's).
CONSTANT_TYPES = (tuple, list, dict, set, frozenset, str, bytes, int, float, complex, type(None))

#: Public names (``package.name``) whose example waits on a module that another change is editing.
#: An entry must still lack its example (the last test), so it is removed once the example is there.
PENDING_EXAMPLES: set[str] = set()  # every subpackage name has its example (issue 21)


def public_objects(names, namespace):
    """(name, object) of ``names`` in ``namespace``, constants skipped."""
    objs = ((name, getattr(namespace, name)) for name in names)
    return [(name, obj) for name, obj in objs if not isinstance(obj, CONSTANT_TYPES)]


def missing_examples(names, namespace) -> list[str]:
    """The names of ``namespace`` whose docstring (``inspect.getdoc``) shows no ``>>>``, constants skipped."""
    return sorted(name for name, obj in public_objects(names, namespace) if ">>>" not in (inspect.getdoc(obj) or ""))


def examples_found_in(module: types.ModuleType) -> set[str]:
    """The dotted names of the docstrings in ``module`` with an example that its doctests run."""
    return {test.name for test in doctest.DocTestFinder().find(module) if test.examples}


def examples_not_run(names, namespace) -> list[str]:
    """The names of ``namespace`` that show a ``>>>`` but whose defining module's doctests run no example of theirs."""
    found: dict[str, set[str]] = {}
    out = []
    for name, obj in public_objects(names, namespace):
        if ">>>" not in (inspect.getdoc(obj) or ""):
            continue  # missing_examples' business
        home = sys.modules.get(getattr(obj, "__module__", None) or "")
        if home is None:
            out.append(name)
            continue
        if home.__name__ not in found:
            found[home.__name__] = examples_found_in(home)
        if f"{home.__name__}.{obj.__name__}" not in found[home.__name__]:
            out.append(name)
    return sorted(out)


def exported(package: str) -> tuple[types.ModuleType, list[str]]:
    """The package and its ``__all__``."""
    pkg = importlib.import_module(package)
    return pkg, list(pkg.__all__)


def pending_in(package: str) -> set[str]:
    """The names of ``package`` in :data:`PENDING_EXAMPLES`."""
    return {entry.rpartition(".")[2] for entry in PENDING_EXAMPLES if entry.rpartition(".")[0] == package}


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_has_an_example(package):
    pkg, names = exported(package)
    missing = [n for n in missing_examples(names, pkg) if n not in pending_in(package)]
    assert not missing, (
        f"{len(missing)} public name(s) of {package} without a runnable example (>>> in the docstring): {missing}"
    )


@pytest.mark.parametrize("package", PACKAGES)
def test_every_example_is_run_by_the_doctests(package):
    pkg, names = exported(package)
    not_run = examples_not_run(names, pkg)
    assert not not_run, (
        f"public name(s) of {package} whose >>> the doctests of the defining module do not run "
        f"(not in its own docstring, or not at the start of a line): {not_run}"
    )


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


def test_the_rule_flags_an_example_the_doctests_would_not_run(monkeypatch):
    mod = types.ModuleType("examples_demo")
    monkeypatch.setitem(sys.modules, mod.__name__, mod)
    source = '''
        class Base:
            """A base.

            Example:
                >>> Base.__name__
                'Base'
            """

        class Heir(Base):
            pass

        def inline():
            """Mentions ``>>> inline()`` in a sentence: no example."""

        def shown():
            """Documented, with an example.

            Example:
                >>> shown.__name__
                'shown'
            """
    '''
    exec(textwrap.dedent(source), mod.__dict__)
    # Heir shows Base's example (inspect.getdoc inherits it), which the doctests run for Base only
    assert examples_not_run(["Base", "Heir", "inline", "shown"], mod) == ["Heir", "inline"]


def test_pending_names_still_lack_their_example():
    stale = []
    for entry in sorted(PENDING_EXAMPLES):
        package, _, name = entry.rpartition(".")
        assert package in PACKAGES, f"{entry}: not a name of the packages checked, {PACKAGES}"
        pkg, names = exported(package)
        assert name in names, f"{entry}: not in {package}.__all__"
        if not missing_examples([name], pkg):
            stale.append(entry)
    assert not stale, f"these names have an example now: remove them from PENDING_EXAMPLES: {stale}"
