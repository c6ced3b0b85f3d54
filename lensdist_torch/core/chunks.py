"""How a batch is cut into chunks: small on the CPU (its cache), large on a GPU (its parallelism).

The metric's hard path and the estimators work through a batch chunk by chunk. On the CPU a
chunk of a few pairs keeps their intermediates in the cache (each config's ``chunk_size``); on a
GPU such small chunks leave it idle between kernel launches (the hard map ran at 0.2-0.5 x
kornia's SSIM there: ``benchmarks/bench_gpu.py``), so a chunk holds up to
:data:`GPU_CHUNK_PIXELS` pixels instead. Results do not depend on the chunking.
"""

from __future__ import annotations

import torch

__all__ = ["GPU_CHUNK_PIXELS", "chunk_slices"]

#: Pixels per image in one chunk on a GPU (2^24: 123 pairs at 320 x 424, 8 at 1920 x 1080).
#: The self-calibration's intermediates, the largest, take about 150 bytes a pixel: ~2.5 GB.
GPU_CHUNK_PIXELS = 2**24


def chunk_slices(n: int, cpu_chunk: int, device: torch.device | str, pixels: int) -> list[slice]:
    """Slices cutting a batch of ``n`` into chunks.

    Args:
        n: the batch size.
        cpu_chunk: the chunk on the CPU (a config's ``chunk_size``), also the least on a GPU.
        device: where the batch is.
        pixels: pixels per image (H W).

    Returns:
        Consecutive slices covering range(n).

    Example:
        >>> chunk_slices(5, 2, "cpu", 100)
        [slice(0, 2, None), slice(2, 4, None), slice(4, 5, None)]
        >>> chunk_slices(5, 2, "cuda", 100)  # a GPU: one chunk
        [slice(0, 5, None)]
    """
    gpu = torch.device(device).type != "cpu"
    step = max(cpu_chunk, GPU_CHUNK_PIXELS // max(pixels, 1)) if gpu else cpu_chunk
    return [slice(i, min(i + step, n)) for i in range(0, n, step)]
