"""Issue 22, item 3: `lensdist calibrate video.mp4` reads a video as easily as a folder: PyAV (the
'video' extra) where installed, OpenCV's VideoCapture where only cv2 is, and a one-line error
naming the extra where neither is."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from lensdist_torch import cli
from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
from lensdist_torch.core.frames import read_frames
from lensdist_torch.core.video import video_frames, video_reader
from lensdist_torch.geometry.distortion import delta_avg

K2, SIZE, N = 1e-5, (120, 160), 8


@pytest.fixture(scope="module")
def frames() -> np.ndarray:
    distorted, _ = synthetic_sequence(N, K2, 0.0, size=SIZE)
    return (distorted[:, 0].clamp(0, 1) * 255).round().byte().numpy()


def _write(path, frames: np.ndarray) -> None:
    """A lossless (PyAV: x264 crf 0, 4:4:4) or near-lossless (cv2: mp4v) mp4 of grey frames."""
    try:
        import av
    except ImportError:
        cv2 = pytest.importorskip("cv2")
        out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, SIZE[::-1])
        for f in frames:
            out.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
        out.release()
        return
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt, stream.options = SIZE[1], SIZE[0], "yuv444p", {"crf": "0"}
        for f in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(np.repeat(f[..., None], 3, 2), format="rgb24")))
        container.mux(stream.encode())


@pytest.fixture(scope="module")
def video(tmp_path_factory, frames):
    path = tmp_path_factory.mktemp("video") / "dive.mp4"
    _write(path, frames)
    return path


def test_calibrate_reads_a_video_as_a_folder(video, capsys, tmp_path):
    """The video is of a plane: with planar pairs (``[selfcal] parallax = 0``) the class is
    right; by default the plane + parallax model's scatter over 9 pairs of 120 x 160 frames is the
    relief the sequence cannot exclude, and the answer is "cannot tell", its interval covering."""
    if video_reader() is None:
        pytest.skip("neither PyAV nor OpenCV installed")
    planar = tmp_path / "planar.toml"
    planar.write_text("[selfcal]\nparallax = 0\n")
    assert cli.main(["calibrate", str(video), "--method", "direct", "--json", "--quiet", "--config", str(planar)]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frames"] == N and res["image_size"] == list(SIZE) and res["class"] == "2"
    assert res["k2_user"] == pytest.approx(K2, rel=0.1)
    assert cli.main(["calibrate", str(video), "--method", "direct", "--json", "--quiet"]) == 0
    default = json.loads(capsys.readouterr().out)
    assert default["delta_avg_user_px"] == res["delta_avg_user_px"]  # the same estimate, a wider interval
    lo, hi = default["delta_avg_user_interval"]
    truth = float(delta_avg([K2], [0.0], *SIZE)[0])
    assert default["class"] is None and "at the paper's frame spans classes" in default["reason"] and lo <= truth <= hi
    assert hi - lo > 5 * (res["delta_avg_user_interval"][1] - res["delta_avg_user_interval"][0])


@pytest.mark.parametrize("reader", ["pyav", "opencv"])
def test_both_readers_give_the_frames(video, frames, reader, monkeypatch):
    pytest.importorskip("av" if reader == "pyav" else "cv2")
    if reader == "opencv":  # PyAV missing: OpenCV reads the video
        monkeypatch.setitem(sys.modules, "av", None)
        assert video_reader() == "opencv"
    got = list(read_frames(video))
    assert [n for n, _ in got] == [f"frame_{i:06d}" for i in range(N)]
    grey = np.stack([(img[0, 0].numpy() * 255).round() for _, img in got])
    assert grey.shape == (N, *SIZE) and np.abs(grey - frames).mean() < 2.0  # lossless but for the colour conversion
    rgb = next(video_frames(video, grey=False, reader=reader))[1]
    assert tuple(rgb.shape) == (1, 3, *SIZE)


@pytest.mark.bad_input
def test_without_a_reader_the_error_names_the_extra(video, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)
    monkeypatch.setitem(sys.modules, "cv2", None)
    assert video_reader() is None
    assert cli.main(["calibrate", str(video), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err == ("lensdist calibrate: error: reading the video dive.mp4 needs PyAV or OpenCV: "
                   "pip install 'lensdist_torch[video]' (or pass a folder of frames)\n")


@pytest.mark.bad_input
@pytest.mark.parametrize("reader", ["pyav", "opencv"])
def test_a_file_that_is_no_video_is_one_line(tmp_path, reader, monkeypatch):
    pytest.importorskip("av" if reader == "pyav" else "cv2")
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"not a video at all")
    with pytest.raises(ValueError, match="clip.mp4 is not a video") as err:
        list(video_frames(bad, reader=reader))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("decoded,announced,cut", [(6, 12, True), (9, 10, False), (8, 8, False), (5, 0, False)])
def test_a_video_decoding_short_of_its_header_is_truncated(fake_pyav, decoded, announced, cut):
    """Fewer than DECODED_SHARE (0.9) of the announced frames: one line naming the cut; a header without a count
    (0) or a count the frames reach within the share passes."""
    fake_pyav([lambda format: np.zeros(SIZE, np.uint8)] * decoded, announced=announced)
    if not cut:
        assert len(list(video_frames("clip.mp4", reader="pyav"))) == decoded
        return
    with pytest.raises(ValueError, match=r"^clip\.mp4 is truncated or damaged: 6 of the 12 frames its header "):
        list(video_frames("clip.mp4", reader="pyav"))


def test_a_decoding_error_midway_is_one_line(fake_pyav):
    fake_pyav([lambda format: np.zeros(SIZE, np.uint8), RuntimeError("Invalid data found when processing input")])
    frames = video_frames("clip.mp4", reader="pyav")
    next(frames)
    with pytest.raises(ValueError, match=r"^clip\.mp4 is truncated or damaged: decoding stopped after 1 frames"):
        next(frames)
