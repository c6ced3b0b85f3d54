"""`lensdist`: every failure is one stderr line and a non-zero status (never a traceback unless
--debug), output paths are validated before the work, results come first, JSON is strict, and
cached checkpoints follow their files. In-process through ``main([...])`` (fast)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from kornia.io import write_image

import lensdist_torch.workflows.analyze as analyze_mod
import lensdist_torch.workflows.prepare as prepare_mod
from lensdist_torch import cli
from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.cli import commands
from lensdist_torch.config import ClassifierConfig, LensdistConfig
from lensdist_torch.core.images import load_scene
from lensdist_torch.selfcal.fit import SelfCalInfo
from lensdist_torch.workflows.reports import dumps_strict, write_report

pytestmark = pytest.mark.usefixtures("one_thread_module")
bad_input = pytest.mark.bad_input


def _strict(text: str):
    """json.loads that refuses NaN and infinities, as strict parsers do."""

    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def run(capsys, *argv) -> tuple[int, str, str]:
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error(capsys, *argv, match: str, code: int = 2) -> str:
    """Run; expect exit ``code`` and exactly one stderr line containing ``match``."""
    rc, _, err = run(capsys, *argv)
    lines = err.splitlines()
    assert rc == code, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"lensdist {argv[0]}: "), err
    assert match in lines[0], err
    return lines[0]


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> tuple[Path, Path]:
    d = tmp_path_factory.mktemp("pair")
    s = load_scene("gravel")[0, 0]
    for name, img in (("a.png", s[10:330, 20:444]), ("b.png", s[30:350, 22:446])):
        write_image(str(d / name), (img.clamp(0, 1) * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous())
    return d / "a.png", d / "b.png"


def _classifier(metric="delta_avg", n=2, seed=0) -> EigenSpaceClassifier:
    """A small classifier at the default analysis size (2120 features), fitted on noise."""
    g = torch.Generator().manual_seed(seed)
    cfg = LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=n, metric=metric))
    x = torch.rand(40, 2120, generator=g)
    return EigenSpaceClassifier(2120, cfg).fit(x, torch.arange(40) % 4, torch.rand(40, generator=g) * 10)


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ckpt")
    paths = {m: d / f"{m}.pt" for m in ("delta_avg", "delta_max")}
    for m, p in paths.items():
        _classifier(m).save(p)
    return paths


def _crafted(tmp_path, base: Path, name: str, **changes) -> Path:
    raw = torch.load(base, weights_only=True)
    for key, value in changes.items():
        if key in raw["state_dict"]:
            raw["state_dict"][key] = value
        elif value is None:
            raw.pop(key)
        else:
            raw[key] = value
    path = tmp_path / name
    torch.save(_resigned(raw), path)
    return path


def _resigned(raw: dict) -> dict:
    """``raw`` with its content digest recomputed, as a tamperer who knows the format would."""
    from lensdist_torch.core.storage import DIGEST_KEY, content_digest

    raw = {k: v for k, v in raw.items() if k != DIGEST_KEY}
    return {**raw, DIGEST_KEY: content_digest(raw)}


# ----------------------------------------------------------------------------- conventions
def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.startswith("lensdist ")


@pytest.mark.parametrize(
    "command", ["demo", "generate", "train", "evaluate", "reproduce", "analyze", "calibrate", "undistort"]
)
def test_help_shows_defaults_example_json_debug(capsys, command):
    with pytest.raises(SystemExit):
        cli.main([command, "--help"])
    out = capsys.readouterr().out
    assert ("example:\n  lensdist " + command in out) or ("examples:\n  lensdist " + command in out)
    assert "default" in out and "--json" in out and "--debug" in out
    if command in ("generate", "reproduce", "evaluate", "analyze"):
        assert "--quiet" in out


def test_cli_module_does_not_import_torch():
    """`lensdist --help` must not pay for torch: cli/commands.py imports it inside the commands only (the
    package's own __init__ is stubbed out here to measure the CLI module alone)."""
    code = (
        "import sys, types\n"
        f"m = types.ModuleType('lensdist_torch'); m.__path__ = [{str(Path(cli.__file__).parent)!r}]\n"
        "m.__version__ = '0'; sys.modules['lensdist_torch'] = m\n"
        "import lensdist_torch.cli as c\n"
        "try:\n    c.main(['--help'])\nexcept SystemExit:\n    pass\n"
        "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip().endswith("NO-TORCH")


# ----------------------------------------------------------------------------- one-line errors
@bad_input
def test_missing_image(capsys, tmp_path):
    one_error(capsys, "analyze", tmp_path / "no.png", tmp_path / "no.png", match="not found")


@bad_input
def test_corrupt_checkpoint(capsys, pair, tmp_path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x80\x02not a checkpoint at all")
    one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", junk, match="corrupted")
    one_error(capsys, "analyze", *pair, "--method", "regression", "--checkpoint", junk, match="corrupted")


@bad_input
def test_nan_checkpoint(capsys, pair, ckpts, tmp_path):
    raw = torch.load(ckpts["delta_avg"], weights_only=True)
    means = raw["state_dict"]["means"].clone()
    means[1, 7] = float("nan")
    bad = _crafted(tmp_path, ckpts["delta_avg"], "nan.pt", means=means)
    line = one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", bad,
                     "--checkpoint-max", ckpts["delta_max"], match="NaN")
    assert str(bad) in line


@bad_input
def test_oversize_n_features_checkpoint_fails_fast(capsys, pair, ckpts, tmp_path):
    """A 1 MB-class file claiming 10**12 features (a 32 TB allocation): refused from the shapes."""
    bad = _crafted(tmp_path, ckpts["delta_avg"], "huge.pt", n_features=10**12)
    t0 = time.perf_counter()
    one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", bad,
              "--checkpoint-max", ckpts["delta_max"], match="expected (4, 1000000000000)")
    assert time.perf_counter() - t0 < 5.0


@bad_input
@pytest.mark.parametrize("missing", ["state_dict", "n_features", "train_delta"])
def test_checkpoint_missing_keys(capsys, pair, ckpts, tmp_path, missing):
    raw = torch.load(ckpts["delta_avg"], weights_only=True)
    if missing in raw:
        del raw[missing]
    else:
        del raw["state_dict"][missing]
    torch.save(_resigned(raw), tmp_path / "m.pt")
    one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", tmp_path / "m.pt",
              "--checkpoint-max", ckpts["delta_max"], match=f"lacks {missing}")


