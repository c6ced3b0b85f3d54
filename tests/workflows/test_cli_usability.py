"""Issue 22, items 4 and 5: every subcommand explains itself (description, example, --debug),
mistyped options get a suggestion, options are checked before any work, and analyze's text
answer gives one reason, barrel or pincushion, and says when an estimate lies beyond the range."""

from __future__ import annotations

import re

import pytest

from lensdist_torch import cli
from lensdist_torch.cli.analyze import print_analysis
from lensdist_torch.config import LensdistConfig
from lensdist_torch.workflows.decision import decide
from lensdist_torch.workflows.pair_analysis import JSON_KEYS, PairAnalysis

COMMANDS = ["demo", "generate", "train", "evaluate", "reproduce", "analyze", "calibrate", "undistort"]


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as info:
        cli.main([*argv, "--help"])
    assert info.value.code == 0
    return capsys.readouterr().out


def test_every_subcommand_is_listed_with_a_description_and_an_example(capsys):
    top = _help(capsys)
    for command in COMMANDS:
        assert re.search(rf"\n    {command}\s", top), command
        out = _help(capsys, command)
        usage, _, rest = out.partition("\n\n")
        assert rest.split("\n")[0].strip() and not rest.startswith("positional"), (command, out)  # a description
        assert "example" in out and f"\n  lensdist {command} " in out, (command, out)
        assert "--debug" in out and "--json" in out, command


@pytest.mark.parametrize("command", ["calibrate", "analyze", "demo", "generate", "train", "evaluate", "reproduce"])
def test_config_is_an_option(capsys, command):
    assert "--config" in _help(capsys, command)


@pytest.mark.bad_input
@pytest.mark.parametrize("argv, prog, wanted", [
    (["calibrate", "x", "--jsn"], "lensdist calibrate", "--jsn (did you mean --json?)"),
    (["undistort", "x", "--out", "o", "--alpah", "1"], "lensdist undistort", "--alpah (did you mean --alpha?)"),
    (["analyze", "a", "b", "--metod=regression"], "lensdist analyze", "--metod=regression (did you mean --method?)"),
    (["reproduce", "--quik"], "lensdist reproduce", "--quik (did you mean --quick?)"),
    (["calibrat", "x"], "lensdist", "did you mean calibrate?"),
    (["analyze", "a", "b", "--method", "regresion"], "lensdist analyze", "did you mean regression?"),
    (["calibrate", "x", "--zzzzzz"], "lensdist calibrate", "unrecognized arguments: --zzzzzz (see"),
])
def test_a_mistyped_option_gets_a_suggestion(capsys, argv, prog, wanted):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith(f"{prog}: error: ") and wanted in err, err


