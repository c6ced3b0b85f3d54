"""Every name the README shows imports from ``lensdist_torch`` (issue 22), and the public API
has one list: ``_EXPORTS`` in ``lensdist_torch/__init__.py``, from which ``__all__``, the lazy
loading and the type checkers' stub ``__init__.pyi`` are built. Each subpackage exports its
public names from its own ``_EXPORTS`` table the same way (issue 21, item 1).

After editing ``_EXPORTS``: ``python tests/meta/test_public_names.py --write`` rewrites the stub.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
STUB = ROOT / "lensdist_torch" / "__init__.pyi"

#: Identifiers of the README that are not Python names of the package although a module exports
#: one so called: a command (`lensdist evaluate`), a JSON field, a constant shown with its module.
NOT_PYTHON_NAMES = {"evaluate", "distortion_type", "relief_agreement", "MAX_STRETCH"}


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


def _bound(node: ast.stmt) -> set[str]:
    """The names a top-level statement defines (a def, a class, an assignment; an import defines none here)."""
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return {node.name}
    targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
    return {t.id for t in targets if isinstance(t, ast.Name)}


def _module_all(path: Path) -> list[str]:
    """A module's ``__all__``, read, not imported: its literal, or the names of its ``_EXPORTS``
    table where ``__all__`` is built from one (``lazy_exports``, the subpackages)."""
    table = None
    for node in ast.parse(path.read_text()).body:
        ids = _bound(node) if getattr(node, "value", None) is not None else set()
        if "__all__" in ids:
            try:
                return list(ast.literal_eval(node.value))
            except ValueError:
                pass
        if "_EXPORTS" in ids:
            table = ast.literal_eval(node.value)
    return sorted(n for names in table.values() for n in names) if table else []


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


SUBPACKAGES = ("core", "classify", "data", "geometry", "registration", "selfcal", "calibration", "workflows")


def _sub_exports(sub: str) -> dict[str, tuple[str, ...]]:
    return importlib.import_module(f"lensdist_torch.{sub}")._EXPORTS


SUB_NAMES = sorted(
    (sub, module, name) for sub in SUBPACKAGES for module, names in _sub_exports(sub).items() for name in names
)


def _defines(module: str, name: str) -> bool:
    """Whether ``module``'s source defines ``name`` at its top level (a def, class or assignment, not an import)."""
    return any(
        name in _bound(node) for node in ast.parse(Path(importlib.util.find_spec(module).origin).read_text()).body
    )


@pytest.mark.parametrize("sub, module, name", SUB_NAMES)
def test_every_subpackage_export_resolves_to_its_definition(sub, module, name):
    package = importlib.import_module(f"lensdist_torch.{sub}")
    assert getattr(package, name) is getattr(importlib.import_module(module), name)
    assert module.startswith(f"lensdist_torch.{sub}.")  # a subpackage exports its own modules' names
    assert _defines(module, name), f"{name} is re-exported by {module}: name the module that defines it"
    assert name in _module_all(Path(importlib.util.find_spec(module).origin)), f"{name} is not in {module}.__all__"


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_subpackage_all_and_dir_agree_with_its_table(sub):
    package = importlib.import_module(f"lensdist_torch.{sub}")
    table = sorted(n for names in _sub_exports(sub).values() for n in names)
    assert package.__all__ == table
    assert set(table) <= set(dir(package))
    assert _module_all(ROOT / "lensdist_torch" / sub / "__init__.py") == table  # what the README checks read
    with pytest.raises(AttributeError, match=f"module 'lensdist_torch.{sub}' has no attribute 'not_a_name'"):
        package.not_a_name  # noqa: B018


@pytest.mark.parametrize("package", ["", *SUBPACKAGES])
def test_no_export_is_named_like_a_module_of_its_package(package):
    """An export named like a module of its package would be shadowed by that module once imported."""
    name = ".".join(["lensdist_torch", package]) if package else "lensdist_torch"
    modules = {m.name for m in pkgutil.iter_modules(importlib.import_module(name).__path__)}
    assert modules & set(importlib.import_module(name).__all__) == set()


def test_top_level_and_subpackages_take_a_name_from_the_same_module():
    top = {n: module for module, names in _exports().items() for n in names}
    differ = [(sub, n, module, top[n]) for sub, module, n in SUB_NAMES if n in top and top[n] != module]
    assert differ == []


def test_importing_a_primitive_loads_no_heavy_module():
    """Importing ``geometry.distortion`` runs ``geometry/__init__.py``: its exports stay unloaded."""
    heavy = ("pycolmap", "cv2", "matplotlib", "lensdist_torch.workflows", "lensdist_torch.data")
    code = (
        "import sys, lensdist_torch.geometry.distortion\n"
        f"print(','.join(m for m in sys.modules if any(m == h or m.startswith(h + '.') for h in {heavy!r})))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


def test_lazy_exports_refuses_a_name_twice():
    from lensdist_torch._lazy import lazy_exports

    with pytest.raises(ValueError, match="names exported twice: sqrt"):
        lazy_exports("demo", {"math": ("sqrt",), "cmath": ("sqrt",)})


def test_the_stub_is_generated_from_the_table():
    assert STUB.read_text() == stub_text(), "run: python tests/meta/test_public_names.py --write"


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    STUB.write_text(stub_text())
    print(f"wrote {STUB.relative_to(ROOT)}")