@bad_input
def test_wrong_metric_for_checkpoint_max(capsys, pair, ckpts):
    one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", ckpts["delta_avg"],
              "--checkpoint-max", ckpts["delta_avg"], match="needs a delta_max one")
    one_error(capsys, "analyze", *pair, "--method", "eigenspace", "--checkpoint", ckpts["delta_max"],
              "--checkpoint-max", ckpts["delta_max"], match="needs a delta_avg one")


@bad_input
def test_unused_options_are_refused(capsys, pair, ckpts, monkeypatch):
    def never(*a, **k):
        raise AssertionError("the images were analysed although an option is wrong")

    monkeypatch.setattr(prepare_mod, "_as_images", never)
    one_error(capsys, "analyze", *pair, "--checkpoint-max", ckpts["delta_max"], match="'eigenspace' only")
    one_error(capsys, "analyze", *pair, "--method", "regression", "--checkpoint-max", ckpts["delta_max"],
              match="'eigenspace' only")
    one_error(capsys, "analyze", *pair, "--checkpoint", ckpts["delta_avg"], match="not used by method 'selfcal'")


@bad_input
def test_eigenspace_checkpoint_as_regressor(capsys, pair, ckpts):
    one_error(capsys, "analyze", *pair, "--method", "regression", "--checkpoint", ckpts["delta_avg"],
              match="not a lensdist Delta-regression checkpoint")


@bad_input
def test_missing_data_and_bad_shard(capsys, tmp_path):
    one_error(capsys, "train", "--data", tmp_path / "none", "--out", tmp_path / "m.pt", match="no manifest.json")
    one_error(
        capsys, "evaluate", "--data", tmp_path / "none", "--selfcal", "--out", tmp_path / "r", match="no manifest.json"
    )
    one_error(capsys, "generate", "--out", tmp_path / "g", "--shard", "3/2", match="0 <= I < N")


@bad_input
def test_keyboard_interrupt(capsys, monkeypatch):
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "_cmd_demo", interrupted)
    rc, out, err = run(capsys, "demo")
    assert rc == 130 and err == "lensdist demo: interrupted\n" and out == ""


