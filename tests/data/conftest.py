"""Shared fixtures of the data-set tests: the tiny data set (generated_sets.TINY) generated once
per module, and a fresh copy of it for each test that changes it. A module that needs another
reference (test_shards.py: with generate's summary) defines its own ``reference``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from generated_sets import generate_once


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The tiny data set, generated once per module."""
    return generate_once(tmp_path_factory, "tiny")[0]


@pytest.fixture
def data(reference, tmp_path) -> Path:
    """A fresh copy of the reference data set."""
    out = tmp_path / "d"
    shutil.copytree(reference, out)
    return out
