"""The package's layering (docs/architecture.md): imports only point down, matplotlib lives in
the figures module only, ``import lensdist_torch`` loads no application layer, no module grows
past the size a reader can hold."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / "lensdist_torch"

#: Layer of a module, by its dotted path below lensdist_torch (first match wins).
LAYERS = [
    ("_lazy", 0),
    ("config", 0),
    ("core.", 1),
    ("metric.", 1),
    ("geometry.", 1),
    ("registration.", 2),
    ("selfcal.", 2),
    ("classify.", 2),
    ("calibration.controllers.", 4),
    ("calibration.", 2),
    ("data.", 3),
    ("workflows.", 4),
    ("cli.", 5),
]
MAX_LINES = 450


def _modules() -> dict[str, Path]:
    out = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG).with_suffix("")
        parts = [p for p in rel.parts if p != "__init__"]
        out[".".join(parts)] = path
    return out


def _layer(name: str) -> int | None:
    for prefix, rank in LAYERS:
        if name == prefix.rstrip(".") or name.startswith(prefix):
            return rank
    return None  # the package's __init__ (the public API) and package markers


def _imports(name: str, path: Path) -> list[str]:
    """Modules of lensdist_torch imported by ``path`` (absolute or relative), anywhere in it."""
    tree = ast.parse(path.read_text())
    pkg_parts = name.split(".")[:-1] if path.name != "__init__.py" else name.split(".")
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[: len(pkg_parts) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
                found.append(mod)
            elif node.module and node.module.startswith("lensdist_torch"):
                found.append(node.module[len("lensdist_torch") :].lstrip("."))
        elif isinstance(node, ast.Import):
            found += [
                a.name[len("lensdist_torch") :].lstrip(".") for a in node.names if a.name.startswith("lensdist_torch")
            ]
    return [f for f in found if f]


def test_every_module_has_a_layer():
    missing = [n for n in _modules() if n and _layer(n) is None and not _modules()[n].name == "__init__.py"]
    assert missing == []


def test_imports_only_point_down():
    bad = []
    for name, path in _modules().items():
        rank = _layer(name)
        if rank is None:
            continue
        for target in _imports(name, path):
            t = _layer(target)
            if t is not None and t > rank:
                bad.append(f"{name} (layer {rank}) imports {target} (layer {t})")
    assert bad == []


def _imports_matplotlib(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text())):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
        names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
        if any(n == "matplotlib" or n.startswith("matplotlib.") for n in names):
            return True
    return False


def test_matplotlib_only_in_figures():
    assert [n for n, p in _modules().items() if _imports_matplotlib(p)] == ["workflows.figures"]


def test_no_module_too_long():
    long = {
        n: len(p.read_text().splitlines()) for n, p in _modules().items() if len(p.read_text().splitlines()) > MAX_LINES
    }
    assert long == {}


def test_import_loads_no_application_layer():
    code = (
        "import sys, lensdist_torch\n"
        "bad = [m for m in sys.modules if m.startswith(('lensdist_torch.data', 'lensdist_torch.workflows', "
        "'lensdist_torch.cli'))"
        " or m == 'matplotlib']\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""


def test_lazy_names_resolve():
    import lensdist_torch

    for name in ("analyze_pair", "reproduce", "generate", "load_set"):
        assert callable(getattr(lensdist_torch, name))
    with pytest.raises(AttributeError, match="no attribute"):
        lensdist_torch.not_a_name  # noqa: B018


ROOT = PKG.parent
#: where code of the project lives: the package, the training scripts, the benchmarks
CODE = [PKG, ROOT / "train", ROOT / "benchmarks"]


def _private_imports(path: Path, home: str, root: Path = ROOT) -> list[str]:
    """``from X import _name`` anywhere in ``path``, and private modules (``_x``) imported from outside their package.

    ``home`` is the dotted package of ``path`` (e.g. "lensdist_torch.metric"); dunders such as
    ``__version__`` are public. A private module's package includes its subpackages
    (``lensdist_torch._lazy`` serves ``lensdist_torch.geometry``).
    """
    bad = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom) or node.module == "__future__":
            continue
        for alias in node.names:
            if alias.name.startswith("_") and not alias.name.startswith("__"):
                bad.append(f"{path.relative_to(root)}:{node.lineno} imports {alias.name} from {node.module}")
        parts = (node.module or "").split(".")
        private = [i for i, p in enumerate(parts) if p.startswith("_") and not p.startswith("__")]
        owner = ".".join(parts[: private[0]]) if private else home
        if not node.level and home != owner and not home.startswith(owner + "."):
            bad.append(f"{path.relative_to(root)}:{node.lineno} imports the private module {node.module}")
    return bad


def test_no_private_name_crosses_a_module():
    """A private name stays in its module; a private module in its package (piq's functional/ shape)."""
    bad = []
    for base in CODE:
        for path in sorted(base.rglob("*.py")):
            home = ".".join(path.relative_to(ROOT).parent.parts)
            bad += _private_imports(path, home)
    assert bad == []


def test_private_import_check_can_fail(tmp_path):
    """The rule above sees both kinds of breach (a check that cannot fail proves nothing)."""
    f = tmp_path / "m.py"
    f.write_text("from lensdist_torch.metric.criteria import _x\nfrom lensdist_torch.metric._hard import y\n")
    got = _private_imports(f, "lensdist_torch.workflows", tmp_path)
    assert [g.split(" imports ")[1] for g in got] == ["_x from lensdist_torch.metric.criteria",
                                                      "the private module lensdist_torch.metric._hard"]
    assert len(_private_imports(f, "lensdist_torch.metric", tmp_path)) == 1  # its own package may use _hard
    f.write_text("from lensdist_torch._lazy import lazy_exports\nfrom lensdist_torch.metric._hard import y\n")
    assert len(_private_imports(f, "lensdist_torch.metric.sub", tmp_path)) == 0  # and its subpackages
    assert len(_private_imports(f, "lensdist_torch_extra", tmp_path)) == 2  # a prefix is not a package


def test_architecture_doc_names_every_module():
    """docs/architecture.md lists every module of the package (by its file name in its folder)."""
    doc = (ROOT / "docs" / "architecture.md").read_text()
    missing = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG)
        if path.name == "__init__.py" or "scenes" in rel.parts:
            continue
        if (
            f"`{path.name}`" not in doc
            and f"`{rel.as_posix()}`" not in doc
            and f"{rel.parent.as_posix()}/{path.name}" not in doc
        ):
            missing.append(rel.as_posix())
    assert missing == []