@bad_input
@pytest.mark.parametrize(
    "exc, code, match",
    [
        (RuntimeError("boom\nsecond line"), 1, "internal error: RuntimeError: boom second line"),
        (KeyError("x"), 1, "internal error: KeyError"),
        (PermissionError(13, "Permission denied", "/root/x"), 2, "/root/x: Permission denied"),
        (OSError("disk full"), 2, "disk full"),
    ],
)
def test_every_exception_is_one_line(capsys, monkeypatch, exc, code, match):
    def fail(args):
        raise exc

    monkeypatch.setattr(commands, "_cmd_demo", fail)
    one_error(capsys, "demo", match=match, code=code)
    rc, _, err = run(capsys, "--debug", "demo")
    assert rc == code and "Traceback" in err and err.rstrip().splitlines()[-1].startswith("lensdist demo: error:")


# ----------------------------------------------------------------------------- output paths
@bad_input
@pytest.mark.parametrize("kind", ["directory", "slash", "fifo", "suffix", "under_a_file"])
def test_save_map_path_checked_before_the_analysis(capsys, pair, tmp_path, monkeypatch, kind):
    def never(*a, **k):
        raise AssertionError("analysed before the --save-map path was checked")

    monkeypatch.setattr(analyze_mod, "analyze_pair", never)
    (tmp_path / "file").write_text("keep")
    target, match = {
        "directory": (tmp_path, "got the directory"),
        "slash": (f"{tmp_path / 'new'}/", "got the directory"),
        "fifo": (tmp_path / "pipe.png", "not a regular file"),
        "suffix": (tmp_path / "map.xyz", "ending in .png"),
        "under_a_file": (tmp_path / "file" / "map.png", "is not a folder"),
    }[kind]
    if kind == "fifo":
        os.mkfifo(target)
    one_error(capsys, "analyze", *pair, "--save-map", target, match=match)
    assert (tmp_path / "file").read_text() == "keep" and not (tmp_path / "new").exists()
    if kind == "fifo":
        assert not Path(target).is_file()


@bad_input
def test_result_printed_before_a_failing_map_write(capsys, pair, tmp_path, monkeypatch):
    import lensdist_torch.workflows.figures as figures

    def disk_full(*a, **k):
        raise OSError(28, "No space left on device", str(tmp_path / "map.png"))

    monkeypatch.setattr(figures, "save_map_grid", disk_full)
    rc, out, err = run(capsys, "analyze", *pair, "--method", "eigenspace", "--json", "--save-map", tmp_path / "map.png")
    assert rc == 2 and err.count("\n") == 1 and "No space left" in err
    assert _strict(out)["method"] == "eigenspace"  # the analysis is not lost


def test_save_map_writes_the_suffix_format(capsys, pair, tmp_path):
    pytest.importorskip("matplotlib")
    rc, out, err = run(capsys, "analyze", *pair, "--method", "eigenspace", "--save-map", tmp_path / "m.svg")
    assert rc == 0, err
    assert "distortion class" in out and "map:" in err
    assert (tmp_path / "m.svg").read_text().lstrip().startswith("<?xml")


@bad_input
@pytest.mark.parametrize("out", ["newdir/", "existing", "model.pth"])
def test_train_out_must_be_a_pt_file(capsys, tmp_path, out):
    (tmp_path / "existing").mkdir()
    target = str(tmp_path / out) + ("/" if out.endswith("/") else "")
    # the --out check comes before the data are read (the data folder does not exist)
    one_error(
        capsys, "train", "--data", tmp_path / "none", "--out", target, match="--out must be a file path ending in .pt"
    )
    assert not (tmp_path / "newdir").exists()


@bad_input
def test_out_folder_that_is_a_file(capsys, tmp_path):
    (tmp_path / "f").write_text("x")
    one_error(capsys, "demo", "--out", tmp_path / "f", match="is not one")
    one_error(capsys, "evaluate", "--data", tmp_path, "--selfcal", "--out", tmp_path / "f", match="is not one")
    assert (tmp_path / "f").read_text() == "x"


# ----------------------------------------------------------------------------- caches and JSON
@bad_input
def test_cached_model_follows_its_file(tmp_path):
    path = tmp_path / "m.pt"
    _classifier(n=2).save(path)
    first = analyze_mod._load_eigenspace(path)
    assert analyze_mod._load_eigenspace(path) is first  # cached while unchanged
    _classifier(n=3, seed=1).save(path)  # replaced atomically (new inode, size)
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    second = analyze_mod._load_eigenspace(path)
    assert second is not first and second.config.classifier.n_eigenvectors == 3
    path.unlink()
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        analyze_mod._load_eigenspace(path)


