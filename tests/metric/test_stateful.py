"""Stateful metrics: RegistrationQualityMetric (and its torchmetrics twin where torchmetrics is
installed), and reset() of ConfusionMatrix and ClassRMSE."""

from __future__ import annotations

import importlib.util
import sys
import types

import pytest
import torch
from metric_helpers import textured

import lensdist_torch.metric.stateful as stateful
from lensdist_torch import ClassRMSE, ConfusionMatrix, QualityConfig, quality_map, registration_quality
from lensdist_torch.metric.stateful import QualityMetricResult, RegistrationQualityMetric

pytestmark = pytest.mark.usefixtures("one_thread_module")


def pairs(n: int = 11, h: int = 37, w: int = 45, seed: int = 0):
    """n pairs of different misregistrations, and masks (one pair fully invalid on one side)."""
    img1 = textured(n, h, w, seed=seed, dtype=torch.float32)
    shifts = [(i % 3, (i * 2) % 3) for i in range(n)]
    img2 = torch.stack([torch.roll(img1[i], s, dims=(-2, -1)) for i, s in enumerate(shifts)])
    valid = torch.ones(n, 1, h, w)
    valid[::4, ..., :, : w // 2] = 0
    return img1, img2, valid


def feed(metric, img1, img2, valid, sizes):
    i = 0
    for s in sizes:
        metric.update(img1[i : i + s], img2[i : i + s], valid[i : i + s])
        i += s
    assert i == img1.shape[0]
    return metric.compute()


def functional(img1, img2, valid):
    res = registration_quality(img1, img2, valid)
    return res.quality_index.double().mean(), res.registration_map.double().mean(dim=0)


class TestRegistrationQualityMetric:
    @pytest.mark.parametrize("sizes", [[1, 3, 7], [7, 3, 1], [1] * 11, [3, 3, 3, 2], [11]])
    def test_equals_the_functional_mean_whatever_the_batches(self, sizes):
        img1, img2, valid = pairs()
        q, m = functional(img1, img2, valid)
        res = feed(RegistrationQualityMetric(), img1, img2, valid, sizes)
        assert isinstance(res, QualityMetricResult)
        assert int(res.num_pairs) == 11
        assert res.registration_map.shape == (1, 5, 6)  # 37 x 45 padded to 40 x 48
        torch.testing.assert_close(res.quality_index, q, atol=1e-7, rtol=0)
        torch.testing.assert_close(res.registration_map, m, atol=1e-7, rtol=0)
        assert 0 < float(res.quality_index) < 1

    def test_weighted_by_pairs_not_batches(self):
        img1, img2, valid = pairs()
        per_pair = registration_quality(img1, img2, valid).quality_index.double()
        res = feed(RegistrationQualityMetric(), img1, img2, valid, [1, 10])
        batch_mean = (per_pair[:1].mean() + per_pair[1:].mean()) / 2
        assert abs(float(res.quality_index - per_pair.mean())) < 1e-7
        assert abs(float(res.quality_index - batch_mean)) > 1e-4

    def test_reset(self):
        img1, img2, valid = pairs()
        metric = RegistrationQualityMetric()
        first = feed(metric, img1, img2, valid, [1, 3, 7])
        metric.reset()
        assert int(metric.num_pairs) == 0 and float(metric.quality_sum) == 0.0
        with pytest.raises(RuntimeError, match="update"):
            metric.compute()
        # after a reset another image size is fine, and the old pairs are forgotten
        metric.update(img1[:2, ..., :16, :16], img1[:2, ..., :16, :16])
        res = metric.compute()
        assert int(res.num_pairs) == 2 and float(res.quality_index) == 1.0
        assert res.registration_map.shape == (1, 2, 2)
        metric.reset()
        again = feed(metric, img1, img2, valid, [7, 3, 1])
        torch.testing.assert_close(again.quality_index, first.quality_index, atol=1e-12, rtol=0)

    def test_forward_returns_the_batch_and_accumulates(self):
        img1, img2, valid = pairs()
        metric = RegistrationQualityMetric()
        batch = metric(img1[:3], img2[:3], valid[:3])
        q, m = functional(img1[:3], img2[:3], valid[:3])
        torch.testing.assert_close(batch.quality_index, q, atol=1e-7, rtol=0)
        torch.testing.assert_close(batch.registration_map, m, atol=1e-7, rtol=0)
        metric(img1[3:], img2[3:], valid[3:])
        torch.testing.assert_close(metric.compute().quality_index, functional(img1, img2, valid)[0], atol=1e-7, rtol=0)

    def test_buffers_state_dict_and_map_shape(self):
        img1, img2, valid = pairs()
        metric = RegistrationQualityMetric(QualityConfig(theta_g=0.03))
        feed(metric, img1, img2, valid, [4, 7])
        assert set(dict(metric.named_buffers())) == {"quality_sum", "map_sum", "num_pairs"}
        fresh = RegistrationQualityMetric(QualityConfig(theta_g=0.03))  # map shape not known yet
        fresh.load_state_dict(metric.state_dict())
        for a, b in zip(fresh.compute(), metric.compute()):
            assert torch.equal(a, b)
        sized = RegistrationQualityMetric(map_shape=(5, 6))
        assert sized.map_sum.shape == (1, 5, 6)
        feed(sized, img1, img2, valid, [11])
        plain = feed(RegistrationQualityMetric(), img1, img2, valid, [11])
        assert torch.equal(sized.compute().registration_map, plain.registration_map)
        assert "block_size=8" in repr(metric)

    def test_config_and_validate_reach_the_map(self):
        img1, img2, valid = pairs(n=3)
        cfg = QualityConfig(theta_g=0.05)
        res = feed(RegistrationQualityMetric(cfg, validate=False), img1, img2, valid, [3])
        torch.testing.assert_close(
            res.registration_map, quality_map(img1, img2, valid, cfg).double().mean(0), atol=1e-7, rtol=0
        )

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
    def test_follows_to_device(self):
        img1, img2, valid = pairs()
        metric = RegistrationQualityMetric().cuda()
        assert metric.map_sum.is_cuda and metric.num_pairs.is_cuda
        res = feed(metric, img1.cuda(), img2.cuda(), valid.cuda(), [1, 3, 7])
        assert res.registration_map.is_cuda
        cpu = feed(RegistrationQualityMetric(), img1, img2, valid, [11])
        torch.testing.assert_close(res.quality_index.cpu(), cpu.quality_index, atol=1e-3, rtol=0)
        metric.reset()
        assert metric.map_sum.is_cuda

    @pytest.mark.bad_input
    def test_bad_inputs(self):
        metric = RegistrationQualityMetric()
        metric.update(torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 16))
        with pytest.raises(ValueError, match="one shape.*reset"):
            metric.update(torch.rand(1, 1, 24, 16), torch.rand(1, 1, 24, 16))
        with pytest.raises(ValueError, match="map_shape"):
            RegistrationQualityMetric(map_shape=(5,))
        with pytest.raises(ValueError, match="map_shape"):
            RegistrationQualityMetric(map_shape=(0, 3))
        with pytest.raises(ValueError, match="data_range=255"):
            RegistrationQualityMetric().update(255 * torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 16))


