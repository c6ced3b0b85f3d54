"""Reading the frames of a video: PyAV (the ``video`` extra) or, without it, OpenCV's VideoCapture.

``pip install -e ".[video]"`` (in the README's set-up command) installs PyAV, which decodes what
FFmpeg decodes. Where PyAV is missing but OpenCV is installed (``opencv-python`` or
``opencv-python-headless``, e.g. from the ``test`` extra), ``cv2.VideoCapture`` reads the video
instead (its FFmpeg backend: the same frames for the usual codecs; the conversion to grey is
OpenCV's, within one grey level of PyAV's). Where neither is installed, reading a video is a
one-line ``ValueError`` naming the extra. :data:`VIDEO_SUFFIXES` lists the suffixes taken for a
video (any letter case). A video whose decoding stops short of the frames its header announces
(by more than :data:`DECODED_SHARE`'s slack) or fails midway is a one-line ``ValueError`` once its
last frame is read: a truncated file, not a shorter video.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import torch

__all__ = ["DECODED_SHARE", "VIDEO_SUFFIXES", "video_reader", "video_frames"]

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
#: A video that decodes fewer than this share of the frames its header announces is truncated (some containers
#: only estimate the count; where they give none, nothing is checked).
DECODED_SHARE = 0.9


def _whole(path: Path, decoded: int, announced: int) -> None:
    """A one-line ``ValueError`` where ``decoded`` frames fall short of the ``announced`` ones (module docstring)."""
    if announced > 0 and decoded < DECODED_SHARE * announced:
        raise ValueError(f"{path.name} is truncated or damaged: {decoded} of the {announced} frames its header "
                         "announces decode")


def video_reader() -> str | None:
    """Which reader a video would be read with here: "pyav", "opencv" or None (neither installed).

    Example:
        >>> video_reader() in ("pyav", "opencv", None)
        True
    """
    try:
        import av  # noqa: F401 (the video extra)

        return "pyav"
    except ImportError:
        pass
    try:
        import cv2  # noqa: F401

        return "opencv"
    except ImportError:
        return None


def _pyav(path: Path, grey: bool) -> Iterator[torch.Tensor]:
    import av

    try:
        container = av.open(str(path))
    except Exception as exc:  # av.error.FFmpegError and its kin: not a video PyAV can open
        raise ValueError(f"{path.name} is not a video PyAV can read ({type(exc).__name__}: {exc})") from None
    with container:
        if not container.streams.video:
            raise ValueError(f"{path.name} holds no video stream")
        announced, decoded, frames = int(container.streams.video[0].frames or 0), 0, container.decode(video=0)
        while True:
            try:
                frame = next(frames)
            except StopIteration:
                break
            except Exception as exc:  # av.error.FFmpegError and its kin, midway
                raise ValueError(f"{path.name} is truncated or damaged: decoding stopped after {decoded} frames "
                                 f"({type(exc).__name__}: {exc})") from None
            arr = torch.from_numpy(frame.to_ndarray(format="gray" if grey else "rgb24"))
            decoded += 1
            yield arr[None] if arr.dim() == 2 else arr.permute(2, 0, 1)
        _whole(path, decoded, announced)


def _opencv(path: Path, grey: bool) -> Iterator[torch.Tensor]:
    import cv2

    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # FFmpeg's own lines would precede the one-line error
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise ValueError(
                f"{path.name} is not a video OpenCV can read (or OpenCV was built without a video backend)"
            )
        announced, decoded = int(max(cap.get(cv2.CAP_PROP_FRAME_COUNT), 0)), 0
        while True:
            ok, bgr = cap.read()
            if not ok:
                _whole(path, decoded, announced)
                return
            decoded += 1
            if grey:
                yield torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))[None]
            else:
                yield torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).permute(2, 0, 1)
    finally:
        cap.release()


def video_frames(path: str | Path, grey: bool = True, reader: str | None = None):
    """Yield (name, (1, C, H, W) float frame in [0, 1]) for every frame of a video, named ``frame_000000`` ...

    Args:
        path: the video file.
        grey: one grey channel (True) or RGB.
        reader: "pyav" or "opencv"; None: :func:`video_reader` (PyAV where installed).

    Raises:
        ValueError: neither PyAV nor OpenCV installed (the message names the extra), or a file
            the reader cannot open (raised at the first frame asked for).

    Example:
        A generator: nothing is opened or checked before the first frame is asked for.

        >>> frames = video_frames("clip.mp4", reader="ffmpeg")
        >>> next(frames)
        Traceback (most recent call last):
        ...
        ValueError: reader must be 'pyav', 'opencv' or None, got 'ffmpeg'
    """
    path = Path(path)
    reader = video_reader() if reader is None else reader
    if reader is None:
        raise ValueError(f"reading the video {path.name} needs PyAV or OpenCV: pip install 'lensdist_torch[video]' "
                         "(or pass a folder of frames)")
    if reader not in ("pyav", "opencv"):
        raise ValueError(f"reader must be 'pyav', 'opencv' or None, got {reader!r}")
    frames = _pyav(path, grey) if reader == "pyav" else _opencv(path, grey)
    for i, arr in enumerate(frames):
        yield f"frame_{i:06d}", (arr.float() / 255.0)[None].contiguous()
