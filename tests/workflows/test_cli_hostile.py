"""`lensdist` against hostile command lines (issue 19): devices, negative numbers in scientific
notation, stdout that cannot be written, outputs that name an input or lie in an input folder,
numbers out of range.
In-process through ``main([...])``; a subprocess only for a stdout closed at start."""

from __future__ import annotations

import errno
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lensdist_torch import cli
from lensdist_torch.cli import support as cli_support
from lensdist_torch.config import LensdistConfig
from lensdist_torch.workflows.demo import MAX_SCALE_ERROR, scale_error_demo

pytestmark = [pytest.mark.usefixtures("one_thread_module"), pytest.mark.bad_input]
ROOT = Path(__file__).resolve().parents[2]


def usage_error(capsys, *argv, match: tuple[str, ...], prog: str | None = None) -> str:
    """argparse's refusal: status 2 and one stderr line ``lensdist CMD: error: ...`` with ``match``."""
    rc = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.splitlines()
    prog = f"lensdist {argv[0]}" if prog is None else prog
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    for m in match:
        assert m in lines[0], err
    return lines[0]


def one_error(capsys, *argv, match: tuple[str, ...], code: int = 2) -> str:
    """A command's refusal: returned status ``code`` and one stderr line with ``match``."""
    rc = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert rc == code, err
    assert len(lines) == 1 and lines[0].startswith(f"lensdist {argv[0]}: error: "), err
    for m in match:
        assert m in lines[0], err
    return lines[0]


@pytest.fixture
def pair(tmp_path) -> tuple[Path, Path]:
    """Two PNG files (their content is never analysed: the refusals come first)."""
    from kornia.io import write_image

    paths = tmp_path / "a.png", tmp_path / "b.png"
    for i, p in enumerate(paths):
        write_image(str(p), torch.full((3, 32, 48), 40 * (i + 1), dtype=torch.uint8))
    return paths


# ----------------------------------------------------------------------------- 1. --device
#: Every subcommand with --device, with arguments that parse (the refusal is at parsing).
DEVICE_COMMANDS = {
    "analyze": ["analyze", "a.png", "b.png"],
    "evaluate": ["evaluate", "--data", "d", "--selfcal"],
    "reproduce": ["reproduce", "--quick"],
    "calibrate": ["calibrate", "frames"],
    "undistort": ["undistort", "frames", "--k2", "0", "--k4", "0", "--out", "o"],
}


@pytest.mark.parametrize("command", sorted(DEVICE_COMMANDS))
@pytest.mark.parametrize("dev", ["bogus", "CPU", "", "meta", "mps", "cuda:-1", "cuda:x", " cpu"])
def test_device_unknown_is_a_usage_error(capsys, command, dev):
    usage_error(
        capsys,
        *DEVICE_COMMANDS[command],
        "--device",
        dev,
        match=("argument --device", repr(dev), "cpu, cuda or cuda:N"),
    )


@pytest.mark.parametrize("command", ["analyze", "calibrate"])
def test_device_cuda_without_cuda(capsys, monkeypatch, command):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for dev in ("cuda", "cuda:0"):
        usage_error(
            capsys, *DEVICE_COMMANDS[command], "--device", dev, match=("argument --device", "CUDA is not available")
        )


def test_device_index_beyond_the_devices(capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    usage_error(
        capsys,
        "analyze",
        "a",
        "b",
        "--device",
        "cuda:2",
        match=("argument --device", "2 CUDA device(s)", "cuda:0 to cuda:1"),
    )
    parser = cli.build_parser()
    for given, parsed in (("cuda", "cuda"), ("cuda:1", "cuda:1"), ("cuda:01", "cuda:1"), ("cpu", "cpu")):
        assert parser.parse_args(["analyze", "a", "b", "--device", given]).device == parsed
    assert parser.parse_args(["analyze", "a", "b"]).device == "cpu"


def test_usage_errors_are_one_line(capsys):
    """argparse's own refusals (an unknown option, a bad choice) are one line, not usage + error."""
    usage_error(capsys, "analyze", "a", "b", "--bogus", match=("unrecognized arguments: --bogus",))
    usage_error(capsys, "analyze", "a", "b", "--method", "nope", match=("argument --method", "invalid choice"))


# ----------------------------------------------------------------------------- 2. negative numbers
@pytest.mark.parametrize("text", ["-1e-3", "-1.5E-9", "-.5", "-3", "-2.", "-1e+2"])
def test_negative_number_is_a_value_not_an_option(text):
    """`--k2 -1e-3` as `--k2=-1e-3` (argparse alone took '-1e-3' for an option)."""
    args = cli.build_parser().parse_args(["undistort", "frames", "--k2", text, "--k4", text, "--out", "o"])
    assert args.k2 == float(text) and args.k4 == float(text)


@pytest.mark.parametrize("text", ["-1e-3", "-1.5E-9", "-.5", "-3"])
def test_negative_number_reaches_the_options_type(capsys, text):
    """A negative value reaches the option's check, which names what it wants."""
    usage_error(
        capsys,
        "calibrate",
        "frames",
        "--focal",
        text,
        match=("argument --focal", "expected a positive number", repr(text)),
    )
    usage_error(capsys, "demo", "--scale-error", text, match=("argument --scale-error", "from 0 to", repr(text)))


def test_an_option_is_still_an_option():
    """Only numbers are taken as values: an option after --k2 is still missing its value."""
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["undistort", "frames", "--k2", "--k4", "0", "--out", "o"])


