"""One analysis path: the figures of ``reproduce`` and ``evaluate`` are what ``analyze_pair``
answers, pair by pair, on the same test pairs; ``analyze_batch`` answers a pair as it answers it
alone."""

from __future__ import annotations

import json
import math

import pytest
import torch
from workflow_helpers import TINY

from lensdist_torch.cli import main
from lensdist_torch.config import config_from_dict, load_config
from lensdist_torch.core.images import load_scene
from lensdist_torch.data.shards import load_scenes, load_set
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.workflows import prepare
from lensdist_torch.workflows.analyze import analyze_batch, analyze_pair, prepare_batch, resolve_device
from lensdist_torch.workflows.evaluate import figures_of
from lensdist_torch.workflows.reports import json_safe

pytestmark = pytest.mark.usefixtures("one_thread_module")

#: method -> (analyze_pair's checkpoints under out/checkpoints, the report's settings)
RUNS = {
    "selfcal": ({}, ("selfcal, delta_avg", "selfcal, delta_max")),
    "regression": ({"checkpoint": "regression.pt"}, ("regression, delta_avg", "regression, delta_max")),
    "eigenspace": ({"checkpoint": "eigenspace_delta_avg_10ev.pt", "checkpoint_max": "eigenspace_delta_max_10ev.pt"},
                   ("10 EV, delta_avg", "10 EV, delta_max")),
}
FIGURES = (
    "confusion",
    "correct",
    "total",
    "cannot_tell",
    "confident_wrong",
    "rejected_R",
    "n_per_class",
    "registration_failed",
)


def _one_by_one(out, method, cfg):
    """Every test pair, rendered alone from its seed and analysed alone by analyze_pair."""
    test = load_set(out / "data", "test")
    scenes, _ = load_scenes(test["config"])
    ckpts = {k: out / "checkpoints" / v for k, v in RUNS[method][0].items()}
    results = []
    for i in range(test["index"].numel()):
        params = draw_pairs(test["config"], "test", [int(test["index"][i])], len(scenes))
        img1, img2 = render_pairs(scenes, params, test["config"])
        hom = test["H"][i] if bool(test["perturbed"][i]) else None  # class R: the protocol's registration
        results.append(analyze_pair(img1[0], img2[0], method=method, config=cfg, homography=hom, **ckpts))
    return test, results


def _same_figures(mine: dict, theirs: dict) -> None:
    mine = json_safe(mine)
    for key in FIGURES:
        assert mine[key] == theirs[key], key
    for key in ("rate", "cannot_tell_share", "confident_rate"):
        assert mine[key] == pytest.approx(theirs[key], abs=1e-12) or (mine[key] is None and theirs[key] is None), key
    for a, b in zip(mine["rmse_px"], theirs["rmse_px"]):
        assert (a is None and b is None) or a == pytest.approx(b, abs=1e-9)


def _same_answers(fig: dict, name: str, test: dict, results: list, cfg) -> None:
    """A report's row ``name`` holds what ``results`` (analyze_pair's, pair by pair) answer."""
    metric = "delta_max" if "delta_max" in name else "delta_avg"
    key = "class_label" if metric == "delta_avg" else "class_max_label"
    assert fig["per_pair"]["index"] == test["index"].tolist()
    assert [getattr(r, key) for r in results] == fig["per_pair"]["class"], name
    assert [r.confidence for r in results] == pytest.approx(fig["per_pair"]["confidence"], abs=1e-12), name
    for r, d in zip(results, fig["per_pair"]["delta"]):
        est = getattr(r, f"estimated_{metric}")  # reported for every pair, as the estimator gave it
        assert (est is None and d is None) or est == pytest.approx(d, abs=1e-9), name
    _same_figures(figures_of(results, test, metric, cfg), fig)


