"""Torch's intra-op thread count for a block of work, restored after it."""

from __future__ import annotations

import contextlib

import torch

__all__ = ["torch_threads"]


@contextlib.contextmanager
def torch_threads(n: int):
    """Torch's CPU ops run on ``n`` threads inside the block; the count before is restored after it.

    The count is the process's: threads started inside the block share it. Float32 reductions
    depend on it, so a result that must not depend on the machine's cores is computed under a
    fixed count.

    Example:
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    before = torch.get_num_threads()
    if n == before:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)

