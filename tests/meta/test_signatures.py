"""Issue 50: a public function takes its data by position and its settings by keyword, after a
bare ``*`` (as scikit-image and kornia do): at most ``MAX_POSITIONAL`` positional parameters.

Public: in the module's ``__all__``, or without a leading underscore where the module has none.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[2] / "lensdist_torch"
MAX_POSITIONAL = 4

#: The public functions that still take more (module below lensdist_torch, function), and why: none.
ALLOWED: dict[str, str] = {}


def _public(tree: ast.Module) -> set[str] | None:
    """The module's ``__all__``, or None where it has none."""
    for node in tree.body:
        targets = (
            node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        )
        if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
            return set(ast.literal_eval(node.value))
    return None


def _positional(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    args = fn.args.posonlyargs + fn.args.args
    return len(args) - (1 if args and args[0].arg in ("self", "cls") else 0)


def too_many(path: Path, name: str) -> dict[str, int]:
    """``name.function`` -> its positional parameters, for the public functions of ``path`` above the limit."""
    tree = ast.parse(path.read_text())
    names = _public(tree)
    out = {}
    for fn in tree.body:
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            public = fn.name in names if names is not None else not fn.name.startswith("_")
            if public and _positional(fn) > MAX_POSITIONAL:
                out[f"{name}.{fn.name}"] = _positional(fn)
    return out


def _package() -> dict[str, int]:
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = path.relative_to(PKG).with_suffix("").parts
        out |= too_many(path, ".".join(p for p in parts if p != "__init__"))
    return out


def test_public_functions_take_settings_by_keyword():
    assert {k: v for k, v in _package().items() if k not in ALLOWED} == {}


def test_allowed_list_is_current():
    """Each exception still exists and still needs its entry (a fixed one leaves the list)."""
    assert sorted(set(ALLOWED) - set(_package())) == []


def test_signature_check_can_fail(tmp_path):
    """The check sees a public function with five positional parameters (a check that cannot fail proves nothing)."""
    f = tmp_path / "m.py"
    f.write_text(
        "def f(a, b, c, d, e): ...\n"
        "def g(a, b, c, d, *, e): ...\n"
        "def _h(a, b, c, d, e): ...\n"
        "class C:\n    def m(self, a, b, c, d, e): ...\n"
    )
    assert too_many(f, "m") == {"m.f": 5}
    f.write_text("__all__ = ['g']\ndef f(a, b, c, d, e): ...\ndef g(a, b, c, d, e, /): ...\n")
    assert too_many(f, "m") == {"m.g": 5}  # __all__ decides what is public; positional-only counts