@pytest.mark.parametrize("method", list(RUNS))
def test_reproduce_reports_what_analyze_pair_answers(tiny_run, method):
    out, _ = tiny_run
    report = json.loads((out / "reproduce.json").read_text())
    cfg = load_config(out / "calibration.toml")  # the calibrated settings reproduce analysed with
    assert cfg.analysis.no_distortion_px == report["calibration"]["analysis"]["no_distortion_px"]
    test, results = _one_by_one(out, method, cfg)
    for name in RUNS[method][1]:
        _same_answers(report["settings"][name], name, test, results, cfg)


def test_reproduce_reports_the_shipped_decision_as_analyze_pair_answers_it(tiny_run):
    """The rows "selfcal, ..., shipped decision": analyze_pair under the config reproduce was given (no --config)."""
    out, _ = tiny_run
    report = json.loads((out / "reproduce.json").read_text())
    cfg = config_from_dict(TINY)
    fitted = load_config(out / "calibration.toml")
    assert fitted.analysis != cfg.analysis  # two decisions: the rows could differ
    test, results = _one_by_one(out, "selfcal", cfg)
    for metric in ("delta_avg", "delta_max"):
        name = f"selfcal, {metric}, shipped decision"
        _same_answers(report["settings"][name], name, test, results, cfg)
        assert name in report["unseen"]["settings"]
    assert "**shipped decision**" in (out / "reproduce.md").read_text()


def test_a_prepared_batch_under_another_decision_is_one_fit(monkeypatch):
    """with_decision: the answers of a batch prepared under that decision, bit for bit, from one self-calibration."""
    import dataclasses

    cfg, a, b = _rendered(2)
    low = min(r.estimated_delta_avg for r in analyze_batch(a, b, config=cfg))  # both R at 0.75 px (0.11, 0.19)
    other = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, no_distortion_px=low / 2))
    fresh = analyze_batch(a, b, config=other)
    calls = []
    real = prepare.estimate_distortion
    monkeypatch.setattr(prepare, "estimate_distortion", lambda *x, **k: calls.append(1) or real(*x, **k))
    prep = prepare_batch(a, b, config=cfg)
    mine = analyze_batch(None, None, config=cfg, prepared=prep)
    theirs = analyze_batch(None, None, config=other, prepared=prep.with_decision(other.analysis))
    assert len(calls) == 2  # one fit per pair, shared by both decisions
    assert prep.with_decision(other.analysis).texture() is prep.texture()  # the histograms too
    for x, y in zip(fresh, theirs, strict=True):
        # the OpenCV export's least squares rounds differently from call to call (1e-18): compared apart
        x, y = x.to_json(), y.to_json()
        cx, cy = x.pop("opencv"), y.pop("opencv")
        assert x == y and (cx is None) == (cy is None)  # "cannot tell": no camera to export
        assert cx is None or cx["dist_coeffs"] == pytest.approx(cy["dist_coeffs"], rel=1e-9, abs=1e-15)
    assert [r.delta_avg for r in mine] == [r.estimated_delta_avg for r in theirs]
    assert [r.estimated_class for r in mine] == ["R", "R"] and "R" not in [r.estimated_class for r in theirs]
    with pytest.raises(TypeError, match=r"^analysis \(with_decision\) must be an AnalysisConfig .*got LensdistConfig$"):
        prep.with_decision(other)  # a whole config: only the decision may differ


def test_evaluate_reports_what_reproduce_reports(tiny_run, tmp_path, capsys):
    """`lensdist evaluate --config calibration.toml` on the same data: the same figures, pair by pair."""
    out, _ = tiny_run
    ck = out / "checkpoints"
    code = main(["evaluate", "--data", str(out / "data"), "--checkpoint", str(ck / "eigenspace_delta_avg_10ev.pt"),
                 str(ck / "eigenspace_delta_max_10ev.pt"), "--regression", str(ck / "regression.pt"), "--selfcal",
                 "--config", str(out / "calibration.toml"), "--out", str(tmp_path), "--quiet"])
    assert code == 0, capsys.readouterr().err
    ev = json.loads((tmp_path / "evaluate.json").read_text())["settings"]
    rep = json.loads((out / "reproduce.json").read_text())["settings"]
    for name in ("10 EV, delta_avg", "10 EV, delta_max", "regression, delta_avg", "selfcal, delta_max"):
        assert ev[name]["per_pair"] == rep[name]["per_pair"], name
        _same_figures(ev[name], rep[name])


