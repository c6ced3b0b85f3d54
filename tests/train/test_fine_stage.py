"""Tests of the fine-stage study (train/finestage/ and train/fine_stage.py) on tiny sizes."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

from lensdist_torch import RegistrationQualityLoss
from lensdist_torch.core.storage import CheckpointError

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "train"))

from finestage import config, data, experiment, loop, losses, refine, report  # noqa: E402
from learnreg.losses import l1_loss, warp_a_to_b  # noqa: E402

TINY = {
    "data.patch": 64,
    "model.width": 4,
    "model.hidden": 16,
    "train.steps": 4,
    "train.batch_size": 2,
    "train.checkpoint_every": 2,
    "train.threads": 1,
    "train.seeds": [0, 1],
    "sweep.lambdas": [0.2],
    "sweep.variants": ["tau_scale=2.0"],
    "sweep.distorted": ["l1"],
    "eval.val_pairs": 4,
    "eval.test_pairs": 4,
    "eval.batch_size": 4,
    "refine.steps": 2,
    "refine.lrs": [0.1],
    "refine.val_pairs": 2,
    "refine.test_pairs": 2,
    "refine.test_sets": 2,
    "refine.distorted": False,
}


def tiny(**extra):
    return config.load_config(ROOT / "configs" / "fine_stage.toml", {**TINY, **extra})


@pytest.fixture(scope="module")
def scenes():
    return data.load_scenes(tiny())


pytestmark = pytest.mark.usefixtures("one_thread_module")  # tests/conftest.py


# --- the peer losses on hand-worked values ---------------------------------------------------


def _img(rows):
    return torch.tensor(rows, dtype=torch.float64).view(1, 1, len(rows), len(rows[0]))


def test_ncc_hand_worked_values():
    x = _img([[0, 0, 0], [0, 1, 0], [0, 0, 0]])
    # y = 1 - x: perfectly anti-correlated
    assert float(losses.local_ncc(x, 1 - x, 3, 0.0)) == pytest.approx(-1.0, abs=1e-12)
    # y has a second bright pixel: cov = 1/9 - 2/81 = 7/81, var_x = 8/81, var_y = 14/81
    y = _img([[0, 0, 0], [0, 1, 1], [0, 0, 0]])
    assert float(losses.local_ncc(x, y, 3, 0.0)) == pytest.approx(7 / math.sqrt(8 * 14), abs=1e-12)
    ones = torch.ones_like(x)
    num, den = losses.ncc_term(x, y, ones, ncc_window=3, ncc_eps=0.0)
    assert float(num / den) == pytest.approx(1 - 7 / math.sqrt(112), abs=1e-12)


def test_ncc_identical_is_zero_and_gain_offset_do_not_change_it():
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(2, 1, 32, 32, generator=gen, dtype=torch.float64)
    y = (x + 0.3 * torch.rand(2, 1, 32, 32, generator=gen, dtype=torch.float64)) / 1.3
    ones = torch.ones_like(x)
    cfg = {"levels": 1, "ncc_window": 9, "ncc_eps": 1e-4}
    assert float(losses.peer_loss("ncc", x, x, ones, cfg)) < 2e-3  # eps only: 1e-4 against var ~ 1/12
    exact = {**cfg, "ncc_eps": 0.0}
    assert float(losses.peer_loss("ncc", x, x, ones, exact)) == pytest.approx(0.0, abs=1e-12)
    base = losses.peer_loss("ncc", x, y, ones, exact, per_pair=True)
    changed = losses.peer_loss("ncc", 0.6 * x + 0.25, 1.4 * y - 0.1, ones, exact, per_pair=True)
    assert torch.allclose(base, changed, atol=1e-10)
    # with the default eps the change is of order eps / var
    b2 = losses.peer_loss("ncc", x, y, ones, cfg)
    c2 = losses.peer_loss("ncc", 0.6 * x + 0.25, 1.4 * y - 0.1, ones, cfg)
    assert abs(float(b2 - c2)) < 5e-3
    # L1 is not invariant: a gain and offset of an image against itself
    assert float(losses.peer_loss("l1", 0.6 * x + 0.25, x, ones, cfg)) > 0.02


def test_ngf_hand_worked_values():
    cols = torch.arange(8, dtype=torch.float64).view(1, 1, 1, 8).expand(1, 1, 8, 8)
    rows = cols.transpose(-1, -2)
    ones = torch.ones_like(cols)
    eta = 0.2
    cfg = {"levels": 1, "ngf_eta": eta}
    # identical ramps: aligned everywhere, loss 0; a ramp against a scaled copy: still 0 (gain)
    assert float(losses.peer_loss("ngf", 0.1 * cols, 0.1 * cols, ones, cfg)) == pytest.approx(0.0, abs=1e-12)
    assert float(losses.peer_loss("ngf", 0.1 * cols, 0.03 * cols + 0.5, ones, cfg)) == pytest.approx(0.0, abs=1e-12)
    # orthogonal ramps a*x and b*y: eps_i = eta |a|, eta |b| -> term = eta^4 / (1 + eta^2)^2
    expect = 1 - eta**4 / (1 + eta**2) ** 2
    assert float(losses.peer_loss("ngf", 0.1 * cols, 0.05 * rows, ones, cfg)) == pytest.approx(expect, abs=1e-12)
    # opposite ramps: (-1 + eta^2)^2 / (1 + eta^2)^2
    expect = 1 - (1 - eta**2) ** 2 / (1 + eta**2) ** 2
    assert float(losses.peer_loss("ngf", 0.1 * cols, 1 - 0.1 * cols, ones, cfg)) == pytest.approx(expect, abs=1e-12)


def test_l1_pyramid_matches_learnreg_and_invalid_pixels_are_ignored():
    gen = torch.Generator().manual_seed(1)
    x, y = torch.rand(3, 1, 32, 32, generator=gen), torch.rand(3, 1, 32, 32, generator=gen)
    valid = torch.ones(3, 1, 32, 32)
    valid[..., :, :10] = 0
    ours = losses.peer_loss("l1", x, y, valid, {"levels": 3})
    assert torch.allclose(ours, l1_loss(x, y, valid, levels=3), atol=1e-6)
    x2 = x.clone()
    x2[..., :, :10] = 5.0  # garbage where invalid
    for peer in ("l1", "ncc", "ngf"):
        cfg = {"levels": 2, "ncc_window": 5, "ncc_eps": 1e-4, "ngf_eta": 0.2}
        assert torch.allclose(losses.peer_loss(peer, x, y, valid, cfg), losses.peer_loss(peer, x2, y, valid, cfg))


def test_quality_per_pair_equals_the_library_masked_mean(scenes):
    cfg = tiny()
    b = data.make_pairs(scenes, [5, 6, 7], cfg["data"], False, "train")
    warped, valid = warp_a_to_b(b["a"], b["delta"] * 2)
    per_pair = losses.quality_per_pair(RegistrationQualityLoss(reduction="none"), warped.clamp(0, 1), b["b"], valid)
    lib = RegistrationQualityLoss(reduction="masked_mean")
    for i in range(3):
        one = lib(warped[i : i + 1].clamp(0, 1), b["b"][i : i + 1], valid[i : i + 1])
        assert float(per_pair[i]) == pytest.approx(float(one), abs=1e-6)


# --- data -------------------------------------------------------------------------------------


def test_pairs_have_fine_residuals_and_disjoint_splits(scenes):
    cfg = tiny(**{"data.photometric": 0.0})
    b = data.make_pairs(scenes, list(range(20)), cfg["data"], False, "train")
    r = b["delta"].norm(dim=-1)
    assert float(r.min()) >= 0.5 - 1e-5 and float(r.max()) <= 3.0 + 1e-5
    warped, valid = warp_a_to_b(b["a"], b["delta"])
    assert float(l1_loss(warped, b["b"], valid)) < 2e-3  # the true offsets register the pair
    again = data.make_pairs(scenes, [7], cfg["data"], False, "train")
    assert torch.equal(again["a"][0], b["a"][7])
    d, big = cfg["data"], 64 + 2 * 4
    w = {s: data._window(s, 512, 512, big, d) for s in data.SPLITS}
    assert w["train"][1] + big <= 512 - d["held_out_rows"] <= w["val"][0] == w["test"][0]
    assert w["val"][3] + big <= d["val_cols"] <= w["test"][2]


def test_illumination_changes_and_vignetting(scenes):
    cfg = tiny()
    b = data.make_pairs(scenes, list(range(8)), cfg["data"], False, "train")
    assert float((b["a"] - b["b"]).abs().mean()) > 0.05
    flat = torch.full((1, 8, 8), 0.8)
    out = data.vignette(flat, torch.Generator().manual_seed(3), {"photometric": 1.0, "vignette": 0.5})
    assert float(out.max()) <= 0.8 and float(out.min()) >= 0.8 * 0.5 - 1e-6 and float(out.min()) < 0.79


# --- training, resume, groups -----------------------------------------------------------------


def test_corner_error_in_the_step_equals_the_homography_corner_error():
    from learnreg.losses import corner_error

    gen = torch.Generator().manual_seed(0)
    p, g = torch.randn(4, 4, 2, generator=gen), torch.randn(4, 4, 2, generator=gen)
    assert torch.allclose((p - g).norm(dim=-1).mean(dim=-1).double(), corner_error(p, g, 64), atol=1e-5)


def test_resume_is_bit_identical_and_groups_do_not_change_an_arm(tmp_path, scenes):
    cfg = tiny()
    specs = [config.arm_spec(cfg, "l1", 0.2), config.arm_spec(cfg, "ncc")]
    full = loop.run_group(cfg, specs, 0, tmp_path / "full", progress=False, scenes=scenes)
    loop.run_group(cfg, specs, 0, tmp_path / "cut", progress=False, scenes=scenes, stop_after=3)  # ckpt at 2
    assert torch.load(loop.checkpoint_path(tmp_path / "cut", specs[0], 0), weights_only=True)["step"] == 2
    resumed = loop.run_group(cfg, specs, 0, tmp_path / "cut", resume=True, progress=False, scenes=scenes)
    alone = loop.run(cfg, specs[0], 0, tmp_path / "alone", progress=False, scenes=scenes)
    for other in (resumed[0], alone):
        for (n1, p1), (_n2, p2) in zip(full[0]["model"].state_dict().items(), other["model"].state_dict().items()):
            assert torch.equal(p1, p2), n1
        assert [r["loss"] for r in other["history"]] == [r["loss"] for r in full[0]["history"]]
    assert full[0]["eval"]["test"] == resumed[0]["eval"]["test"]
    with pytest.raises(CheckpointError, match="another config"):
        loop.run(tiny(**{"loss.ngf_eta": 0.3}), specs[0], 0, tmp_path / "cut", resume=True, progress=False)
    with pytest.raises(CheckpointError, match="holds arm"):
        path = loop.checkpoint_path(tmp_path / "cut", specs[1], 0)
        path.replace(loop.checkpoint_path(tmp_path / "cut", specs[1], 1))
        loop.run(cfg, specs[1], 1, tmp_path / "cut", resume=True, progress=False)


def test_refinement_lowers_the_error_and_pairs_do_not_interact(scenes):
    cfg = tiny(**{"data.photometric": 0.0, "refine.steps": 30})
    b = data.make_pairs(scenes, [1, 2, 3], cfg["data"], False, "val")
    crit = losses.Criterion("ncc", cfg["loss"], per_pair=True)
    delta, curve = refine.refine_batch(b["a"], b["b"], b["delta"], crit, 0.2, 0.1, 30)
    assert float(curve[-1].mean()) < 0.7 * float(curve[0].mean())
    d1, _ = refine.refine_batch(b["a"][1:2], b["b"][1:2], b["delta"][1:2], crit, 0.2, 0.1, 30)
    assert torch.allclose(d1, delta[1:2], atol=1e-5)


def test_lambda_is_chosen_on_validation_only():
    cands = {0.05: {"median_corner_error": 1.2}, 0.2: {"median_corner_error": 0.9}, 0.5: {"median_corner_error": 0.9}}
    assert report.choose(cands) == 0.2
    runs = {}
    cfg = tiny(**{"sweep.lambdas": [0.05, 0.2]})
    groups, cells = experiment.plan(cfg)
    for specs, seed in groups:
        for spec in specs:
            lam = spec["lambda"]
            val = {"median_corner_error": {0.05: 1.0, 0.2: 2.0}.get(lam, 3.0)}
            test = {"median_corner_error": {0.05: 9.0, 0.2: 0.1}.get(lam, 3.0)}  # test would pick 0.2
            for d in (val, test):
                d.update(mean_corner_error=1.0, share_below_0_5px=0.0, share_below_1px=0.0)
            runs[(config.arm_name(spec), seed)] = {
                "eval": {"val": val, "test": test},
                "wall_s": 1.0,
                "nondeterministic": [],
            }
    res = experiment.assemble(cfg, runs, cells)
    assert res["selection_network"]["network"]["lambda"] == {"l1": 0.05, "ncc": 0.05, "ngf": 0.05}
    assert res["network"]["l1+quality"]["lambda"] == 0.05


def test_cli_writes_results_json_with_every_field(tmp_path):
    spec = importlib.util.spec_from_file_location("fine_stage", ROOT / "train" / "fine_stage.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "res"
    args = ["--config", str(ROOT / "configs" / "fine_stage.toml"), "--out", str(out), "--no-progress"]
    for k, v in TINY.items():
        args += ["--set", f"{k}={json.dumps(v) if not isinstance(v, bool) else str(v).lower()}"]
    mod.main(args)
    res = json.loads((out / "results.json").read_text())
    for section in ("network", "network_distorted", "refinement"):
        assert res[section], section
        for arm in res[section].values():
            for key in report.METRICS:
                assert math.isfinite(arm[key]["mean"]) and math.isfinite(arm[key]["std"])
                assert len(arm[key]["per_seed"]) == len(arm["seeds"]) >= 2
    assert set(res["network"]) == {"l1", "l1+quality", "ncc", "ncc+quality", "ngf", "ngf+quality"}
    assert "claim_met" in res["verdict"]["network"] and "claim_met" in res["verdict"]["refinement"]
    assert res["threads"] == 1 and (out / "results.md").read_text().count("|") > 20


def test_merge_pools_seeds_of_arms_with_the_same_lambda():
    def part(seeds, med, lam_ncc):
        arm = lambda lam, m: {  # noqa: E731
            "peer": "x",
            "lambda": lam,
            "seeds": seeds,
            **report.seed_stats([{k: m for k in report.METRICS} for _ in seeds], seeds),
        }
        return {
            "device": "d",
            "identity": {},
            "config": tiny(**{"train.seeds": seeds}),
            "network": {"l1": arm(0.0, med), "ncc+quality": arm(lam_ncc, med)},
        }

    merged = report.merge_results([part([0, 1], 1.0, 0.5), part([3], 4.0, 0.2)])
    l1 = merged["network"]["l1"]
    assert l1["seeds"] == [0, 1, 3] and l1["median_corner_error"]["per_seed"] == [1.0, 1.0, 4.0]
    assert l1["median_corner_error"]["mean"] == pytest.approx(2.0) and "ncc+quality" not in merged["network"]
    with pytest.raises(ValueError, match="seed twice"):
        report.merge_results([part([0, 1], 1.0, 0.5), part([1], 4.0, 0.5)])
    with pytest.raises(ValueError, match="different configs"):
        other = part([5], 1.0, 0.5)
        other["config"]["loss"]["ngf_eta"] = 0.3
        report.merge_results([part([0, 1], 1.0, 0.5), other])