def _import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports anywhere (a function's import too); packages' own tables aside."""
    mods = {n: p for n, p in _modules().items() if p.name != "__init__.py"}
    graph = {}
    for name, path in mods.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lensdist_torch."):
                base = node.module[len("lensdist_torch.") :]
                targets |= {f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names}
        graph[name] = {t for t in targets if t in mods and t != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circle():
    """No two modules import each other, directly or around a circle, not even inside a function."""
    assert _cycles(_import_graph()) == []


def test_circle_check_can_fail():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _record_fields() -> dict[str, int]:
    """The package's result records (NamedTuples and dataclasses) -> their number of fields."""
    out = {}
    for path in PKG.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and (
                any(getattr(b, "id", None) == "NamedTuple" for b in node.bases)
                or any("dataclass" in ast.unparse(d) for d in node.decorator_list)
            ):
                out[node.name] = sum(isinstance(s, ast.AnnAssign) for s in node.body)
    return out


def positional_records(path: Path, records: dict[str, int], root: Path = ROOT) -> list[str]:
    """Calls in ``path`` that build one of ``records`` of more than two fields from two or more positional values.

    ``Record(*fields)`` of one starred value (a record rebuilt field by field, as ``torch.cat``
    over a batch's records) is allowed: its order is the record's own.
    """
    bad = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
            if records.get(name, 0) > 2 and len(node.args) >= 2:
                bad.append(f"{path.relative_to(root)}:{node.lineno} {name}")
    return bad


def test_no_record_is_built_by_position():
    """Insert a field and every value after it would shift silently: records are built by keyword."""
    records = _record_fields()
    assert [b for path in sorted(PKG.rglob("*.py")) for b in positional_records(path, records)] == []


def test_record_check_can_fail(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("R(1, 2, 3)\nR(*xs)\nR(a=1, b=2, c=3)\n")
    assert positional_records(f, {"R": 3}, tmp_path) == ["m.py:1 R"]