@bad_input
def test_analyze_json_is_strict_when_selfcal_diverges(capsys, pair, monkeypatch):
    def diverged(a, b, init=None, config=None, validate=True):
        z = torch.zeros(1, dtype=torch.float64)
        info = SelfCalInfo(*(torch.full((1,), float("nan"), dtype=torch.float64) for _ in SelfCalInfo._fields))
        return z, z, None, info._replace(converged=torch.tensor([False]))

    monkeypatch.setattr(prepare_mod, "estimate_distortion", diverged)
    rc, out, err = run(capsys, "analyze", *pair, "--json")
    assert rc == 0, err
    res = _strict(out)  # exactly one JSON object, no NaN
    assert res["delta_avg"] is None and res["delta_max_user_px"] is None
    assert any("diverged" in w for w in res["warnings"])
    rc, out, _ = run(capsys, "analyze", *pair)
    assert rc == 0 and "Delta: none given" in out and "nan" not in out.lower()


def test_reports_are_strict_json(tmp_path):
    nan = float("nan")
    assert _strict(dumps_strict({"a": [nan, 1.0, float("inf")], "b": (2, {"c": -float("inf")})})) == {
        "a": [None, 1.0, None], "b": [2, {"c": None}]
    }
    fig = {"confusion": [[1, 0, 0, 0, 0]] + [[0] * 5] * 4, "rate": 100.0, "correct": 1, "total": 1, "rejected_R": 0,
           "n_R": 0, "rmse_px": [0.5, nan, nan, nan], "rmse_pct": [3.5, nan, nan, nan], "bias_px": [0.1, nan, nan, nan],
           "n_per_class": [1, 0, 0, 0], "delta_range_px": 14.4}
    md, js = write_report({"title": "t", "settings": {"x": fig}}, tmp_path, "evaluate")
    assert _strict(js.read_text())["settings"]["x"]["rmse_px"] == [0.5, None, None, None]
    assert "nan" not in md.read_text()


def test_generate_reports_reused_shards(capsys, tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text('[image]\nheight = 96\nwidth = 128\n\n[protocol]\nshard_size = 2\n')
    argv = ["generate", "--config", cfg, "--out", tmp_path / "data", "--sets", "test", "--limit", "4", "--workers", "1"]
    rc, out, err = run(capsys, *argv, "--json", "--quiet")
    assert rc == 0, err
    first = _strict(out)
    assert first["written"] == 2 and err == ""
    rc, out, _ = run(capsys, *argv, "--quiet")
    assert rc == 0 and "0 shards written" in out and "2 reused" in out
    assert commands._shards(first) == (2, 0)


def test_json_only_on_stdout(capsys, tmp_path):
    rc, out, err = run(capsys, "demo", "--out", tmp_path, "--json")
    assert rc == 0, err
    summary = _strict(out)
    assert (
        summary["blocks"] == 40 * 53
        and summary["mean_error_ratio_outer_third"] > summary["mean_error_ratio_centre_third"]
    )
    rc, out, err = run(capsys, "demo", "--out", tmp_path)
    assert rc == 0 and out.startswith("A 1.0 % scale error") and not out.lstrip().startswith("{")
    assert math.isfinite(summary["quality_index"])


def test_the_text_answer_names_the_reason_codes(tmp_path, capsys):
    """A pair of the realistic relief condition (test pair 9, relief 2.7 %, true Delta_avg 11.18
    px): the text answer says "cannot tell" with the reason code beside the motion, and the
    warning names both answers (the plane + parallax one 11.98 px with the fixed relief prior,
    11.48 px with each pair's own)."""
    from kornia.io import write_image

    from lensdist_torch import load_config
    from lensdist_torch.data import draw_pairs, render_pairs

    cfg = load_config(Path(__file__).resolve().parents[2] / "configs" / "realistic_relief.toml")
    p = draw_pairs(cfg, "test", [9], len(cfg.protocol.scenes))
    pair = render_pairs([load_scene(s) for s in cfg.protocol.scenes], p, cfg)
    for name, img in zip(("a.png", "b.png"), pair):
        write_image(str(tmp_path / name), (img[0] * 255).round().to(torch.uint8))
    assert cli.main(["analyze", str(tmp_path / "a.png"), str(tmp_path / "b.png")]) == 0
    out = capsys.readouterr().out
    assert "Delta: none given (reason: relief; the views moved by" in out
    assert (
        "warning: cannot tell: relief: a plane + parallax model puts Delta_avg at 11.48 px" in out
        and "planar model at 9.25 px" in out
    )