def _rendered(n=3, size=(96, 128)):
    cfg = load_config(None)
    import dataclasses

    cfg = dataclasses.replace(cfg, image=dataclasses.replace(cfg.image, height=size[0], width=size[1]))
    scenes, _ = load_scenes(cfg)
    return cfg, *render_pairs(scenes, draw_pairs(cfg, "test", list(range(n)), len(scenes)), cfg)


def test_a_pair_is_answered_as_in_a_batch():
    """Batched kernels round differently with the batch size: the estimators run pair by pair."""
    cfg, a, b = _rendered(3)
    batch = analyze_batch(a, b, config=cfg)
    for i in range(3):
        one = analyze_pair(a[i], b[i], config=cfg)
        assert one.homography == batch[i].homography
        assert one.delta_avg == batch[i].delta_avg and one.class_label == batch[i].class_label


def test_inputs_and_shared_preparation(tmp_path):
    """Lists of tensors or paths, one prepared batch for several methods, the given homography."""
    cfg, a, b = _rendered(2)
    as_list = analyze_batch([a[0], a[1]], [b[0], b[1]], config=cfg)
    as_tensor = analyze_batch(a, b, config=cfg)
    assert [r.delta_avg for r in as_list] == [r.delta_avg for r in as_tensor]
    prep = prepare_batch(a, b, config=cfg)
    again = analyze_batch(None, None, config=cfg, prepared=prep)
    assert [r.delta_avg for r in again] == [r.delta_avg for r in as_tensor]
    given = analyze_batch(a, b, config=cfg, homography=prep.H)
    assert [r.homography for r in given] == [r.homography for r in as_tensor]
    assert all(r.registration_ok for r in given)
    with pytest.raises(ValueError, match="as many images"):
        analyze_batch(a, b[:1], config=cfg)
    with pytest.raises(ValueError, match="homography must be"):
        analyze_batch(a, b, config=cfg, homography=torch.eye(3)[None])
    with pytest.raises(ValueError, match="analyze_batch"):
        analyze_pair(a, b, config=cfg)


def test_batched_estimators_answer_as_pair_by_pair(monkeypatch):
    """A GPU's way (one estimator call for the batch, the pairs without a registration in a call
    of their own), run on the CPU: the answers of the pair-by-pair way, up to rounding."""
    cfg, a, b = _rendered(4)
    g = torch.Generator().manual_seed(5)
    b[2] = torch.rand(b[2].shape, generator=g)  # unrelated: no registration, no start
    alone = analyze_batch(a, b, config=cfg)
    monkeypatch.setattr(prepare, "_batched", lambda dev: True)
    together = analyze_batch(a, b, config=cfg)
    assert [r.registration_ok for r in alone] == [True, True, False, True]
    for x, y in zip(alone, together, strict=True):
        assert (x.class_label, x.registration_ok) == (y.class_label, y.registration_ok)
        if not x.registration_ok:  # a fit of unrelated images: rounding moves it anywhere
            continue
        assert x.estimated_class == y.estimated_class
        for key in ("delta_avg", "delta_avg_std", "relief_delta_avg"):
            a, b = getattr(x, key), getattr(y, key)
            assert (a is None and b is None) or math.isclose(a, b, abs_tol=1e-3), key
        torch.testing.assert_close(torch.tensor(x.homography), torch.tensor(y.homography), atol=1e-3, rtol=0)


