"""The paper's data: the pair protocol, data sets on disk, the embedded scenes.

Modules:

* :mod:`~lensdist_torch.data.synthesis`: the pair protocol: draw, render, register, measure.
* :mod:`~lensdist_torch.data.realism`: the realistic protocol's photometry, noise, JPEG, parallax, occluders.
* :mod:`~lensdist_torch.data.relief`: a scene with relief seen from above: height fields, ground points.
* :mod:`~lensdist_torch.data.relens`: real frames through a known lens (their calibration undone, eq. 4 applied).
* :mod:`~lensdist_torch.data.shards`: generating, resuming and loading data sets (``lensdist generate``).
* :mod:`~lensdist_torch.data.shardfile`: one checksummed shard file, and the check of a set's shards.
* :mod:`~lensdist_torch.data.manifest`: a data set's manifest, validated, merged, never shrunk.
* :mod:`~lensdist_torch.data.locks`: lock files, one run per share of a folder.
* :mod:`~lensdist_torch.data.workers`: the worker processes of ``generate`` and how a run stops.
* ``scenes/``: the embedded CC0 images.

The names users need are exported here and imported on first use (PEP 562), so importing one
module of the package loads no other.

Example:
    >>> from lensdist_torch import LensdistConfig
    >>> from lensdist_torch.data import draw_pairs
    >>> params = draw_pairs(LensdistConfig(), "train", range(3), n_scenes=2)
    >>> tuple(params.M.shape), params.k2.dtype
    ((3, 3, 3), torch.float64)
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.data.shards": ("generate", "load_set"),
    "lensdist_torch.data.synthesis": ("PairBatch", "PairParams", "draw_pairs", "make_pairs", "render_pairs"),
    "lensdist_torch.data.realism": ("draw_realism",),
    "lensdist_torch.data.relief": ("draw_height_field", "relief_samples"),
    "lensdist_torch.data.relens": ("RelensedFrames", "relens_frames"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
