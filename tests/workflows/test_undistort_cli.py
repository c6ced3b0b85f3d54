"""``lensdist undistort`` and lensdist_torch.workflows.undistort on hostile inputs (issue 19): folding
coefficients, two inputs with one name, 16-bit frames, numbers read from a calibration file, and
outputs that would destroy a file."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from one_line import one_line_error, one_line_usage

from lensdist_torch.cli import main
from lensdist_torch.core.png import encode_png
from lensdist_torch.workflows.undistort import undistort_path

SIZE = (240, 320)


def _image(seed: int, size=SIZE, channels: int = 1, bits: int = 8) -> np.ndarray:
    """A smooth ramp plus noise, (H, W) or (H, W, 3), uint8 or uint16 (many levels at 16 bits)."""
    rng = np.random.default_rng(seed)
    h, w = size
    ramp = (np.arange(h)[:, None] / h + np.arange(w)[None, :] / w) / 2
    x = np.clip(ramp[..., None] * np.array([1.0, 0.8, 0.6][:channels]) + rng.normal(0, 0.01, (h, w, channels)), 0, 1)
    top = 65535 if bits == 16 else 255
    x = np.round(x * top).astype(np.uint16 if bits == 16 else np.uint8)
    return x[..., 0] if channels == 1 else x


def _frames(folder, names=("frame_00.png", "frame_01.png"), **kwargs):
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), _image(i, **kwargs))
    return folder


def _run(capsys, *argv):
    code = main(["undistort", *map(str, argv), "--quiet"])
    out, err = capsys.readouterr()
    return code, out, err.strip()




# ------------------------------------------------------------------ 1. coefficients that fold
@pytest.mark.bad_input
@pytest.mark.parametrize("coefficients", [["--k2=-1e-3", "--k4", "0"], ["--k2=-1e-4", "--k4=-1e-9"]])
def test_coefficients_that_fold_inside_the_frame_are_refused(tmp_path, capsys, coefficients):
    # eq. 4 folds 18.3 px and 57 px from the centre of 240 x 320 frames (119.5 px to the nearest
    # edge); before the fix: exit 0 and 17-20 k pixels sampled from mirrored positions, marked valid
    folder = _frames(tmp_path / "frames")
    code, _, err = _run(capsys, folder, *coefficients, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert "--k2/--k4" in err and "fold" in err and "240 x 320" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.bad_input
def test_folding_coefficients_from_a_file_name_the_file(tmp_path, capsys):
    folder = _frames(tmp_path / "frames")
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"k2_user": -1e-3, "k4_user": 0.0, "image_size": list(SIZE), "class": "4"}))
    code, _, err = _run(capsys, folder, "--from", cal, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert str(cal) in err and "k2_user" in err and "fold" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.bad_input
def test_coefficients_that_stretch_the_frame_beyond_any_lens_are_refused(tmp_path, capsys):
    # the re-audit's case: --k2=1e-3 at 320 x 424 gave exit 0 and a 71-fold zoom on the centre;
    # 1 + k2 r^2 at the farthest corner (r^2 = 211.5^2 + 159.5^2 = 70172.5) is 71.2
    folder = _frames(tmp_path / "frames", names=("a.png",), size=(320, 424))
    code, _, err = _run(capsys, folder, "--k2=1e-3", "--k4", "0", "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert "--k2/--k4" in err and "k2 = 0.001, k4 = 0" in err and "stretch the 320 x 424 frames 71.2-fold" in err
    assert "r = 264.9 px, the farthest corner" in err and "expected at most 10" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.bad_input
def test_a_stretch_peaking_inside_the_frame_is_refused(tmp_path):
    # k4 < 0: 1 + k2 s + k4 s^2 peaks at s = r^2 = 5e4, 1 + 50 - 25 = 26, though the corner gives 1 + 70.2 - 49.2 = 22;
    # it does not fold before the nearest edge (159.5 px)
    folder = _frames(tmp_path / "frames", names=("a.png",), size=(320, 424))
    with pytest.raises(
        ValueError, match=r"k2 = 0.001, k4 = -1e-08 stretch the 320 x 424 frames 26-fold .*r = 223.6 px, inside"
    ):
        undistort_path(folder, tmp_path / "out", k2=1e-3, k4=-1e-8)


@pytest.mark.bad_input
def test_a_stretching_calibration_file_is_refused_naming_it(tmp_path, capsys):
    folder = _frames(tmp_path / "frames")
    cal = tmp_path / "calibration.json"
    cal.write_text(json.dumps({"k2_user": 1e-3, "k4_user": 0.0, "image_size": list(SIZE), "class": "4"}))
    code, _, err = _run(capsys, folder, "--from", cal, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")  # 240 x 320: r^2 = 119.5^2 + 159.5^2 = 39720.5 at the corner: 40.7
    assert str(cal) in err and "k2_user" in err and "40.7-fold" in err and "expected at most 10" in err
    assert not (tmp_path / "out").exists()


def test_a_wide_angle_lens_within_the_bound_is_undistorted(tmp_path, capsys):
    # eq. 4 fitted to the GoPro HERO4's wide calibration (k2 = 6.37e-7, k4 = 1.763e-12 at 1280 x 960), here at
    # a quarter of that size (k2 x 16, k4 x 256): a stretch of 2.13 at the corner, accepted
    folder = _frames(tmp_path / "frames", names=("a.png",))
    code, out, err = _run(
        capsys, folder, f"--k2={6.37e-7 * 16!r}", f"--k4={1.763e-12 * 256!r}", "--out", tmp_path / "out"
    )
    assert code == 0 and "1 frames undistorted" in out, err
    mask = cv2.imread(str(tmp_path / "out" / "masks" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert (mask == 255).all()  # barrel: every ideal pixel samples inside the frame


def test_a_fold_in_the_corners_is_masked_there(tmp_path, capsys):
    # eq. 4 folds at 160 px (k2 = -1 / (3 160^2)): beyond the nearest edge (119.5 px), inside the
    # half diagonal (199.7 px). Accepted; no ideal pixel beyond rho_max = 2/3 160 px has a preimage
    folder = _frames(tmp_path / "frames", names=("a.png",))
    k2 = -1 / (3 * 160.0**2)
    code, out, _ = _run(capsys, folder, f"--k2={k2!r}", "--k4", "0", "--out", tmp_path / "out")
    assert code == 0 and "1 frames undistorted" in out
    mask = cv2.imread(str(tmp_path / "out" / "masks" / "a.png"), cv2.IMREAD_UNCHANGED)
    y, x = np.mgrid[: SIZE[0], : SIZE[1]]
    rho = np.hypot(x - (SIZE[1] - 1) / 2, y - (SIZE[0] - 1) / 2)
    assert set(np.unique(mask)) == {0, 255}
    assert (mask[rho > 160 * 2 / 3 + 0.01] == 0).all()
    # below rho_max: the monotone branch's preimage (numpy, by interpolation), kept where it is inside
    r = np.linspace(0, 160, 160_001)
    factor = np.interp(rho, r * (1 + k2 * r**2), r) / np.maximum(rho, 1e-9)
    xs, ys = (SIZE[1] - 1) / 2 + (x - (SIZE[1] - 1) / 2) * factor, (SIZE[0] - 1) / 2 + (y - (SIZE[0] - 1) / 2) * factor
    inside = (xs >= 0.01) & (xs <= SIZE[1] - 1.01) & (ys >= 0.01) & (ys <= SIZE[0] - 1.01)
    keep = inside & (rho < 160 * 2 / 3 - 0.5)
    assert (mask[keep] == 255).all() and keep.sum() > 0.4 * mask.size


# ------------------------------------------------------------------ 2. two inputs, one output name
@pytest.mark.bad_input
def test_two_inputs_with_one_stem_are_refused_before_writing(tmp_path, capsys):
    # before the fix: "4 frames undistorted", 3 on disk (frame_01.jpg overwrote frame_01.png's output)
    folder = _frames(tmp_path / "frames", names=("frame_00.png", "frame_01.png", "frame_01.jpg", "frame_02.png"))
    code, _, err = _run(capsys, folder, "--k2", "1e-6", "--k4", "0", "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert "frame_01.jpg" in err and "frame_01.png" in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="would both be written as frame_01.png"):
        undistort_path(folder, tmp_path / "out", k2=1e-6, k4=0.0)


# ------------------------------------------------------------------ 3. 16-bit frames
def test_png_writer_writes_16_bits_exactly():
    for c in (1, 3):
        img = torch.randint(0, 65536, (c, 37, 53), dtype=torch.int32).to(torch.uint16)
        dec = cv2.imdecode(np.frombuffer(encode_png(img), np.uint8), cv2.IMREAD_UNCHANGED)
        assert dec.dtype == np.uint16
        dec = dec[None] if c == 1 else dec[..., ::-1].transpose(2, 0, 1)  # BGR -> RGB, channels first
        assert np.array_equal(dec, img.to(torch.int32).numpy())


@pytest.mark.bad_input
@pytest.mark.parametrize("channels", [1, 3])
def test_16_bit_frames_stay_16_bit(tmp_path, capsys, channels):
    # before the fix: written as 8-bit, 31 k levels rounded to at most 256
    folder = _frames(tmp_path / "frames", names=("a.png", "b.png"), channels=channels, bits=16)
    code, out, _ = _run(capsys, folder, "--k2", "0", "--k4", "0", "--out", tmp_path / "same")
    assert code == 0 and "16-bit PNG" in out
    for i, name in enumerate(("a.png", "b.png")):
        src, got = (
            _image(i, channels=channels, bits=16),
            cv2.imread(str(tmp_path / "same" / name), cv2.IMREAD_UNCHANGED),
        )
        assert got.dtype == np.uint16 and got.shape == src.shape
        assert np.abs(got.astype(np.int64) - src).max() <= 2  # the identity warp keeps every level
        assert len(np.unique(got)) > 5000
    code, _, _ = _run(capsys, folder, "--k2", "2e-6", "--k4", "0", "--out", tmp_path / "warped")
    got = cv2.imread(str(tmp_path / "warped" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert code == 0 and got.dtype == np.uint16 and len(np.unique(got)) > 5000
    assert cv2.imread(str(tmp_path / "warped" / "masks" / "a.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint8


def test_8_bit_frames_stay_8_bit(tmp_path, capsys):
    folder = _frames(tmp_path / "frames", names=("a.png", "b.jpg"))
    code, out, _ = _run(capsys, folder, "--k2", "2e-6", "--k4", "0", "--out", tmp_path / "out")
    assert code == 0 and "8-bit PNG" in out and "16-bit" not in out
    assert all(
        cv2.imread(str(tmp_path / "out" / n), cv2.IMREAD_UNCHANGED).dtype == np.uint8 for n in ("a.png", "b.png")
    )


# ------------------------------------------------------------------ 4. numbers read from --from
_GOOD = {"k2_user": 1e-6, "k4_user": 0.0, "image_size": list(SIZE), "class": "1"}


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "text,field",
    [
        (json.dumps({**_GOOD, "k2_user": True}), "'k2_user'"),  # before the fix: read as 1.0
        (json.dumps({**_GOOD, "k4_user": False}), "'k4_user'"),
        (json.dumps({**_GOOD, "k4_user": "1e-9"}), "'k4_user'"),
        (json.dumps({**_GOOD, "k2_user": [1e-6]}), "'k2_user'"),
        (json.dumps(_GOOD).replace("1e-06", "NaN"), "'k2_user'"),
        (json.dumps(_GOOD).replace("1e-06", "1e400"), "'k2_user'"),
        (json.dumps({**_GOOD, "k2_user": None}), "'k2_user' and 'k4_user'"),
        (json.dumps({**_GOOD, "image_size": [0, 0]}), "'image_size'"),  # before the fix: exit 1, internal error
        (json.dumps({**_GOOD, "image_size": [-240, -320]}), "'image_size'"),
        (json.dumps({**_GOOD, "image_size": [240]}), "'image_size'"),
        (json.dumps({**_GOOD, "image_size": [True, 320]}), "'image_size'"),
        (json.dumps({**_GOOD, "image_size": [240.5, 320]}), "'image_size'"),
        (json.dumps({**_GOOD, "image_size": "240 x 320"}), "'image_size'"),
        (json.dumps({"k2_user": 1e-6, "k4_user": 0.0}), "'image_size'"),
        (json.dumps([1e-6, 0.0]), "not a JSON object"),
        ("{\"k2_user\": 1e-6,", "not a calibration"),
    ],
)
def test_every_number_read_from_the_calibration_is_checked(tmp_path, capsys, text, field):
    folder = _frames(tmp_path / "frames", names=("a.png",))
    cal = tmp_path / "calibration.json"
    cal.write_text(text)
    code, _, err = _run(capsys, folder, "--from", cal, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert str(cal) in err and field in err
    assert not (tmp_path / "out").exists()


@pytest.mark.bad_input
@pytest.mark.parametrize("k2,k4", [(True, 0.0), (1e-6, "0"), (1e-6, float("inf"))])
def test_coefficients_given_in_python_are_real_numbers(tmp_path, k2, k4):
    folder = _frames(tmp_path / "frames", names=("a.png",))
    with pytest.raises(ValueError, match=r"`k[24]` must be a finite number") as err:
        undistort_path(folder, tmp_path / "out", k2=k2, k4=k4)
    assert "\n" not in str(err.value) and not (tmp_path / "out").exists()


@pytest.mark.bad_input
@pytest.mark.parametrize(
    "option,value,wants",
    [
        ("--k2", "nan", "a finite number"),  # before: a one-line error from the workflow, not the option's
        ("--k2", "inf", "a finite number"),
        ("--k2", "-inf", "a finite number"),
        ("--k4", "NaN", "a finite number"),
        ("--k4", "Infinity", "a finite number"),
        ("--k4", "1e400", "a finite number"),
        ("--k2", "abc", "a finite number"),
        ("--max-frames", "0", "a positive integer"),  # before: "max_frames must be a positive int or None"
        ("--max-frames", "-3", "a positive integer"),
        ("--max-frames", "2.5", "a positive integer"),
    ],
)
def test_numeric_options_are_refused_by_their_type(tmp_path, capsys, option, value, wants):
    """Every numeric option of undistort refuses nan, inf, 0 and negatives where they mean nothing:
    argparse's one line naming the option and the value, before anything is read or written."""
    folder = _frames(tmp_path / "frames")
    frames = {p.name: p.read_bytes() for p in folder.iterdir()}
    values = {"--k2": "1e-6", "--k4": "0", "--max-frames": "1", option: value}
    argv = [a for name, v in values.items() for a in (name, v)]
    code, _, err = _run(capsys, folder, *argv, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert err.startswith(f"lensdist undistort: error: argument {option}: expected {wants}, got {value!r}"), err
    assert not (tmp_path / "out").exists() and {p.name: p.read_bytes() for p in folder.iterdir()} == frames


@pytest.mark.bad_input
def test_negative_coefficients_and_counts_that_mean_something_still_parse():
    from lensdist_torch.cli import build_parser

    args = build_parser().parse_args(
        ["undistort", "f", "--k2", "-1e-7", "--k4", "-0", "--max-frames", "1", "--out", "o"]
    )
    assert (args.k2, args.k4, args.max_frames) == (-1e-7, 0.0, 1)
    assert build_parser().parse_args(["undistort", "f", "--k2", "0", "--k4", "0", "--out", "o"]).max_frames is None


# ------------------------------------------------------------------ 5. nothing destroyed
@pytest.mark.bad_input
def test_an_existing_file_of_an_output_name_is_not_overwritten(tmp_path, capsys):
    # the audit's `lensdist undistort par/frames --out par` over an unrelated par/frame_00.png
    par = tmp_path / "par"
    folder = _frames(par / "frames")
    mine = par / "frame_00.png"
    mine.write_bytes(b"not yours")
    before = sorted(p.relative_to(par) for p in par.rglob("*"))
    code, _, err = _run(capsys, folder, "--k2", "1e-6", "--k4", "0", "--out", par)
    one_line_usage(code, err, "undistort")
    assert str(mine) in err and "--overwrite" in err
    assert mine.read_bytes() == b"not yours" and sorted(p.relative_to(par) for p in par.rglob("*")) == before
    code, out, _ = _run(capsys, folder, "--k2", "1e-6", "--k4", "0", "--out", par, "--overwrite")
    assert code == 0 and "2 frames undistorted" in out
    assert cv2.imread(str(mine), cv2.IMREAD_UNCHANGED).shape == SIZE and (par / "masks" / "frame_01.png").is_file()


@pytest.mark.bad_input
def test_errors_name_flags_on_the_command_line_and_parameters_in_python(tmp_path, capsys):
    # the same refusal: the command line's words on the command line, Python's in Python
    par = tmp_path / "par"
    folder = _frames(par / "frames")
    (par / "frame_00.png").write_bytes(b"not yours")
    code, _, err = _run(capsys, folder, "--k2", "1e-6", "--k4", "0", "--out", par)
    one_line_usage(code, err, "undistort")
    assert "choose an empty --out or pass --overwrite" in err
    assert "out_dir" not in err and "overwrite=True" not in err and "`" not in err
    with pytest.raises(ValueError, match="choose an empty `out_dir` or pass `overwrite=True`") as caught:
        undistort_path(folder, par, k2=1e-6, k4=0.0)
    assert "--" not in str(caught.value)
    code, _, err = _run(capsys, folder, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert "give --k2 or --k4 (the other is 0), or --from" in err
    # --k2 alone is a lens (k4 = 0): beside --from the error names what was typed, not a missing --k4
    (tmp_path / "cal.json").write_text("{}")
    code, _, err = _run(capsys, folder, "--k2", "1e-6", "--from", tmp_path / "cal.json", "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert err == "lensdist undistort: error: give the coefficients (--k2, --k4) or --from, not both"


@pytest.mark.bad_input
def test_an_input_is_never_overwritten_even_with_overwrite(tmp_path, capsys):
    # out/masks is the input folder: the masks would replace the frames
    par = tmp_path / "par"
    folder = _frames(par / "masks")
    frames = {p.name: p.read_bytes() for p in folder.iterdir()}
    code, _, err = _run(capsys, folder, "--k2", "1e-6", "--k4", "0", "--out", par, "--overwrite")
    one_line_usage(code, err, "undistort")
    assert "is one of the inputs" in err
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == frames
    assert sorted(p.name for p in par.iterdir()) == ["masks"]
    # the calibration file is an input too
    other = _frames(tmp_path / "frames")
    cal = tmp_path / "out" / "frame_00.png"
    cal.parent.mkdir()
    cal.write_text(json.dumps(_GOOD))
    with pytest.raises(ValueError, match="is one of the inputs"):
        undistort_path(other, tmp_path / "out", from_json=cal, overwrite=True)
    assert json.loads(cal.read_text()) == _GOOD


@pytest.mark.bad_input
def test_a_video_does_not_overwrite_earlier_frames(tmp_path, fake_pyav):
    fake_pyav([lambda format: np.zeros((*SIZE, 3), np.uint8)] * 2)  # two frames, whatever the format
    (tmp_path / "clip.mp4").write_bytes(b"")
    out = tmp_path / "out"
    (out / "masks").mkdir(parents=True)
    (out / "masks" / "frame_000001.png").write_bytes(b"earlier")
    video = tmp_path / "clip.mp4"
    one_line_error(ValueError, lambda: undistort_path(video, out, k2=1e-6, k4=0.0), "frame_000001.png exists")
    assert (out / "masks" / "frame_000001.png").read_bytes() == b"earlier"
    assert sorted(p.name for p in out.rglob("*")) == ["frame_000001.png", "masks"]
    assert undistort_path(tmp_path / "clip.mp4", out, k2=1e-6, k4=0.0, overwrite=True)["frames"] == 2


@pytest.mark.bad_input
def test_a_deeply_nested_calibration_file_is_a_one_line_error(tmp_path, capsys):
    # the third issue-19 audit: 100 000 nested '[' made json.loads raise RecursionError ("internal error", exit 1)
    folder = _frames(tmp_path / "frames")
    cal = tmp_path / "deep.json"
    cal.write_text("[" * 100_000)
    code, _, err = _run(capsys, folder, "--from", cal, "--out", tmp_path / "out")
    one_line_usage(code, err, "undistort")
    assert str(cal) in err and "nested too deeply" in err
    assert not (tmp_path / "out").exists()
