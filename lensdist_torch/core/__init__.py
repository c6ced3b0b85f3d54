"""Primitives used everywhere: image checks and loading, atomic files and versioned checkpoints.

Modules:

* :mod:`~lensdist_torch.core.images`: image checks, grey conversion, loading, resizing, the embedded scenes.
* :mod:`~lensdist_torch.core.image_headers`: a file's header (size, palette) read before decoding.
* :mod:`~lensdist_torch.core.video`: a video's frames, through PyAV or OpenCV.
* :mod:`~lensdist_torch.core.outputs`: output paths checked before the work.
* :mod:`~lensdist_torch.core.storage`: atomic writes and versioned checkpoints.
* :mod:`~lensdist_torch.core.chunks`: how a batch is cut into chunks, by device.
* :mod:`~lensdist_torch.core.threads`: torch's thread count for a block.

The names users need are exported here and imported on first use (PEP 562), so importing one
module of the package loads no other.

Example:
    >>> from lensdist_torch.core import load_scene, resize_to, to_grey
    >>> tuple(resize_to(to_grey(load_scene("gravel")), 32, 40).shape)
    (1, 1, 32, 40)
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.core.images": ("check_image", "load_image", "load_scene", "resize_to", "scene_names", "to_grey"),
    "lensdist_torch.core.storage": (
        "CheckpointError",
        "atomic_write_bytes",
        "atomic_write_text",
        "load_versioned",
        "save_versioned",
    ),
    "lensdist_torch.core.video": ("video_frames",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
