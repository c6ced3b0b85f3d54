"""Shared setup of the metric tests: every module runs with one intra-op thread."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module", autouse=True)
def _one_thread(one_thread_module):
    """``one_thread_module`` (tests/conftest.py) for every module of this folder."""
    yield
