"""Text has one home each: a docstring or a config comment says what a value does, never when it was
measured or on which footage (those live in docs/results/ and CHANGELOG.md, which change with each
run, where a docstring would silently go stale)."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: a date, or the name of the footage a benchmark ran on
STALE = re.compile(r"\b20\d\d-\d\d-\d\d\b|GoPro|HERO4")


def _docstrings(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            doc = ast.get_docstring(node, clean=False)
            if doc:
                out.append((getattr(node, "lineno", 1), doc))
    return out


def _comments(path: Path) -> list[tuple[int, str]]:
    tokens = tokenize.generate_tokens(io.StringIO(path.read_text()).readline)
    return [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT]


def stale_text(path: Path, root: Path = ROOT) -> list[str]:
    """``path:line: text`` for each docstring or comment of a .py file, or comment of a .toml file, that dates a figure
    or names footage."""
    if path.suffix == ".toml":
        found = [(i + 1, line.split("#", 1)[1]) for i, line in enumerate(path.read_text().splitlines()) if "#" in line]
    else:
        found = _docstrings(path) + _comments(path)
    return [
        f"{path.relative_to(root)}:{line}: {STALE.search(text).group(0)}" for line, text in found if STALE.search(text)
    ]


def test_no_docstring_or_comment_dates_a_figure_or_names_footage():
    files = sorted((ROOT / "lensdist_torch").rglob("*.py")) + sorted((ROOT / "configs").glob("*.toml"))
    assert [hit for f in files for hit in stale_text(f)] == []


@pytest.mark.parametrize("text", ['"""Measured on 2026-11-28."""\n', '"""x."""\n# on the GoPro views\n'])
def test_the_check_can_fail(tmp_path, text):
    f = tmp_path / "m.py"
    f.write_text(text)
    assert len(stale_text(f, tmp_path)) == 1


#: a Markdown link that climbs out of its file's folder or starts at the root: users of a copied
#: folder (a wheel's docs, a checkout's subfolder) would meet a dead link
CLIMBING = re.compile(r"\]\((\.\./|/)")


def climbing_links(path: Path, root: Path = ROOT) -> list[str]:
    """``path:line`` of each Markdown link in ``path`` that climbs out of its folder."""
    return [
        f"{path.relative_to(root)}:{i + 1}"
        for i, line in enumerate(path.read_text().splitlines())
        if CLIMBING.search(line)
    ]


def test_no_markdown_link_climbs_out_of_its_folder():
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "train").rglob("*.md")),
             *sorted((ROOT / "checkpoints").rglob("*.md"))]
    assert [bad for f in files for bad in climbing_links(f)] == []


def test_climbing_link_check_can_fail(tmp_path):
    f = tmp_path / "a.md"
    f.write_text("[ok](b.md)\n[up](../b.md)\n[root](/x)\n`../b.md` as text\n")
    assert climbing_links(f, tmp_path) == ["a.md:2", "a.md:3"]
