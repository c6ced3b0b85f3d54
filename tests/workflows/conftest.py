"""Shared fixtures of the workflow tests: one tiny protocol run (small images, few pairs)."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.config import config_from_dict

#: A protocol small enough for CI: 96 x 128 images, 200 training and 12 test pairs.
TINY = {
    "image": {"height": 96, "width": 128},
    "protocol": {"n_train": 200, "n_test_distorted": 8, "n_test_undistorted": 4, "shard_size": 100},
    "classifier": {"n_eigenvectors": 2},
}


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
