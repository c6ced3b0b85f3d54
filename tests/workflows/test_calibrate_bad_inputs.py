"""Bad input to `lensdist calibrate PATH`, run as a user runs it (`--out` a fresh folder, `--json`): frames no
engine can reconstruct (uniform grey, noise), unrelated frames, two frames and one, frames of mixed sizes, a
truncated video.

Each ends as documented (README "Commands", docs/guide/reliability.md, docs/guide/calibrate.md "Cannot tell"):
an error is exit status 2 and one line ``lensdist calibrate: error: ...`` on stderr naming the reason, nothing on
stdout and nothing in --out; a "cannot tell" is status 0, one strict JSON object with ``class`` null and the reason,
and --out holding calibration.json alone, what was printed. No temporary folder is left behind either way.
Frames are 120 x 160, so each run takes seconds (COLMAP's runs a little more).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time

import pytest
import torch
from one_line import one_line_error, one_line_usage

from lensdist_torch import cli
from lensdist_torch.calibration.controllers.calibrate import calibrate_path, synthetic_sequence
from lensdist_torch.core.images import load_scene
from lensdist_torch.core.png import encode_png, to_uint8

pytestmark = pytest.mark.bad_input

SIZE = (120, 160)
K2 = 2e-5  # a clear lens: Delta_avg about 4.4 px at 120 x 160
#: A run on 120 x 160 frames that takes more CPU seconds than this (all threads, COLMAP's too) is a bug of its own;
#: CPU time, not wall time: the cores may be shared.
CPU_SECONDS = 60.0


def _write(folder, frames):
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        (folder / f"frame_{i:02d}.png").write_bytes(encode_png(to_uint8(f)))
    return folder


def _listing(folder):
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []


@pytest.fixture
def calibrate(tmp_path, capsys, monkeypatch):
    """``calibrate(path, *options)``: `lensdist calibrate PATH --out FRESH --json --quiet *options` in-process:
    (status, stdout, stderr, --out folder); checks the run's CPU time and that no temporary folder was left."""
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))  # COLMAP's frames and database go here
    runs = []

    def run(path, *options):
        out = tmp_path / f"out{len(runs)}"
        start = time.process_time()
        code = cli.main(["calibrate", str(path), "--out", str(out), "--json", "--quiet", *options])
        took = time.process_time() - start
        runs.append(out)
        printed = capsys.readouterr()
        assert took < CPU_SECONDS, f"{took:.0f} CPU s on {path}"
        assert _listing(tmp) == [], "a temporary file was left behind"
        return code, printed.out, printed.err, out

    return run


def _error(result, *words) -> str:
    """Status 2, one line on stderr holding every one of ``words``, nothing printed or written."""
    code, out, err, folder = result
    line = one_line_usage(code, err, "calibrate")
    for w in words:
        assert w in line, (w, line)
    assert "Traceback" not in err and out == "" and _listing(folder) == [], (out, _listing(folder))
    return line


def _cannot_tell(result, *words) -> dict:
    """Status 0, one strict JSON object with no class and a reason holding every one of ``words``; --out holds
    calibration.json alone, what was printed."""
    code, out, err, folder = result
    assert code == 0 and err == "", (code, err)
    answer = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert answer["class"] is None and isinstance(answer["reason"], str) and "\n" not in answer["reason"], answer
    for w in words:
        assert w in answer["reason"], (w, answer["reason"])
    assert _listing(folder) == ["calibration.json"]
    assert json.loads((folder / "calibration.json").read_text()) == answer
    return answer


# ------------------------------------------------------------------ frames no engine can reconstruct
@pytest.fixture(scope="module")
def grey(tmp_path_factory):
    return _write(tmp_path_factory.mktemp("grey"), [torch.full((1, *SIZE), 0.5)] * 8)


@pytest.fixture(scope="module")
def noise(tmp_path_factory):
    g = torch.Generator().manual_seed(0)
    return _write(tmp_path_factory.mktemp("noise"), [torch.rand(1, *SIZE, generator=g) for _ in range(8)])


@pytest.mark.parametrize("method", ["auto", "direct", "multiview"])
def test_uniform_grey_frames_are_cannot_tell_with_no_estimate(calibrate, grey, method):
    answer = _cannot_tell(calibrate(grey, "--method", method))
    assert answer["k2_user"] is None and answer["delta_avg_user_px"] is None and answer["opencv"] is None


def test_uniform_grey_frames_say_they_have_no_texture(calibrate, grey):
    reason = _cannot_tell(calibrate(grey))["reason"]
    assert any(w in reason for w in ("texture", "contrast", "featureless")), reason


def test_noise_is_cannot_tell_no_pair_registered_and_no_reconstruction(calibrate, noise):
    answer = _cannot_tell(calibrate(noise), "too few usable pairs: 0 of at least 4", "not registered")
    assert answer["k2_user"] is None and answer["pairs_used"] == 0
    assert answer["multiview"]["reason"].startswith("the engine could not reconstruct the sequence: 0 of 8 frames")


