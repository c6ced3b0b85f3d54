"""Every Python block of the README and of the guides (docs/guide/) runs as written (a user copies them)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
GUIDE_BLOCKS = [(p.name, i, block) for p in sorted((ROOT / "docs" / "guide").glob("*.md"))
                for i, block in enumerate(re.findall(r"```python\n(.*?)```", p.read_text(), flags=re.S))]
MAX_README_LINES = 300


def test_readme_has_python_blocks():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_runs(index, capsys):
    exec(compile(BLOCKS[index], f"README block {index}", "exec"), {"__name__": "__readme__"})


def test_readme_is_short():
    """The README says how to use; the guides, the method and the results hold the rest."""
    assert len(README.read_text().splitlines()) <= MAX_README_LINES


@pytest.mark.parametrize("guide, index, block", GUIDE_BLOCKS, ids=[f"{g}-{i}" for g, i, _ in GUIDE_BLOCKS])
def test_guide_block_runs(guide, index, block, capsys):
    exec(compile(block, f"{guide} block {index}", "exec"), {"__name__": "__guide__"})


def test_loss_snippet_prints_what_the_readme_says(capsys):
    block = next(b for b in BLOCKS if "masked_mean" in b)
    exec(compile(block, "README loss block", "exec"), {"__name__": "__readme__"})
    out = capsys.readouterr().out.splitlines()
    claimed = re.search(r"This prints `(full [^`]*)`, `(quarter [^`]*)`, `(none [^`]*)`", README.read_text())
    assert claimed is not None
    printed = [line for line in out if line]
    assert printed == list(claimed.groups())


TOML_BLOCKS = re.findall(r"```toml\n(.*?)```", README.read_text(), flags=re.S)


@pytest.mark.parametrize("index", range(len(TOML_BLOCKS)))
def test_readme_toml_block_is_a_valid_config(index, tmp_path):
    """Every TOML block of the README loads as a config and sets what it says (non-default)."""
    from lensdist_torch.config import LensdistConfig, config_to_dict, load_config

    path = tmp_path / "block.toml"
    path.write_text(TOML_BLOCKS[index])
    loaded, default = config_to_dict(load_config(path)), config_to_dict(LensdistConfig())
    assert loaded != default
