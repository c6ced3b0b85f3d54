"""Torch's thread count for a block (lensdist_torch.core.threads)."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.core.threads import torch_threads


def test_the_thread_count_holds_inside_the_block_and_is_restored_after_an_error():
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError, match="inside"):
        with torch_threads(before + 1):
            assert torch.get_num_threads() == before + 1
            raise RuntimeError("inside")
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("n", [0, -1, 1.0, True, "2"])
def test_a_thread_count_that_is_not_a_positive_int_is_refused(n):
    with pytest.raises(ValueError, match="n must be a positive int"):
        with torch_threads(n):
            pass