# ----------------------------------------------------------------------------- torchmetrics


def test_pure_class_needs_no_torchmetrics():
    if importlib.util.find_spec("torchmetrics") is None:
        assert not hasattr(stateful, "RegistrationQualityTorchMetric")
        assert "RegistrationQualityTorchMetric" not in stateful.__all__
    assert RegistrationQualityMetric.__bases__ == (torch.nn.Module,)


def _run_torchmetric(cls):
    img1, img2, valid = pairs()
    metric = cls()
    res = feed(metric, img1, img2, valid, [1, 3, 7])
    q, m = functional(img1, img2, valid)
    torch.testing.assert_close(res.quality_index, q, atol=1e-7, rtol=0)
    torch.testing.assert_close(res.registration_map, m, atol=1e-7, rtol=0)
    metric.reset()
    res = feed(metric, img1, img2, valid, [11])
    torch.testing.assert_close(res.quality_index, q, atol=1e-7, rtol=0)


def test_torchmetrics_metric():
    pytest.importorskip("torchmetrics")
    _run_torchmetric(stateful.RegistrationQualityTorchMetric)


def test_torchmetrics_metric_against_a_stub(monkeypatch):
    """The guarded class, defined against a minimal stand-in for ``torchmetrics.Metric``
    (add_state, reset): its update/compute/reset logic runs where torchmetrics is absent."""

    class Metric(torch.nn.Module):
        def __init__(self, **kwargs):
            super().__init__()
            self._defaults, self._reductions = {}, {}

        def add_state(self, name, default, dist_reduce_fx=None, persistent=False):
            assert dist_reduce_fx == "sum"
            self._defaults[name], self._reductions[name] = default.clone(), dist_reduce_fx
            setattr(self, name, default.clone())

        def reset(self):
            for name, default in self._defaults.items():
                setattr(self, name, default.clone())

    stub = types.ModuleType("torchmetrics")
    stub.Metric = Metric
    monkeypatch.setitem(sys.modules, "torchmetrics", stub)
    spec = importlib.util.spec_from_file_location("_stateful_with_stub", stateful.__file__)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert "RegistrationQualityTorchMetric" in module.__all__
    cls = module.RegistrationQualityTorchMetric
    assert cls.higher_is_better and not cls.is_differentiable
    metric = cls(map_shape=(5, 6))
    assert metric.map_sum.shape == (1, 5, 6) and set(metric._reductions) == {"quality_sum", "map_sum", "num_pairs"}
    _run_torchmetric(cls)


# ----------------------------------------------------------------------------- classification


class TestClassificationReset:
    def test_confusion_matrix(self):
        cm = ConfusionMatrix()
        cm.update(torch.tensor([0, 1, 4, 4]), torch.tensor([0, 2, 4, 3]))
        assert int(cm.compute().sum()) == 4 and cm.rate() == 0.5
        cm.reset()
        assert int(cm.compute().sum()) == 0 and cm.compute().shape == (5, 5)
        assert cm.rate() != cm.rate()  # NaN when empty
        cm.update(torch.tensor([1]), torch.tensor([1]))
        assert cm.compute()[1, 1] == 1 and cm.rate() == 1.0

    def test_compute_is_a_copy(self):
        cm = ConfusionMatrix(2)
        cm.update(torch.tensor([0]), torch.tensor([0]))
        snapshot = cm.compute()
        cm.reset()
        assert int(snapshot.sum()) == 1

    def test_class_rmse(self):
        m = ClassRMSE()
        m.update(torch.tensor([1.0, 2.0, 9.0]), torch.tensor([0.0, 0.0, 0.0]), torch.tensor([0, 1, 4]))
        assert m.compute()["n"] == [1, 1, 0, 0]
        m.reset()
        out = m.compute()
        assert out["n"] == [0, 0, 0, 0]
        assert all(v != v for v in out["rmse"])  # NaN for empty classes
        m.update(torch.tensor([3.0]), torch.tensor([1.0]), torch.tensor([2]))
        out = m.compute()
        assert out["rmse"][2] == 2.0 and out["bias"][2] == 2.0 and out["n"] == [0, 0, 1, 0]
