"""Shared fixtures of the workflow tests: one tiny protocol run (small images, few pairs)."""

from __future__ import annotations

import pytest
import torch
from workflow_helpers import TINY

from lensdist_torch.config import config_from_dict


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """``reproduce`` of the tiny protocol, once per session: (out folder, its return value)."""
    from lensdist_torch.workflows.reproduce import reproduce

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out = tmp_path_factory.mktemp("reproduce")
        res = reproduce(config_from_dict(TINY), out, workers=1, progress=False, figures=True)
    finally:
        torch.set_num_threads(n)
    return out, res
