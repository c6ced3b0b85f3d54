"""Delta regression (lensdist_torch.regression): fit, prediction, confidence, checkpoints."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.classify.eigenspace import CheckpointError, EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import LensdistConfig


def _synthetic(n, seed=0, n_features=40):
    """Features whose pattern grows with Delta (plus noise); Delta_max ~ 5.5 Delta_avg."""
    g = torch.Generator().manual_seed(seed)
    d_avg = torch.rand(n, generator=g, dtype=torch.float64) * 14.4
    basis = torch.rand(2, n_features, generator=g, dtype=torch.float64)
    x = (d_avg[:, None] / 14.4) * basis[0] + (d_avg[:, None] / 14.4) ** 2 * basis[1]
    x = x + 0.01 * torch.randn(n, n_features, generator=g, dtype=torch.float64)
    return (x / 2).float().clamp(-0.1, 1.1), d_avg, 5.5 * d_avg  # quality-map range


def test_fit_predicts_deltas_and_classes():
    x, da, dm = _synthetic(400)
    reg = DeltaRegressor(40, n_components=4, k=8).fit(x[:300], da[:300], dm[:300])
    with torch.no_grad():
        r = reg(x[300:])
    rmse = (r.delta_avg - da[300:]).pow(2).mean().sqrt()
    assert rmse < 0.5
    assert (r.delta_max - dm[300:]).pow(2).mean().sqrt() < 2.5
    assert r.class_avg.shape == (100,)
    # R (index 4) exactly where the predicted Delta_avg is below the no-distortion threshold
    assert torch.equal(r.class_avg == 4, r.delta_avg < LensdistConfig().analysis.no_distortion_px)
    assert torch.isfinite(r.std_avg).all() and ((r.confidence > 0) & (r.confidence <= 1)).all()
    assert r.confident.float().mean() > 0.9


def test_uninformative_features_are_not_confident():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(300, 20, generator=g)  # features unrelated to Delta
    da = torch.rand(300, generator=g, dtype=torch.float64) * 14.4
    reg = DeltaRegressor(20, n_components=4, k=16).fit(x, da, 5.5 * da)
    r = reg(torch.rand(50, 20, generator=g))
    assert r.confident.float().mean() < 0.2


def test_save_load_round_trip(tmp_path):
    x, da, dm = _synthetic(200, seed=2)
    reg = DeltaRegressor(40, LensdistConfig(), n_components=5, k=4).fit(x, da, dm)
    path = tmp_path / "reg.pt"
    reg.save(path, extra={"note": "test"})
    back = DeltaRegressor.load(path, expected=LensdistConfig())
    assert back.extra == {"note": "test"} and back.n_components == 5 and back.k == 4
    a, b = reg(x[:17]), back(x[:17])
    for f in a._fields:
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_bad_checkpoints(tmp_path):
    clf = EigenSpaceClassifier(n_features=12)
    clf.save(tmp_path / "eig.pt")
    with pytest.raises(CheckpointError):
        DeltaRegressor.load(tmp_path / "eig.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        DeltaRegressor.load(tmp_path / "junk.pt")
    with pytest.raises(RuntimeError):
        DeltaRegressor(12)(torch.rand(2, 12))
    with pytest.raises(ValueError):
        DeltaRegressor(12).fit(torch.rand(10, 11), torch.rand(10), torch.rand(10))


@pytest.mark.bad_input
@pytest.mark.parametrize("field", ["n_features", "n_components", "k"])
@pytest.mark.parametrize("value", [True, 2.5, 0, -3, "8"])
def test_sizes_must_be_positive_integers(field, value):
    # the third issue-19 audit: k=True was taken as k = 1 (a checkpoint's loader refuses a bool k)
    kwargs = {"n_features": 12, "n_components": 3, "k": 4, field: value}
    n_features = kwargs.pop("n_features")
    with pytest.raises(ValueError, match=rf"^{field} must be a positive integer, got {value!r}$".replace("(", r"\(")):
        DeltaRegressor(n_features, **kwargs)