def test_device():
    cfg, a, b = _rendered(1)
    assert resolve_device(None) == torch.device("cpu")
    r = analyze_pair(a[0], b[0], config=cfg, device="cpu")
    assert r.registration_ok
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda")
        with pytest.raises(ValueError, match="CUDA is not available"):
            analyze_pair(a[0], b[0], config=cfg, device="cuda")
    else:  # the same answer on the GPU, up to the float32 kernels
        g = analyze_pair(a[0], b[0], config=cfg, device="cuda")
        assert g.class_label == r.class_label and math.isclose(g.delta_avg, r.delta_avg, abs_tol=0.05)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA present")
@pytest.mark.parametrize("command", ["analyze", "evaluate", "reproduce"])
def test_device_cuda_absent_is_one_line(tmp_path, capsys, command):
    s = load_scene("gravel")[0, 0]
    from kornia.io import write_image

    for name, img in (("a.png", s[:96, :128]), ("b.png", s[4:100, :128])):
        write_image(str(tmp_path / name), (img * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous())
    argv = {"analyze": ["analyze", str(tmp_path / "a.png"), str(tmp_path / "b.png")],
            "evaluate": ["evaluate", "--data", str(tmp_path / "none"), "--selfcal", "--out", str(tmp_path / "o")],
            "reproduce": ["reproduce", "--quick", "--out", str(tmp_path / "r")]}[command]
    assert main(argv + ["--device", "cuda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "CUDA is not available" in err[0]


@pytest.mark.parametrize("method", ["selfcal", "regression"])
def test_analyze_pair_is_one_call_of_analyze_batch(monkeypatch, method):
    """analyze_pair resolves the models and the config once, prepares (loads, checks, registers)
    the pair once, and answers what analyze_batch answers for the same pair."""
    from lensdist_torch.workflows import analyze as mod

    calls = {"_models_and_config": 0, "prepare_batch": 0}
    for name in calls:
        real = getattr(mod, name)

        def counted(*args, _real=real, _name=name, **kwargs):
            calls[_name] += 1
            return _real(*args, **kwargs)

        monkeypatch.setattr(mod, name, counted)
    scene = load_scene("gravel")
    a, b = scene[..., :320, :424], scene[..., 6:326, 2:426]
    res, qmap = analyze_pair(a, b, method=method, return_map=True)
    assert calls == {"_models_and_config": 1, "prepare_batch": 1}
    batch, maps = analyze_batch(a, b, method=method, return_maps=True)
    assert torch.equal(qmap, maps)
    # the same answer to 1e-7 relative: the batch's buffers may be aligned otherwise, and the CPU
    # kernels' SIMD paths then round differently (seen: 1e-13 relative, once in ~3 runs; 1.4e-9 on an
    # OpenCV coefficient of 7.6e-13 that its least-squares fit leaves at the noise, once in CI)
    assert _same(res.to_json(), batch[0].to_json())


def _same(a, b) -> bool:
    """Equal structures, floats within 1e-7 relative (or both NaN), everything else exactly."""
    if isinstance(a, float) and isinstance(b, float):
        return (a != a and b != b) or math.isclose(a, b, rel_tol=1e-7, abs_tol=0.0)
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def test_each_image_is_checked_once_per_analyze_pair():
    """The values of each image (NaN, Inf: a reduction and a host sync) are checked once, at the
    entry; the estimators downstream take the checked tensors (validate=False)."""
    import sys

    scene = load_scene("gravel")
    a, b = scene[..., :320, :424], scene[..., 6:326, 2:426]
    analyze_pair(a, b)  # warm up: lazy imports
    value_checks = []

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_name == "check_image" and frame.f_locals.get("finite"):
            value_checks.append(frame.f_locals.get("name"))
        elif event == "call" and frame.f_code.co_name == "check_values":  # the metric's own value check
            value_checks.append("metric")

    sys.setprofile(profile)
    try:
        analyze_pair(a, b)
    finally:
        sys.setprofile(None)
    assert sorted(value_checks) == ["img1", "img2"]
