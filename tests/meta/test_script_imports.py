"""Every ``from lensdist_torch... import name`` in benchmarks/, examples/ and train/ names something that exists:
a module move (``git mv``) must move the scripts' imports with it."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted(p for folder in ("benchmarks", "examples", "train") for p in (ROOT / folder).rglob("*.py"))


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "lensdist_torch":
            yield node.module, [a.name for a in node.names]


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_the_scripts_import_what_exists(path):
    missing = []
    for module, names in _imports(path):
        m = importlib.import_module(module)
        for name in names:
            if not hasattr(m, name):
                try:
                    importlib.import_module(f"{module}.{name}")
                except ImportError:
                    missing.append(f"{module}.{name}")
    assert not missing, f"{path.name} imports {missing}"


def test_there_are_scripts_to_check():
    assert len(SCRIPTS) > 20