def test_noise_with_the_multiview_path_alone_is_one_line_naming_the_engine(calibrate, noise):
    _error(calibrate(noise, "--method", "multiview"), "the engine could not reconstruct the sequence",
           "0 of 8 frames registered")


# ------------------------------------------------------------------ unrelated frames
@pytest.fixture(scope="module")
def unrelated(tmp_path_factory):
    """8 frames of 3 scenes, none overlapping another: disjoint windows of each scene."""
    scenes, windows = ("gravel", "grass", "brick"), [(0, 0), (196, 176), (392, 352)]  # 512 x 512 scenes
    frames = []
    for i in range(8):
        y, x = windows[i // 3]
        frames.append(load_scene(scenes[i % 3])[0, :, y : y + SIZE[0], x : x + SIZE[1]])
    return _write(tmp_path_factory.mktemp("unrelated"), frames)


def test_unrelated_frames_are_cannot_tell_no_pair_registered_and_no_reconstruction(calibrate, unrelated):
    answer = _cannot_tell(calibrate(unrelated), "too few usable pairs: 0 of at least 4", "not registered")
    assert answer["k2_user"] is None and answer["pairs_used"] == 0
    assert answer["multiview"]["reason"].startswith("the engine could not reconstruct the sequence: 0 of 8 frames")
    assert answer["planar"]["reason"].startswith("too few matched pairs")


# ------------------------------------------------------------------ one frame, two frames
@pytest.fixture(scope="module")
def pan(tmp_path_factory):
    """Two frames of a pan 5-10 px apart, and two 25 px apart (enough motion for a pair)."""
    near = synthetic_sequence(2, K2, 0.0, size=SIZE, seed=1)[0]
    far = synthetic_sequence(2, K2, 0.0, size=SIZE, seed=1, step_px=(25.0, 25.0))[0]
    root = tmp_path_factory.mktemp("pan")
    return _write(root / "near", near), _write(root / "far", far), _write(root / "one", near[:1])


def test_one_frame_is_one_line_naming_the_count(calibrate, pan):
    _error(calibrate(pan[2]), "at least 2 frames", "got 1")


def test_two_frames_close_together_are_cannot_tell_too_little_motion(calibrate, pan):
    answer = _cannot_tell(calibrate(pan[0]), "too little motion: the camera moved")
    assert answer["frames"] == 2 and answer["k2_user"] is None


def test_two_frames_far_apart_are_cannot_tell_too_few_pairs(calibrate, pan):
    answer = _cannot_tell(calibrate(pan[1]), "too few usable pairs: 1 of at least 4")
    assert answer["delta_avg_user_interval"] == [None, None]  # an estimate, never an interval that reads as one


@pytest.mark.parametrize("folder", [0, 1], ids=["near", "far"])
def test_two_frames_with_the_multiview_path_alone_are_one_line_naming_the_count(calibrate, pan, folder):
    _error(calibrate(pan[folder], "--method", "multiview"), "at least 3 frames, got 2")


# ------------------------------------------------------------------ frames of mixed sizes
@pytest.mark.parametrize("odd", [5, 0], ids=["last", "first"])
def test_mixed_sizes_are_one_line_naming_the_odd_frame(calibrate, tmp_path, odd):
    frames = list(synthetic_sequence(6, K2, 0.0, size=SIZE, seed=1)[0])
    frames[odd] = synthetic_sequence(1, K2, 0.0, size=(128, 160), seed=1)[0][0]
    first, other = ("120 x 160", "128 x 160") if odd else ("128 x 160", "120 x 160")
    named = f"frame_0{odd}" if odd else "frame_01"
    _error(calibrate(_write(tmp_path / "mixed", frames)), "frames must all have one size",
           f"the first is {first}, {named} is {other}")


def test_a_frame_cut_short_in_a_folder_is_one_line_naming_it(calibrate, tmp_path):
    folder = _write(tmp_path / "frames", synthetic_sequence(6, K2, 0.0, size=SIZE, seed=1)[0])
    data = (folder / "frame_03.png").read_bytes()
    (folder / "frame_03.png").write_bytes(data[: len(data) // 2])
    _error(calibrate(folder), "cannot decode image file", "frame_03.png")


# ------------------------------------------------------------------ a truncated video
@pytest.fixture(scope="module")
def video(tmp_path_factory):
    """``video(suffix, fourcc)``: 12 frames of a pan written by OpenCV; its bytes."""
    cv2 = pytest.importorskip("cv2")
    frames = synthetic_sequence(12, K2, 0.0, size=SIZE, seed=2)[0]
    root = tmp_path_factory.mktemp("video")

    def write(suffix, fourcc):
        path = root / f"pan{suffix}"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, SIZE[::-1], isColor=False)
        assert writer.isOpened(), f"OpenCV cannot write {fourcc}"
        for f in frames:
            writer.write(to_uint8(f)[0].numpy())
        writer.release()
        return path.read_bytes()

    return write


@pytest.mark.parametrize("cut", ["half", "1 KB"])
def test_a_truncated_mp4_is_one_line_naming_the_file(calibrate, video, tmp_path, cut):
    data = video(".mp4", "mp4v")  # OpenCV writes the index (moov) last: any cut loses it
    path = tmp_path / "cut.mp4"
    path.write_bytes(data[: len(data) // 2] if cut == "half" else data[:1024])
    _error(calibrate(path), "cut.mp4 is not a video")


def test_a_truncated_avi_that_decodes_in_part_is_one_line_naming_the_cut(calibrate, video, tmp_path):
    data = video(".avi", "MJPG")  # frames first, the index last: the first half still decodes
    path = tmp_path / "cut.avi"
    path.write_bytes(data[: len(data) // 2])
    line = _error(calibrate(path, "--method", "direct"), "cut.avi").replace(str(tmp_path), "TMP")  # the test's name
    assert any(w in line for w in ("truncated", "damaged", "incomplete")), line


def test_a_truncated_mp4_with_its_index_first_is_one_line_naming_the_cut(calibrate, tmp_path):
    av = pytest.importorskip("av")
    path = tmp_path / "cut.mp4"
    with av.open(str(tmp_path / "whole.mp4"), "w", options={"movflags": "faststart"}) as container:
        stream = container.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = SIZE[1], SIZE[0], "yuv420p"
        for f in synthetic_sequence(24, K2, 0.0, size=SIZE, seed=2)[0]:
            frame = av.VideoFrame.from_ndarray(to_uint8(f)[0].numpy(), format="gray").reformat(format="yuv420p")
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    data = (tmp_path / "whole.mp4").read_bytes()
    path.write_bytes(data[: len(data) // 2])
    line = _error(calibrate(path), "cut.mp4").replace(str(tmp_path), "TMP")  # the test's name says "truncated"
    assert any(w in line for w in ("truncated", "damaged", "incomplete")), line


def test_a_truncated_mp4_read_by_opencv_is_one_line_too(video, tmp_path):
    """In a fresh process, as a user runs it: FFmpeg's log level is set at its first use, which here was the writer."""
    data = video(".mp4", "mp4v")
    (tmp_path / "cut.mp4").write_bytes(data[: len(data) // 2])
    run = ("import sys; sys.modules['av'] = None; from lensdist_torch import cli; "  # PyAV missing: OpenCV reads it
           f"sys.exit(cli.main(['calibrate', {str(tmp_path / 'cut.mp4')!r}, '--out', {str(tmp_path / 'out')!r}, "
           "'--json', '--quiet']))")
    done = subprocess.run([sys.executable, "-c", run], capture_output=True, text=True, timeout=120)
    assert "OpenCV" in one_line_usage(done.returncode, done.stderr, "calibrate") and not (tmp_path / "out").exists()
    assert done.stdout == ""


# ------------------------------------------------------------------ the line, without --quiet
def test_an_error_is_the_only_line_on_stderr_without_quiet(tmp_path, capsys):
    frames = list(synthetic_sequence(6, K2, 0.0, size=SIZE, seed=1)[0])
    frames[5] = synthetic_sequence(1, K2, 0.0, size=(128, 160), seed=1)[0][0]
    assert cli.main(["calibrate", str(_write(tmp_path / "mixed", frames)), "--json"]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [err.strip()] and err.startswith("lensdist calibrate: error: frames must"), repr(err)


# ------------------------------------------------------------------ the same in Python
@pytest.mark.parametrize("case", ["one frame", "mixed sizes", "cut mp4", "two frames, multiview alone"])
def test_calibrate_path_raises_the_same_one_line_value_error(tmp_path, video, case):
    frames = synthetic_sequence(3, K2, 0.0, size=SIZE, seed=1)[0]
    method, path = "auto", tmp_path / "frames"
    if case == "one frame":
        _write(path, frames[:1])
        words = ("at least 2 frames", "got 1")
    elif case == "mixed sizes":
        _write(path, [*frames[:2], synthetic_sequence(1, K2, 0.0, size=(128, 160), seed=1)[0][0]])
        words = ("frames must all have one size", "frame_02 is 128 x 160")
    elif case == "cut mp4":
        path = tmp_path / "cut.mp4"
        path.write_bytes(video(".mp4", "mp4v")[:1024])
        words = ("cut.mp4 is not a video",)
    else:
        _write(path, frames[:2])
        method, words = "multiview", ("at least 3 frames, got 2",)
    one_line_error(ValueError, lambda: calibrate_path(path, method=method), *words)
