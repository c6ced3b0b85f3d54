"""A sequence's frames in order: a folder of images or a video, what calibrate and undistort read.

A folder's images are sorted by name, numbers in their natural order; a video is decoded by
:mod:`~lensdist_torch.core.video`. Frames are read one at a time, so a long video stays small.

Example:
    >>> import tempfile
    >>> import torch
    >>> from lensdist_torch.core.png import encode_png, to_uint8
    >>> tmp = tempfile.TemporaryDirectory()
    >>> for name in ("f10.png", "f2.png"):
    ...     _ = (Path(tmp.name) / name).write_bytes(encode_png(to_uint8(torch.zeros(1, 4, 6))))
    >>> [p.name for p in list_frames(tmp.name)]  # 2 before 10
    ['f2.png', 'f10.png']
    >>> [(name, tuple(img.shape)) for name, img in read_frames(tmp.name)]
    [('f2', (1, 1, 4, 6)), ('f10', (1, 1, 4, 6))]
    >>> tmp.cleanup()
"""

from __future__ import annotations

import re
from pathlib import Path

from lensdist_torch.core.images import IMAGE_SUFFIXES, load_image
from lensdist_torch.core.video import VIDEO_SUFFIXES, video_frames

__all__ = ["IMAGE_SUFFIXES", "VIDEO_SUFFIXES", "list_frames", "read_frames", "frames_of_one_size"]


def _natural(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_frames(folder: str | Path) -> list[Path]:
    """The image files of a folder (``IMAGE_SUFFIXES``), by name, numbers in order (2 before 10)."""
    folder = Path(folder)
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if not files:
        raise ValueError(f"path {folder} holds no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return sorted(files, key=lambda p: _natural(p.name))


def read_frames(path: str | Path, grey: bool = True, max_frames: int | None = None):
    """Yield (name, (1, C, H, W) float frame in [0, 1]) from a folder of images or a video.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: an empty folder, an unknown file type, or a video with neither PyAV nor OpenCV installed.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"path not found: {path}")
    if max_frames is not None and (type(max_frames) is not int or max_frames < 1):
        raise ValueError(f"max_frames must be a positive int or None, got {max_frames!r}")
    if path.is_dir():
        source = ((p.stem, load_image(p, grey=grey)) for p in list_frames(path))
    elif path.suffix.lower() in VIDEO_SUFFIXES:
        source = video_frames(path, grey)
    else:
        raise ValueError(f"path must be a folder of frames or a video ({', '.join(VIDEO_SUFFIXES)}), got {path.name}")
    for i, item in enumerate(source):
        if max_frames is not None and i >= max_frames:
            return
        yield item


def frames_of_one_size(path: str | Path, *, grey: bool, max_frames: int | None, quiet: bool, desc: str):
    """:func:`read_frames` with a progress bar, checking that every frame has the first's size."""
    from tqdm import tqdm

    path, size = Path(path), None
    total = min(len(list_frames(path)), max_frames or 1 << 62) if path.is_dir() else None
    with tqdm(total=total, disable=quiet, desc=desc, unit="frame", leave=False) as bar:
        for name, img in read_frames(path, grey, max_frames):
            size = size or tuple(img.shape[-2:])
            if tuple(img.shape[-2:]) != size:
                raise ValueError(f"frames must all have one size: the first is {size[0]} x {size[1]}, {name} is "
                                 f"{img.shape[-2]} x {img.shape[-1]}")
            yield name, img
            bar.update(1)
