"""`lensdist train` on hostile paths and configs (issue 19): an --out that names a data shard or
any file that is not a checkpoint of the same kind is refused and left as it was; a --config
that disagrees with the data on what made the maps is refused (one line, exit 2), and the
checkpoint records the data's config.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
import torch
from generated_sets import generate_once

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.cli import main
from lensdist_torch.config import config_from_dict, config_to_dict
from lensdist_torch.data.shards import shard_path
from lensdist_torch.workflows.evaluate import fit_classifier

pytestmark = pytest.mark.bad_input

SMALL = {
    "quality": {"theta_e": 0.06},
    "image": {"height": 96, "width": 128},
    "protocol": {"n_train": 40, "n_test_distorted": 4, "n_test_undistorted": 2, "shard_size": 20},
}
CFG = config_from_dict(SMALL)


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return generate_once(tmp_path_factory, "train", CFG, folder="mid")[0]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _toml(path: Path, theta_e: float, n_eigenvectors: int = 1) -> Path:
    path.write_text(
        f"[quality]\ntheta_e = {theta_e}\n[image]\nheight = 96\nwidth = 128\n"
        f"[classifier]\nn_eigenvectors = {n_eigenvectors}\n"
        "[protocol]\nn_train = 40\nn_test_distorted = 4\nn_test_undistorted = 2\nshard_size = 20\n"
    )
    return path


def test_out_naming_a_data_shard_is_refused(data, capsys):
    """The audit's case: `train --data mid --out mid/train/shard-00000.pt` overwrote the shard."""
    shard = shard_path(data, "train", 0)
    before = _digest(shard)
    code = main(["train", "--data", str(data), "--eigenvectors", "1", "--out", str(shard)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "--out" in err and "inside the lensdist data set" in err
    assert _digest(shard) == before


def test_out_naming_another_file_is_refused(data, tmp_path, capsys):
    for name, content in (("img.pt", b"\x89PNG\r\n\x1a\n not a checkpoint"), ("empty.pt", b"")):
        target = tmp_path / name
        target.write_bytes(content)
        assert main(["train", "--data", str(data), "--eigenvectors", "1", "--out", str(target)]) == 2
        assert "refusing to overwrite" in capsys.readouterr().err
        assert target.read_bytes() == content


def test_library_save_refuses_other_kinds(data, tmp_path):
    """A regressor checkpoint is not replaced by an eigen-space one, nor the other way round."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(40, 12, generator=g)
    reg = DeltaRegressor(12, n_components=3, k=4).fit(x, torch.rand(40), torch.rand(40))
    eig = EigenSpaceClassifier(12, config_from_dict({"classifier": {"n_eigenvectors": 1}})).fit(
        x, torch.arange(40) % 4, torch.rand(40)
    )
    reg.save(tmp_path / "r.pt")
    eig.save(tmp_path / "e.pt")
    eig.save(tmp_path / "e.pt")  # its own kind: replaced
    for model, other in ((eig, "r.pt"), (reg, "e.pt")):
        before = _digest(tmp_path / other)
        with pytest.raises(
            FileExistsError,
            match=f"refusing to overwrite .*{other}: it is not a lensdist-(eigenspace|delta-regression) checkpoint",
        ):
            model.save(tmp_path / other)
        assert _digest(tmp_path / other) == before


def test_config_that_disagrees_with_the_data_is_refused(data, tmp_path, capsys):
    """The audit's case: the checkpoint recorded --config's theta_e while its tensors were the data's."""
    out = tmp_path / "c.pt"
    code = main(
        ["train", "--data", str(data), "--config", str(_toml(tmp_path / "other.toml", 0.05)), "--out", str(out)]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "quality.theta_e (0.05 here, 0.06 in the data)" in err
    assert not out.exists()


def test_checkpoint_records_the_data_config(data, tmp_path, capsys):
    """Without --config, and with one that changes only the classifier: the data's quality thresholds."""
    for args in ([], ["--config", str(_toml(tmp_path / "same.toml", 0.06, n_eigenvectors=1))]):
        out = tmp_path / f"c{len(args)}.pt"
        assert main(["train", "--data", str(data), "--eigenvectors", "1", "--out", str(out), *args]) == 0, (
            capsys.readouterr().err
        )
        model = EigenSpaceClassifier.load(out)
        assert model.config.quality == CFG.quality and model.config.image == CFG.image
        assert config_to_dict(model.config)["protocol"] == config_to_dict(CFG)["protocol"]


def test_fit_classifier_names_the_field(data):
    from lensdist_torch.data.shards import load_set

    train = load_set(data, "train")
    other = config_from_dict({**SMALL, "image": {"height": 128, "width": 160}})
    with pytest.raises(ValueError, match=r"image.height \(128 here, 96 in the data\)"):
        fit_classifier(train, other, n_eigenvectors=1)


def test_evaluate_out_inside_the_data_folder_is_refused(data, capsys):
    """Issue 19 audit: `lensdist evaluate --data data --out data/train` wrote its report into the shards' folder."""
    before = sorted(p.name for p in (data / "train").iterdir())
    code = main(["evaluate", "--data", str(data), "--selfcal", "--out", str(data / "train")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--out" in err and "inside the lensdist data set" in err
    assert sorted(p.name for p in (data / "train").iterdir()) == before


@pytest.mark.parametrize("where", ["train", "train/sub", "."])
def test_outputs_inside_a_data_set_are_refused(data, tmp_path, capsys, where):
    """Issue 19 audit: `--save-map data/train/map.png` and `undistort --out data/train` wrote into a data set."""
    from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
    from lensdist_torch.core.png import encode_png, to_uint8

    pair = []
    for i, f in enumerate(synthetic_sequence(2, 0.0, 0.0, size=(64, 96))[0]):
        (tmp_path / f"f{i}.png").write_bytes(encode_png(to_uint8(f)))
        pair.append(str(tmp_path / f"f{i}.png"))
    before = sorted(str(p.relative_to(data)) for p in data.rglob("*"))
    target = data / where
    for argv in (["analyze", *pair, "--save-map", str(target / "map.png")],
                 ["demo", "--out", str(target)],
                 ["undistort", str(tmp_path), "--k2", "1e-7", "--k4", "0", "--out", str(target / "u")]):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1 and "inside the lensdist data set" in err, (argv, err)
    assert sorted(str(p.relative_to(data)) for p in data.rglob("*")) == before
    # the data set itself stays generate's to re-check and resume
    assert main(["generate", "--config", str(_toml(tmp_path / "c.toml", 0.06)), "--out", str(data), "--quiet"]) == 0
