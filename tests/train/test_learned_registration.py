"""Tests of the learned-registration demonstration (train/learnreg/ and its entry script
train/learned_registration.py) on a tiny config (a few seconds in all)."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from lensdist_torch import QualityConfig, RegistrationQualityLoss, load_scene
from lensdist_torch.core.storage import CheckpointError, save_versioned
from lensdist_torch.geometry.distortion import delta_max
from lensdist_torch.workflows.figures import have_matplotlib

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "train"))  # the entry script imports the package the same way

from learnreg import config, data, loop, losses, report  # noqa: E402


def _load_entry_script():
    spec = importlib.util.spec_from_file_location("learned_registration", ROOT / "train" / "learned_registration.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


TINY = {
    "data.patch": 64,
    "data.rho": 6.0,
    "data.eval_rows": 96,
    "model.width": 4,
    "model.hidden": 16,
    "train.steps": 6,
    "train.batch_size": 4,
    "train.checkpoint_every": 2,
    "train.threads": 1,
    "eval.n_pairs": 8,
    "eval.batch_size": 8,
}


def tiny_config(**extra):
    return config.load_train_config(ROOT / "configs" / "learned_registration.toml", {**TINY, **extra})


@pytest.fixture(scope="module")
def scenes():
    return [load_scene(s) for s in ("gravel", "grass")]


pytestmark = pytest.mark.usefixtures("one_thread_module")  # tests/conftest.py


def test_default_config_loads_with_three_arms():
    cfg = config.load_train_config(ROOT / "configs" / "learned_registration.toml")
    assert list(cfg["arms"]) == ["l1", "l1_quality", "l1_quality_distorted"]
    assert cfg["arms"]["l1"]["lambda_quality"] == 0.0
    assert cfg["arms"]["l1_quality"]["lambda_quality"] > 0
    assert cfg["arms"]["l1_quality_distorted"]["distorted"] is True
    assert cfg["train"]["threads"] == 2
    with pytest.raises(ValueError):
        config.load_train_config(None, {"train.stpes": 3})


def test_overrides_parse_as_toml_values():
    o = config.parse_overrides(["train.steps=20", "arms.l1.lambda_quality=0.5", "model.kind=stacked"])
    assert o == {"train.steps": 20, "arms.l1.lambda_quality": 0.5, "model.kind": "stacked"}
    with pytest.raises(ValueError):
        config.parse_overrides(["train.steps"])


def test_pairs_are_consistent_with_their_labels(scenes):
    cfg = tiny_config(**{"data.photometric": 0.0})
    batch = data.make_pairs(scenes, [1, 2, 3, 4], cfg["data"], distorted=False, held_out=False)
    assert batch["a"].shape == (4, 1, 64, 64) and batch["delta"].shape == (4, 4, 2)
    warped, valid = losses.warp_a_to_b(batch["a"], batch["delta"])
    assert losses.l1_loss(warped, batch["b"], valid) < 1e-3  # the true homography registers them
    assert losses.l1_loss(batch["a"], batch["b"], torch.ones_like(valid)) > 0.02
    # per-pair seeds: a pair does not depend on the batch it is drawn in
    again = data.make_pairs(scenes, [3], cfg["data"], distorted=False, held_out=False)
    assert torch.equal(again["a"][0], batch["a"][2]) and torch.equal(again["b"][0], batch["b"][2])


def test_distortion_grid_follows_spec6():
    k2, k4 = torch.tensor([3e-6]), torch.tensor([3e-10])
    grid = data.source_points(128, k2, k4, distorted=True)
    c = 63.5
    r = math.hypot(c, c)
    corner = grid[0, 0, 0]  # p_d = (0, 0)
    expected = c + (1 + 3e-6 * r**2 + 3e-10 * r**4) * (0 - c)
    assert torch.allclose(corner, torch.tensor([expected, expected]), atol=1e-4)
    offset = (corner - torch.tensor([0.0, 0.0])).norm()
    assert abs(float(offset) - float(delta_max(k2, k4, 128, 128)[0])) < 1e-3


def test_corner_error_is_the_mean_corner_distance():
    gen = torch.Generator().manual_seed(0)
    pred, gt = torch.randn(5, 4, 2, generator=gen) * 4, torch.randn(5, 4, 2, generator=gen) * 4
    expected = (pred.double() - gt.double()).norm(dim=-1).mean(dim=-1)
    assert torch.allclose(losses.corner_error(pred, gt, 64), expected, atol=1e-9)


def test_quality_loss_gives_finite_nonzero_gradient_through_the_warp(scenes):
    cfg = tiny_config()
    model, _ = loop.build(cfg)
    # move the zero-initialised last layer so that the gradient reaches every layer
    torch.nn.init.normal_(model.head[-1].weight, std=0.05)
    batch = data.make_pairs(scenes, [10, 11, 12, 13], cfg["data"], distorted=False, held_out=False)
    pred = model(batch["a"], batch["b"])
    warped, valid = losses.warp_a_to_b(batch["a"], pred)
    loss = losses.quality_loss(RegistrationQualityLoss(reduction="none"), warped, batch["b"], valid)
    assert torch.isfinite(loss) and loss > 0
    loss.backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert all(float(g.abs().sum()) > 0 for g in grads)


def test_training_step_lowers_the_loss(scenes):
    cfg = tiny_config(**{"train.lr": 3e-3, "data.photometric": 0.0})
    model, opt = loop.build(cfg)
    batch = data.make_pairs(scenes, list(range(100, 108)), cfg["data"], distorted=False, held_out=False)
    arm = {**config.ARM_DEFAULTS, "lambda_quality": 0.5}
    steps = 15
    recs = [loop.train_step(model, opt, batch, arm, s, steps, cfg, QualityConfig()) for s in range(steps)]
    assert all(math.isfinite(r["loss"]) for r in recs)
    assert recs[-1]["loss"] < recs[0]["loss"]


def test_resume_reaches_bit_identical_parameters(tmp_path, scenes):
    cfg = tiny_config()
    arm = "l1_quality"
    cfg["arms"][arm]["quality_start"] = 0.3  # the schedule switches on during the run
    full, hist_full, _ = loop.train_arm(cfg, arm, tmp_path / "full", progress=False, scenes=scenes)
    # a crash after step 3: the last checkpoint is the one of step 2, so one step is redone
    loop.train_arm(cfg, arm, tmp_path / "cut", progress=False, scenes=scenes, stop_after=3)
    state = torch.load(tmp_path / "cut" / "checkpoints" / f"{arm}.pt", weights_only=True)
    assert state["step"] == 2
    resumed, hist_res, _ = loop.train_arm(cfg, arm, tmp_path / "cut", resume=True, progress=False, scenes=scenes)
    for (n1, p1), (n2, p2) in zip(full.state_dict().items(), resumed.state_dict().items()):
        assert n1 == n2 and torch.equal(p1, p2), n1
    assert [r["loss"] for r in hist_full] == [r["loss"] for r in hist_res]
    assert not [p for p in (tmp_path / "cut" / "checkpoints").iterdir() if "tmp" in p.name]
    # another config (here the thread count, which can change the floats) is refused
    with pytest.raises(CheckpointError, match="another config"):
        loop.train_arm(
            tiny_config(**{"train.threads": 2}), arm, tmp_path / "cut", resume=True, progress=False, scenes=scenes
        )


def test_checkpoint_loads_with_weights_only_and_checks_kind_and_version(tmp_path):
    cfg = tiny_config()
    model, opt = loop.build(cfg)
    path = loop.checkpoint_path(tmp_path, "l1")
    loop.save_checkpoint(path, model, opt, 3, [{"loss": 1.0, "step": 0}], cfg, "l1", 1.5)
    state = torch.load(path, weights_only=True)
    assert state["kind"] == loop.CHECKPOINT_KIND and state["format_version"] == loop.CHECKPOINT_VERSION
    assert state["config"] == json.loads(json.dumps(cfg)) and state["step"] == 3
    assert loop.load_checkpoint(path, cfg, "l1", *loop.build(cfg))["step"] == 3
    with pytest.raises(CheckpointError, match="holds arm"):
        loop.load_checkpoint(path, cfg, "l1_quality", *loop.build(cfg))
    payload = {k: v for k, v in state.items() if k not in ("kind", "format_version")}
    save_versioned(path, "something_else", loop.CHECKPOINT_VERSION, payload)
    with pytest.raises(CheckpointError, match="not a lensdist"):
        loop.load_checkpoint(path, cfg, "l1", *loop.build(cfg))
    save_versioned(path, loop.CHECKPOINT_KIND, loop.CHECKPOINT_VERSION + 1, payload)
    with pytest.raises(CheckpointError, match="format version"):
        loop.load_checkpoint(path, cfg, "l1", *loop.build(cfg))


def test_cli_writes_results(tmp_path):
    out = tmp_path / "res"
    args = ["--config", str(ROOT / "configs" / "learned_registration.toml"), "--out", str(out), "--no-progress"]
    for k, v in TINY.items():
        args += ["--set", f"{k}={v}"]
    args += ["--steps", "2"]
    _load_entry_script().main(args)
    results = json.loads((out / "results.json").read_text())
    assert set(results) == {"l1", "l1_quality", "l1_quality_distorted"}
    for r in results.values():
        for key in ("mean_corner_error", "median_corner_error", "share_under_1px"):
            assert math.isfinite(r[key])
        assert r["threads"] == 1 and r["steps"] == 2
    assert (out / "results.md").read_text().count("|") > 10
    if have_matplotlib():
        for name, _ in report.CURVES.values():
            assert (out / name).is_file()