@pytest.mark.bad_input
@pytest.mark.parametrize("argv", [
    ["calibrate", "{d}", "--focal", "-3"],
    ["calibrate", "{d}", "--max-frames", "0"],
    ["calibrate", "{d}", "--config", "{d}/missing.toml"],
    ["undistort", "{d}", "--k2", "1e-7", "--k4", "0", "--alpha", "1.5", "--out", "{d}/o"],
    ["undistort", "{d}", "--from", "{d}/missing.json", "--out", "{d}/o"],
])
def test_options_are_refused_before_any_frame_is_read(tmp_path, capsys, monkeypatch, argv):
    import lensdist_torch.calibration.controllers.calibrate as calibrate

    def never(*args, **kwargs):
        raise AssertionError("a frame was read before the options were checked")

    import lensdist_torch.calibration.controllers.multiview_path as multiview_path

    monkeypatch.setattr(multiview_path, "read_frames", never)
    monkeypatch.setattr(calibrate, "frames_of_one_size", never)
    import lensdist_torch.workflows.undistort as undistort

    monkeypatch.setattr(undistort, "frames_of_one_size", never)
    assert cli.main([a.format(d=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and " error: " in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("where", ["before", "after"])
def test_debug_shows_the_traceback_of_an_internal_error(capsys, monkeypatch, tmp_path, where):
    import lensdist_torch.calibration.controllers.calibrate as calibrate

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(calibrate, "calibrate_path", broken)
    argv = ["calibrate", str(tmp_path), "--quiet"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert (
        err.strip()
        == "lensdist calibrate: error: internal error: RuntimeError: boom (run with --debug for the traceback)"
    )
    assert cli.main(["--debug", *argv] if where == "before" else [*argv, "--debug"]) == 1
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and err.strip().endswith("internal error: RuntimeError: boom")


# ------------------------------------------------------------------ analyze's text answer
def _res(**kw):
    base = {
        "estimated_class": "3",
        "estimated_class_max": "3",
        "delta_avg": 9.0,
        "delta_max": 50.0,
        "confidence": 0.9,
        "registration_ok": True,
        "overlap": 0.9,
        "method": "selfcal",
        "analysis_size": [320, 424],
        "input_size": [320, 424],
        "delta_avg_user_px": 9.0,
        "delta_max_user_px": 50.0,
        "delta_avg_region_user_px": 9.0,
        "delta_max_region_user_px": 50.0,
        "distances": None,
        "motion_px": 12.0,
        "distortion_type": "barrel",
        "delta_avg_interval": [8.5, 9.5],
        "reject_threshold": None,
        "registered_by": "homography",
        "analysed_region_user_px": [0, 0, 320, 424],
        "registration_residual": 0.01,
        "error_blocks": 0,
        "user_px_per_analysis_px": 1.0,
        "homography": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    }
    return {**base, **kw}


def _text(capsys, res) -> str:
    decide(res, LensdistConfig())
    attribute = {key: name for name, key in JSON_KEYS.items()}
    print_analysis(PairAnalysis(**{attribute.get(key, key): value for key, value in res.items()}))
    return capsys.readouterr().out


def test_unrelated_images_get_one_reason(capsys):
    out = _text(capsys, _res(registration_ok=False, confidence=0.05))
    assert "registration failed" in out and "too little motion or texture" not in out
    assert "Delta: none given (registration failed)" in out
    out = _text(capsys, _res(overlap=0.2, confidence=0.05))
    assert "overlap on 20 % only" in out and "too little motion or texture" not in out
    out = _text(capsys, _res(confidence=0.05))  # aligned, but nothing to see: that reason
    assert "too little motion or texture" in out and "registration failed" not in out


@pytest.mark.parametrize("kind", ["barrel", "pincushion"])
def test_the_class_line_says_barrel_or_pincushion(capsys, kind):
    line = next(s for s in _text(capsys, _res(distortion_type=kind)).splitlines() if s.startswith("distortion class"))
    assert line.startswith(f"distortion class: 3, {kind}  (1 = small")


def test_an_estimate_beyond_the_class_range_says_so_on_the_class_line(capsys):
    res = _res(estimated_class="4", estimated_class_max="4", delta_avg=40.0, delta_max=150.0)
    out = _text(capsys, res)
    assert res["beyond_class_range"] and res["delta_avg_interval"] is None
    assert "distortion class: 4 or beyond (Delta_avg lies past the classes' range), barrel" in out
    assert "warning: Delta_avg 40.0 px is beyond the classes' range" in out
    assert not _res()["delta_avg"] > 20 and "or beyond" not in _text(capsys, _res())


def test_the_planar_setting_the_readme_gives_answers(tmp_path, capsys):
    """Issue 51: ``[selfcal] parallax = 0`` (the README's advice for flat scenes) made every pair exit 2 with
    "k2 and k4 must be finite": the plane + parallax model is not fitted then, and its NaN coefficients were
    turned into a Delta. The planar answer stands, against the truth at the analysis frame."""
    import json

    from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
    from lensdist_torch.core.png import encode_png, to_uint8
    from lensdist_torch.geometry.distortion import paper_frame_delta_avg

    frames, _ = synthetic_sequence(2, 2e-6, 0.0, size=(240, 320), step_px=(12.0, 12.0))
    for name, f in zip("ab", frames):
        (tmp_path / f"{name}.png").write_bytes(encode_png(to_uint8(f)))
    (tmp_path / "flat.toml").write_text("[selfcal]\nparallax = 0\n")
    argv = [
        "analyze",
        str(tmp_path / "a.png"),
        str(tmp_path / "b.png"),
        "--config",
        str(tmp_path / "flat.toml"),
        "--json",
    ]
    assert cli.main(argv) == 0
    res = json.loads(capsys.readouterr().out)
    truth = paper_frame_delta_avg(2e-6, 0.0, (240, 320), LensdistConfig())  # the same lens at the analysis frame
    assert res["relief_found"] is False and res["estimated_delta_avg"] == pytest.approx(truth, rel=0.1)
