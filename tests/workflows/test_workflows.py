"""End-to-end workflows: analyze_pair and `lensdist analyze`, and train/evaluate/reproduce on a
tiny protocol (small images, few pairs) so that CI exercises every command."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from kornia.io import write_image
from workflow_helpers import tiny_cli_folder

from lensdist_torch import analyze_pair
from lensdist_torch.config import config_from_dict
from lensdist_torch.core.images import load_scene
from lensdist_torch.data.shards import load_set

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "lensdist_torch" / "checkpoints" / "eigenspace_delta_avg_10ev.pt"
needs_shipped = pytest.mark.skipif(not SHIPPED.is_file(), reason="shipped checkpoints not present")


pytestmark = pytest.mark.usefixtures("one_thread_module")


def _views(shift=(20, 2)):
    s = load_scene("gravel")[0, 0]
    dy, dx = shift
    return s[10:330, 20:444].clone(), s[10 + dy : 330 + dy, 20 + dx : 444 + dx].clone()


def _write_png(path, img):
    write_image(str(path), (img.clamp(0, 1) * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous())


@needs_shipped
class TestAnalyze:
    @pytest.mark.parametrize("method", ["eigenspace", "regression", "selfcal"])
    def test_result_fields(self, method):
        a, b = _views()
        r, qmap = analyze_pair(a, b, method=method, return_map=True)
        # an undistorted pair: R, or (learned methods) "cannot tell" where they find distortion
        # that the self-calibration does not see
        assert r.class_label == "R" or (method != "selfcal" and r.class_label is None and r.estimated_class != "R")
        disagrees = r.class_label is None
        assert disagrees == any("self-calibration disagrees" in w for w in r.warnings) == (not r.in_domain)
        # the numbers of an answer; "cannot tell" keeps only the estimator's own (estimated_*)
        for key in ("estimated_delta_avg", "estimated_delta_max", "overlap", "motion_px"):
            assert isinstance(getattr(r, key), float)
        for key in ("delta_avg", "delta_max", "delta_avg_user_px"):
            assert isinstance(getattr(r, key), float) if r.class_label is not None else getattr(r, key) is None
        # eigen-space distances, per class, come with the eigen-space method only
        n_dist = 4 if method == "eigenspace" else 0
        assert len(r.distances) == n_dist and all(d >= 0 for d in r.distances)
        assert r.registration_ok is True
        assert qmap.shape == (1, 1, 40, 53)
        # same size as the analysis size: user pixels are analysis pixels
        assert r.user_px_per_analysis_px == pytest.approx(1.0)

    def test_selfcal_sees_no_distortion_in_an_undistorted_pair(self):
        a, b = _views()
        r = analyze_pair(a, b)  # default: selfcal
        assert r.method == "selfcal"
        assert r.class_label == "R" and r.delta_avg < 0.25 and not r.cannot_tell

    def test_tensor_shapes_and_colour(self):
        a, b = _views()
        r1 = analyze_pair(a, b, method="eigenspace")
        r2 = analyze_pair(a[None].expand(3, -1, -1), b[None, None], method="eigenspace")
        assert r1.class_label == r2.class_label
        assert r1.estimated_delta_avg == pytest.approx(r2.estimated_delta_avg, rel=1e-4)

    def test_user_pixels_scale(self):
        s = load_scene("gravel")
        a = torch.nn.functional.interpolate(s[..., 0:320, 0:424], scale_factor=2.0, mode="bilinear")[0]
        b = torch.nn.functional.interpolate(s[..., 16:336, 2:426], scale_factor=2.0, mode="bilinear")[0]
        r = analyze_pair(a, b)
        assert r.input_size == [640, 848] and r.class_label is not None
        assert r.analysed_region_user_px == [0, 0, 640, 848]  # the same aspect: the whole frame
        assert r.delta_avg_region_user_px == pytest.approx(2.0 * r.delta_avg)
        # over the whole frame from the coefficients, sampled at the analysis resolution
        assert r.delta_avg_user_px == pytest.approx(2.0 * r.delta_avg, rel=1e-6)

    def test_textureless_pair_warns(self):
        flat = torch.full((320, 424), 0.5)
        r = analyze_pair(flat, flat.clone(), method="eigenspace")
        assert r.registration_ok is False and r.in_domain is False
        assert any("registration failed" in w for w in r.warnings)

    def test_bad_input(self):
        a, b = _views()
        with pytest.raises(ValueError, match="same size"):
            analyze_pair(a, b[:-8])
        with pytest.raises(ValueError, match="method"):
            analyze_pair(a, b, method="magic")
        with pytest.raises(FileNotFoundError, match="not found"):
            analyze_pair("/nonexistent/a.png", "/nonexistent/b.png")

    def test_cli_json(self, tmp_path):
        a, b = _views()
        _write_png(tmp_path / "a.png", a)
        _write_png(tmp_path / "b.png", b)
        out = subprocess.run(
            [sys.executable, "-m", "lensdist_torch.cli", "analyze", str(tmp_path / "a.png"), str(tmp_path / "b.png"),
             "--json", "--method", "eigenspace"],
            capture_output=True, text=True, timeout=300, check=True,
        )
        r = json.loads(out.stdout)
        for key in ("class", "delta_avg", "delta_max", "distances", "registration_ok", "in_domain"):
            assert key in r
        assert r["class"] == "R" or (r["class"] is None and r["cannot_tell"] is True)  # undistorted (as above)


class TestTinyProtocol:
    def test_reproduce_report(self, tiny_run):
        out, res = tiny_run
        rep = json.loads((out / "reproduce.json").read_text())
        names = set(rep["settings"])
        assert {"5 EV, delta_max", "10 EV, delta_max", "5 EV, delta_avg", "10 EV, delta_avg"} <= names
        assert {"regression, delta_avg", "selfcal, delta_avg"} <= names
        for fig in rep["settings"].values():
            conf = torch.tensor(fig["confusion"])  # columns 1-4, R, cannot tell
            assert conf.shape == (5, 6) and int(conf.sum()) == 12
            assert fig["rate"] == pytest.approx(100.0 * float(conf[:, :5].diag().sum()) / 12)
            assert fig["cannot_tell"] == int(conf[:, 5].sum())
            assert fig["confident_wrong"] == int(conf[:, :5].sum() - conf[:, :5].diag().sum())
            assert int(conf[4].sum()) == 4  # the class-R pairs
        cal = rep["calibration"]
        assert {row["split"] for row in cal["ece"]} == {"validation", "test"}
        assert (out / "calibration.json").is_file() and (out / "validation" / "manifest.json").is_file()
        md = (out / "reproduce.md").read_text()
        assert "67.8 %" in md and "Table 2" in md
        for fig in rep["settings"].values():  # the trust table's shares, from the confusion matrix
            conf = torch.tensor(fig["confusion"])
            assert fig["right_or_cannot_tell_share"] == pytest.approx(
                100.0 * float(conf[:, :5].diag().sum() + conf[:, 5].sum()) / 12
            )

    def test_reproduce_tests_every_method_on_the_unseen_scene(self, tiny_run):
        out, _ = tiny_run
        rep = json.loads((out / "reproduce.json").read_text())
        unseen = rep["unseen"]
        assert unseen["scenes"] == ["brick"] and set(unseen["settings"]) == set(rep["settings"])
        test = load_set(out / "unseen", "test")
        seen = load_set(out / "data", "test")
        assert test["config"].protocol.scenes == ("brick",) and bool((test["scene"] == 0).all())
        assert torch.equal(test["k2"], seen["k2"]) and torch.equal(
            test["seed"], seen["seed"]
        )  # same draws, another scene
        for fig in unseen["settings"].values():
            assert int(torch.tensor(fig["confusion"]).sum()) == 12
        assert "## On a scene no method was fitted on: brick" in (out / "reproduce.md").read_text()

    def test_train_and_evaluate_cli(self, tiny_run, tmp_path):
        out, _ = tiny_run
        ck = tmp_path / "m.pt"
        cmd = [sys.executable, "-m", "lensdist_torch.cli"]
        r = subprocess.run(
            cmd
            + [
                "train",
                "--data",
                str(out / "data"),
                "--out",
                str(ck),
                "--metric",
                "delta_max",
                "--eigenvectors",
                "3",
                "--json",
            ],
            check=True,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert json.loads(r.stdout)["checkpoint"] == str(ck)
        raw = torch.load(ck, weights_only=True)
        assert raw["config"]["classifier"] == {
            **raw["config"]["classifier"],
            "metric": "delta_max",
            "n_eigenvectors": 3,
        }
        r = subprocess.run(
            cmd + ["evaluate", "--data", str(out / "data"), "--checkpoint", str(ck), "--out", str(tmp_path)],
            check=True,
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert "3 EV, delta_max" in r.stdout
        rep = json.loads((tmp_path / "evaluate.json").read_text())
        assert rep["settings"]["3 EV, delta_max"]["total"] == 12

    def test_evaluate_all_methods_cli(self, tiny_run, tmp_path):
        out, _ = tiny_run
        r = subprocess.run(
            [sys.executable, "-m", "lensdist_torch.cli", "evaluate", "--data", str(out / "data"),
             "--regression", str(out / "checkpoints" / "regression.pt"), "--selfcal", "--out", str(tmp_path)],
            check=True, capture_output=True, text=True, timeout=300,
        )
        rep = json.loads((tmp_path / "evaluate.json").read_text())
        assert {"regression, delta_avg", "selfcal, delta_avg", "selfcal, delta_max"} <= set(rep["settings"])
        assert "confident_share" in rep["settings"]["selfcal, delta_avg"]
        assert "selfcal, delta_avg" in r.stdout

    def test_evaluate_refuses_other_image_size(self, tiny_run, tmp_path):
        out, _ = tiny_run
        r = subprocess.run(
            [
                sys.executable,
                "-m",
                "lensdist_torch.cli",
                "evaluate",
                "--data",
                str(out / "data"),
                "--checkpoint",
                str(SHIPPED),
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        if SHIPPED.is_file():
            assert r.returncode == 2 and "image size" in r.stderr


    def test_reproduce_cli_reuses_shards(self, tiny_run, tmp_path, capsys):
        """On existing data, `lensdist reproduce` says how many shards it reused; --json prints
        the report alone on stdout, strict (no NaN)."""
        out, _ = tiny_run
        tiny_cli_folder(out, tmp_path)
        from lensdist_torch.cli import main

        code = main(
            ["reproduce", "--config", str(tmp_path / "tiny.toml"), "--out", str(tmp_path), "--workers", "1", "--json"]
        )
        r = capsys.readouterr()
        assert code == 0, r.err
        rep = json.loads(r.out, parse_constant=lambda c: pytest.fail(f"{c} in strict JSON"))
        assert rep["generation"]["written"] == 0 and "10 EV, delta_avg" in rep["settings"]
        assert "reused 3 shards" in r.err


class TestSequence:
    """`--sequence DIR`: pairs of consecutive real frames instead of synthetic motion."""

    def _frames(self, folder, n=4, step=6, size=(150, 200)):
        big = torch.nn.functional.interpolate(
            load_scene("gravel"), scale_factor=1.5, mode="bilinear", align_corners=True
        )
        folder.mkdir()
        for i in range(n):
            fr = big[0, :, step * i : step * i + size[0], 50 : 50 + size[1]]
            _write_png(folder / f"f{i:03d}.png", fr[0])
        return folder

    def test_consecutive_frames(self, tmp_path):
        from lensdist_torch.data.shards import generate, load_set

        cfg = config_from_dict(
            {
                "image": {"height": 96, "width": 128},
                "protocol": {"n_train": 6, "n_test_distorted": 2, "n_test_undistorted": 1, "shard_size": 6},
            }
        )
        frames = self._frames(tmp_path / "seq")
        generate(cfg, tmp_path / "out", scenes_dir=frames, sequence=True, progress=False)
        d = load_set(tmp_path / "out", "train")
        assert d["scene"].tolist() == [0, 1, 2, 0, 1, 2]  # pair i = frames (i mod 3, i mod 3 + 1)
        assert bool(d["converged"].all())
        assert bool(torch.isnan(d["motion"]).all())  # the real motion is unknown
        # the frames move 6 px down the scene: the registration sees a vertical translation
        ty = d["H"][:, 1, 2]
        assert bool((ty < -2).all()), ty

    def test_bad_sequences(self, tmp_path):
        from lensdist_torch.data.shards import load_scenes

        cfg = config_from_dict({"image": {"height": 96, "width": 128}})
        one = tmp_path / "one"
        one.mkdir()
        _write_png(one / "a.png", load_scene("gravel")[0, 0, :150, :200])
        with pytest.raises(ValueError, match="at least 2 frames"):
            load_scenes(cfg, one, sequence=True)
        _write_png(one / "b.png", load_scene("gravel")[0, 0, :160, :200])
        with pytest.raises(ValueError, match="b.png"):
            load_scenes(cfg, one, sequence=True)


def test_demo_cli(tmp_path):
    """`lensdist demo`: a 1 % scale error gives more errors in the outer third than the centre."""
    r = subprocess.run([sys.executable, "-m", "lensdist_torch.cli", "demo", "--out", str(tmp_path), "--json"],
                       capture_output=True, text=True, timeout=300, check=True)
    summary = json.loads(r.stdout)  # --json: one JSON object and nothing else on stdout
    assert summary["blocks"] == 40 * 53
    assert summary["max_offset_px"] == pytest.approx(0.01 * (211.5**2 + 159.5**2) ** 0.5, rel=1e-3)
    assert summary["mean_error_ratio_outer_third"] > 2 * summary["mean_error_ratio_centre_third"]
    assert 0.0 <= summary["quality_index"] <= 1.0


def test_cli_reports_bad_input_clearly(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "lensdist_torch.cli", "analyze", str(tmp_path / "no.png"), str(tmp_path / "no.png")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 2 and "not found" in r.stderr
