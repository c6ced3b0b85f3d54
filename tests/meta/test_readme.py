"""Every Python block of the README runs as written (a user copies them)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_has_python_blocks():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_runs(index, capsys):
    exec(compile(BLOCKS[index], f"README block {index}", "exec"), {"__name__": "__readme__"})


def test_loss_snippet_prints_what_the_readme_says(capsys):
    block = next(b for b in BLOCKS if "masked_mean" in b)
    exec(compile(block, "README loss block", "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out.splitlines()
    claimed = re.search(r"This prints `(full [^`]*)`, `(quarter [^`]*)`, `(none [^`]*)`", README.read_text())
    assert claimed is not None
    printed = [line for line in out if line]
    assert printed == list(claimed.groups())