# ----------------------------------------------------------------------------- 3. stdout
class _Stream(io.StringIO):
    """A stdout that fails: on flush (a buffered write to a full disk) or on write."""

    def __init__(self, exc: OSError, on: str):
        super().__init__()
        self.exc, self.on = exc, on

    def write(self, text):
        if self.on == "write":
            raise self.exc
        return super().write(text)

    def flush(self):
        if self.on == "flush" and self.getvalue():
            raise self.exc


def test_stdout_closed_at_start_fails_loudly(tmp_path):
    """`lensdist demo --json >&-`: exit 2 and one line, before any work (was: exit 0, result lost)."""
    cmd = f"exec {sys.executable} -m lensdist_torch.cli demo --json --out out >&-"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    res = subprocess.run(["bash", "-c", cmd], stderr=subprocess.PIPE, text=True, timeout=300, env=env, cwd=tmp_path)
    lines = res.stderr.splitlines()
    assert res.returncode == 2, res.stderr
    assert len(lines) == 1 and lines[0].startswith("lensdist demo: error: stdout is closed"), res.stderr
    assert list(tmp_path.iterdir()) == []  # refused before any work


def test_stdout_none_in_process(capsys, monkeypatch, tmp_path):
    monkeypatch.setattr(sys, "stdout", None)
    rc = cli.main(["demo", "--json", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.splitlines() == [
        "lensdist demo: error: stdout is closed, the result would be lost (redirect it, e.g. > /dev/null)"
    ]
    assert not (tmp_path / "demo.png").exists()  # nothing done


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EBADF, errno.EIO])
def test_stdout_write_fails_at_the_last_flush(capsys, monkeypatch, tmp_path, code):
    """A buffered result that cannot be flushed (disk full, EBADF): exit 2, one line."""
    stream = _Stream(OSError(code, os.strerror(code)), "flush")
    monkeypatch.setattr(sys, "stdout", stream)
    rc = cli.main(["demo", "--json", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.splitlines() == [f"lensdist demo: error: cannot write the result to stdout: {os.strerror(code)}"]


def test_stdout_write_fails_on_write(capsys, monkeypatch, tmp_path):
    monkeypatch.setattr(sys, "stdout", _Stream(OSError(errno.ENOSPC, "No space left on device"), "write"))
    rc = cli.main(["demo", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.splitlines() == [
        "lensdist demo: error: cannot write the result to stdout: No space left on device"
    ]


def test_broken_pipe_ends_quietly(capsys, monkeypatch, tmp_path):
    """`lensdist demo --json | head -c0`: exit 1, nothing on stderr (Python's convention)."""
    monkeypatch.setattr(sys, "stdout", _Stream(BrokenPipeError(errno.EPIPE, "Broken pipe"), "flush"))
    rc = cli.main(["demo", "--json", "--out", str(tmp_path)])
    assert rc == 1 and capsys.readouterr().err == ""


# ----------------------------------------------------------------------------- 4. outputs = inputs
def test_save_map_onto_an_input_image(capsys, pair, tmp_path):
    a, b = pair
    before = a.read_bytes(), b.read_bytes()
    link = tmp_path / "hard.png"
    os.link(a, link)
    sym = tmp_path / "sym.png"
    sym.symlink_to(b)
    for target, name in ((a, "img1"), (b, "img2"), (link, "img1"), (sym, "img2"), (tmp_path / "." / "a.png", "img1")):
        one_error(
            capsys,
            "analyze",
            a,
            b,
            "--save-map",
            target,
            match=("--save-map", f"the input {name}", "refusing to overwrite"),
        )
    assert (a.read_bytes(), b.read_bytes()) == before


def test_save_map_onto_the_config_or_checkpoint(capsys, pair, tmp_path):
    a, b = pair
    cfg = tmp_path / "cfg.png"  # a TOML file with a figure's suffix
    cfg.write_text("[quality]\ntheta_e = 0.5\n")
    one_error(capsys, "analyze", a, b, "--config", cfg, "--save-map", cfg, match=("--save-map", "the input --config"))
    assert cfg.read_text() == "[quality]\ntheta_e = 0.5\n"


def test_demo_out_writes_onto_its_config(capsys, tmp_path):
    cfg = tmp_path / "demo.png"
    cfg.write_text("[quality]\ntheta_e = 0.5\n")
    one_error(capsys, "demo", "--config", cfg, "--out", tmp_path, match=("--out would overwrite", "the input --config"))
    assert cfg.read_text() == "[quality]\ntheta_e = 0.5\n"


def test_evaluate_out_is_the_data(capsys, tmp_path):
    (tmp_path / "manifest.json").write_text("{}")
    one_error(
        capsys, "evaluate", "--data", tmp_path, "--selfcal", "--out", tmp_path, match=("--out", "the input --data")
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["manifest.json"]


def test_evaluate_report_onto_a_checkpoint(capsys, tmp_path):
    ck = tmp_path / "evaluate.json"
    ck.write_text("not really a checkpoint")
    one_error(capsys, "evaluate", "--data", tmp_path / "d", "--checkpoint", ck, "--out", tmp_path,
              match=("--out would overwrite", "the input --checkpoint"))
    assert ck.read_text() == "not really a checkpoint"


def test_reproduce_onto_its_config(capsys, tmp_path):
    cfg = tmp_path / "calibration.toml"
    cfg.write_text("[quality]\ntheta_e = 0.5\n")
    one_error(
        capsys, "reproduce", "--config", cfg, "--out", tmp_path, match=("--out would overwrite", "the input --config")
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.toml"]


def test_generate_into_the_scenes_folder(capsys, tmp_path):
    for flag in ("--scenes", "--sequence"):
        one_error(capsys, "generate", flag, tmp_path, "--out", tmp_path, match=("--out", f"the input {flag}"))
    assert list(tmp_path.iterdir()) == []


def test_calibrate_out_is_the_input_folder(capsys, tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    one_error(capsys, "calibrate", frames, "--out", frames, match=("--out", "the input path"))
    assert list(frames.iterdir()) == []


@pytest.fixture
def data_folder(tmp_path) -> Path:
    """A folder laid out as `lensdist generate` writes one (contents never read: the refusal comes first)."""
    data = tmp_path / "mid"
    (data / "train").mkdir(parents=True)
    (data / "manifest.json").write_text("{}")
    (data / "train" / "shard-00000.pt").write_bytes(b"shard bytes")
    return data


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_train_out_inside_the_data_folder(capsys, monkeypatch, data_folder, tmp_path):
    """`train --out` in the --data folder (a shard, the manifest, a new file, a new subfolder, the
    folder's own name through `..` or a symlinked alias): one line naming --out, before any fitting."""
    import lensdist_torch.data.shards as shards

    monkeypatch.setattr(shards, "load_set", lambda *a, **k: pytest.fail("train read its data before refusing --out"))
    before = _tree(data_folder)
    alias = tmp_path / "alias"
    alias.symlink_to(data_folder, target_is_directory=True)
    link = tmp_path / "link.pt"
    link.symlink_to(data_folder / "train" / "shard-00000.pt")
    hard = tmp_path / "hard.pt"
    os.link(data_folder / "train" / "shard-00000.pt", hard)
    targets = [data_folder / "train" / "shard-00000.pt", data_folder / "new.pt", data_folder / "sub" / "new.pt",
               data_folder / "train" / ".." / "x.pt", alias / "x.pt", link, hard]
    for out in targets:
        one_error(capsys, "train", "--data", data_folder, "--out", out,
                  match=(f"--out {out} is inside the input --data folder {data_folder}", "refusing to write there"))
    assert _tree(data_folder) == before and link.is_symlink() and hard.read_bytes() == b"shard bytes"


def test_train_out_is_its_config(capsys, monkeypatch, data_folder, tmp_path):
    import lensdist_torch.data.shards as shards

    monkeypatch.setattr(shards, "load_set", lambda *a, **k: pytest.fail("train read its data before refusing --out"))
    cfg = tmp_path / "cfg.pt"  # a TOML file with a checkpoint's suffix
    cfg.write_text("[quality]\ntheta_e = 0.5\n")
    sym = tmp_path / "sym.pt"
    sym.symlink_to(cfg)
    for out in (cfg, sym):
        one_error(capsys, "train", "--data", data_folder, "--config", cfg, "--out", out,
                  match=(f"--out {out} is the input --config", "refusing to overwrite an input"))
    assert cfg.read_text() == "[quality]\ntheta_e = 0.5\n"
    one_error(
        capsys, "train", "--data", data_folder, "--out", data_folder, match=("--out must be a file path", "directory")
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.pt", "mid", "sym.pt"]


def test_refuse_inside_api(tmp_path):
    from lensdist_torch.core.outputs import refuse_inside

    data = tmp_path / "data"
    data.mkdir()
    (data / "a.pt").write_bytes(b"x")
    for out in (data / "a.pt", data / "b.pt", data / "s" / "b.pt", tmp_path / "." / "data" / "b.pt"):
        with pytest.raises(ValueError, match="^--out .* is inside the input --data folder"):
            refuse_inside(out, "--out", data, "--data")
    # outside: a sibling whose name starts with the folder's, the parent, no folder given
    for out, folder in ((tmp_path / "data2" / "b.pt", data), (tmp_path / "b.pt", data), (data / "b.pt", None)):
        refuse_inside(out, "--out", folder, "--data")


def test_refuse_inputs_api(tmp_path):
    from lensdist_torch.core.outputs import check_output_dir, check_output_file

    a = tmp_path / "a.png"
    a.write_bytes(b"x")
    with pytest.raises(ValueError, match="--map .* is the input img"):
        check_output_file(a, "--map", suffixes=(".png",), inputs={"img": [tmp_path / "other.png", a]})
    assert (
        check_output_file(tmp_path / "b.png", "--map", suffixes=(".png",), inputs={"img": a, "cfg": None})
        == tmp_path / "b.png"
    )
    with pytest.raises(ValueError, match="would overwrite"):
        check_output_dir(tmp_path, "--out", inputs={"img": str(a)}, writes=["a.png"])
    assert check_output_dir(tmp_path / "sub", "--out", inputs={"img": a}, writes=["a.png"]) == tmp_path / "sub"


# ----------------------------------------------------------------------------- 5. numbers
@pytest.mark.parametrize("value", ["-0.5", "1e6", "0.11", "nan", "inf", "-inf", "NaN", "abc"])
def test_demo_scale_error_range(capsys, value):
    usage_error(
        capsys,
        "demo",
        "--scale-error",
        value,
        match=("argument --scale-error", f"from 0 to {MAX_SCALE_ERROR:g}", repr(value)),
    )


def test_demo_scale_error_api_and_help(capsys):
    for bad in (-0.5, 1e6, float("nan"), True, "0.01"):
        with pytest.raises(ValueError, match="scale_error must be a number from 0 to"):
            scale_error_demo(LensdistConfig(), scale_error=bad)
    with pytest.raises(SystemExit):
        cli.main(["demo", "--help"])
    assert f"from 0 to {MAX_SCALE_ERROR:g}" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, option",
    [
        (["generate", "--out", "o", "--workers", "0"], "--workers"),
        (["generate", "--out", "o", "--workers", "-2"], "--workers"),
        (["generate", "--out", "o", "--batch-size", "0"], "--batch-size"),
        (["generate", "--out", "o", "--limit", "-1"], "--limit"),
        (["generate", "--out", "o", "--limit", "0"], "--limit"),
        (["generate", "--out", "o", "--limit", "1.5"], "--limit"),
        (["train", "--data", "d", "--out", "o.pt", "--eigenvectors", "0"], "--eigenvectors"),
        (["reproduce", "--workers", "-1"], "--workers"),
        (["reproduce", "--batch-size", "0"], "--batch-size"),
        (["calibrate", "f", "--max-frames", "0"], "--max-frames"),
        (["calibrate", "f", "--focal", "0"], "--focal"),
        (["calibrate", "f", "--focal", "nan"], "--focal"),
        (["calibrate", "f", "--focal", "inf"], "--focal"),
    ],
)
def test_counts_and_sizes(capsys, argv, option):
    usage_error(capsys, *argv, match=(f"argument {option}", "expected a positive"))


def test_number_types():
    assert cli_support.positive_int("3") == 3 and cli_support.positive_float("1e-3") == 1e-3
    assert cli_support.finite_float("-1.5E-9") == -1.5e-9
    assert cli_support.float_in(0, 0.1)("0.1") == 0.1
    for f, text in (
        (cli_support.finite_float, "nan"),
        (cli_support.finite_float, "-inf"),
        (cli_support.positive_float, "-0.0"),
    ):
        with pytest.raises(Exception, match="expected"):
            f(text)
