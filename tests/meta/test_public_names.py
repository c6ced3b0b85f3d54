"""Every name the README shows imports from ``lensdist_torch`` (issue 22), and the public API
has one list: ``_EXPORTS`` in ``lensdist_torch/__init__.py``, from which ``__all__``, the lazy
loading and the type checkers' stub ``__init__.pyi`` are built.

After editing ``_EXPORTS``: ``python tests/meta/test_public_names.py --write`` rewrites the stub.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
STUB = ROOT / "lensdist_torch" / "__init__.pyi"

#: Identifiers of the README that are not Python names of the package although a module exports
#: one so called: a command (`lensdist evaluate`), a JSON field, a constant shown with its module.
NOT_PYTHON_NAMES = {"evaluate", "distortion_type", "MAX_STRETCH"}


def _exports() -> dict[str, tuple[str, ...]]:
    import lensdist_torch

    return lensdist_torch._EXPORTS


def stub_text() -> str:
    """The stub for type checkers and IDEs, generated from ``_EXPORTS``."""
    lines = [
        "# Generated from _EXPORTS in __init__.py by `python tests/meta/test_public_names.py --write`:",
        "# do not edit. Type checkers and IDEs read this file; the package loads each name on first use.",
        "",
    ]
    for module, names in sorted(_exports().items()):
        lines += [f"from {module} import {name} as {name}" for name in sorted(names)]
    names = sorted(n for ns in _exports().values() for n in ns)
    lines += ["", "__version__: str", "__all__ = ["] + [f'    "{n}",' for n in names] + ["]", ""]
    return "\n".join(lines)


def _readme_imports() -> set[str]:
    """Names of every ``from lensdist_torch import ...`` in the README (one line or parenthesised)."""
    found = set()
    for wrapped, line in re.findall(r"from lensdist_torch import (?:\(([^)]*)\)|([^\n]*))", README):
        found |= {n.strip() for n in (wrapped or line).split("#")[0].split(",") if n.strip()}
    return found


def _readme_sub_imports() -> dict[str, set[str]]:
    """``from lensdist_torch.<subpackage> import ...`` in the README: subpackage -> names."""
    found: dict[str, set[str]] = {}
    for sub, wrapped, line in re.findall(r"from lensdist_torch\.([\w.]+) import (?:\(([^)]*)\)|([^\n]*))", README):
        found.setdefault(sub, set()).update(n.strip() for n in (wrapped or line).split("#")[0].split(",") if n.strip())
    return found


def _readme_attributes() -> set[str]:
    """Dotted paths used as ``lensdist_torch.X`` anywhere in the README."""
    return {m.rstrip(".") for m in re.findall(r"lensdist_torch\.([A-Za-z_][\w.]*)", README)}


def _module_all(path: Path) -> list[str]:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            try:
                return list(ast.literal_eval(node.value))
            except ValueError:
                return []
    return []


def _package_public_names() -> set[str]:
    """Names in the ``__all__`` of any module of the package (read, not imported)."""
    names: set[str] = set()
    for path in (ROOT / "lensdist_torch").rglob("*.py"):
        if not path.name.startswith("cli"):
            names |= set(_module_all(path))
    return names


def _readme_code_names() -> set[str]:
    """Backticked identifiers of the README (``name`` or ``name(...)``) that the package exports."""
    ticked = set(re.findall(r"`([A-Za-z_]\w*)(?:\(|`)", README))
    code = "\n".join(re.findall(r"```python\n(.*?)```", README, flags=re.S))
    code = re.sub(r"#[^\n]*", "", code)  # comments are prose
    in_code = set(re.findall(r"\b([A-Za-z_]\w*)\b", code))
    from_subpackages = set().union(*_readme_sub_imports().values())
    return ((ticked | in_code) & _package_public_names()) - NOT_PYTHON_NAMES - from_subpackages


def test_the_readme_shows_the_names_the_issue_names():
    shown = _readme_code_names() | _readme_imports()
    for name in ("calibrate_sequence", "undistort_image", "Undistort", "analyze_batch", "RegistrationQualityMetric"):
        assert name in shown


@pytest.mark.parametrize("name", sorted(_readme_imports() | _readme_code_names()))
def test_every_readme_name_imports_from_the_top_level(name):
    namespace: dict = {}
    exec(f"from lensdist_torch import {name}", namespace)
    assert namespace[name] is not None
    import lensdist_torch

    assert name in lensdist_torch.__all__ and name in dir(lensdist_torch)


@pytest.mark.parametrize("sub, name", sorted((s, n) for s, names in _readme_sub_imports().items() for n in names))
def test_every_readme_subpackage_import_works(sub, name):
    module = importlib.import_module(f"lensdist_torch.{sub}")
    assert name in module.__all__ and getattr(module, name) is not None


@pytest.mark.parametrize("path", sorted(_readme_attributes()))
def test_every_readme_dotted_path_resolves(path):
    parts = path.split(".")
    for i in range(len(parts), 0, -1):  # the longest module prefix, then attributes
        try:
            obj = importlib.import_module(".".join(["lensdist_torch", *parts[:i]]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return
    import lensdist_torch

    assert getattr(lensdist_torch, path) is not None


def test_all_is_built_from_the_one_table():
    import lensdist_torch

    table = {n for names in _exports().values() for n in names}
    assert set(lensdist_torch.__all__) == table
    assert len(table) == sum(len(names) for names in _exports().values())  # no name twice
    for module, names in _exports().items():
        path = ROOT / module.replace(".", "/")
        exported = _module_all(path / "__init__.py" if path.is_dir() else path.with_suffix(".py"))
        assert set(names) <= set(exported), module


def test_the_stub_is_generated_from_the_table():
    assert STUB.read_text() == stub_text(), "run: python tests/meta/test_public_names.py --write"


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    STUB.write_text(stub_text())
    print(f"wrote {STUB.relative_to(ROOT)}")
