"""Stateful metrics: RegistrationQualityMetric (a torchmetrics.Metric where torchmetrics is
installed, an nn.Module with buffers where it is not), and reset() of ConfusionMatrix and ClassRMSE."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import torch
from metric_helpers import textured

import lensdist_torch.metric.stateful as stateful
from lensdist_torch import ClassRMSE, ConfusionMatrix, QualityConfig, quality_map, registration_quality
from lensdist_torch.metric.stateful import QualityMetricResult, RegistrationQualityMetric


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
    res = metric.compute_details()
    index = metric.compute()  # what MetricCollection and log_dict see: the index alone
    assert isinstance(index, torch.Tensor) and index.dim() == 0 and torch.equal(index, res.quality_index)
    return res


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
        with pytest.raises(RuntimeError, match="update"):
            metric.compute_details()
        # after a reset another image size is fine, and the old pairs are forgotten
        metric.update(img1[:2, ..., :16, :16], img1[:2, ..., :16, :16])
        res = metric.compute_details()
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
        assert batch.shape == () and 0.3 < float(batch) < 0.9
        torch.testing.assert_close(batch, q, atol=1e-7, rtol=0)
        torch.testing.assert_close(metric.compute_details().registration_map, m, atol=1e-7, rtol=0)
        later = metric(img1[3:], img2[3:], valid[3:])
        torch.testing.assert_close(later, functional(img1[3:], img2[3:], valid[3:])[0], atol=1e-7, rtol=0)
        torch.testing.assert_close(metric.compute(), functional(img1, img2, valid)[0], atol=1e-7, rtol=0)

    def test_buffers_state_dict_and_map_shape(self):
        img1, img2, valid = pairs()
        metric = RegistrationQualityMetric(QualityConfig(theta_g=0.03))
        feed(metric, img1, img2, valid, [4, 7])
        assert set(metric.state_dict()) == {"quality_sum", "map_sum", "num_pairs", "num_skipped"}
        fresh = RegistrationQualityMetric(QualityConfig(theta_g=0.03))  # map shape not known yet
        fresh.load_state_dict(metric.state_dict())
        for a, b in zip(fresh.compute_details(), metric.compute_details()):
            assert torch.equal(a, b)
        sized = RegistrationQualityMetric(map_shape=(5, 6))
        assert sized.map_sum.shape == (1, 5, 6)
        feed(sized, img1, img2, valid, [11])
        plain = feed(RegistrationQualityMetric(), img1, img2, valid, [11])
        assert torch.equal(sized.compute_details().registration_map, plain.registration_map)
        assert "block_size=8" in repr(metric)

    def test_config_and_validate_reach_the_map(self):
        img1, img2, valid = pairs(n=3)
        cfg = QualityConfig(theta_g=0.05)
        res = feed(RegistrationQualityMetric(cfg, validate=False), img1, img2, valid, [3])
        torch.testing.assert_close(
            res.registration_map, quality_map(img1, img2, valid, config=cfg).double().mean(0), atol=1e-7, rtol=0
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


# ----------------------------------------------------------------------------- dtype casts (issue 19)


CASTS = {
    "half": lambda m: m.half(),
    "float": lambda m: m.float(),
    "bfloat16": lambda m: m.bfloat16(),
    "double": lambda m: m.double(),
    "to(float16)": lambda m: m.to(torch.float16),
    "to(dtype=float32)": lambda m: m.to(dtype=torch.float32),
    "type(float16)": lambda m: m.type(torch.float16),
}


class TestAccumulatorDtypes:
    @pytest.mark.bad_input
    @pytest.mark.parametrize("cast", sorted(CASTS))
    def test_a_cast_keeps_float64_sums_and_int64_counts(self, cast):
        img1, img2, valid = pairs(n=6, h=16, w=24)
        metric = CASTS[cast](RegistrationQualityMetric())
        for _ in range(2):  # after updates and after a reset too
            for name in ("quality_sum", "map_sum"):
                assert getattr(metric, name).dtype == torch.float64, name
            for name in ("num_pairs", "num_skipped"):
                assert getattr(metric, name).dtype == torch.long, name
            feed(metric, img1, img2, valid, [3, 3])
            metric = CASTS[cast](metric)
            assert metric.map_sum.dtype == torch.float64
            metric.reset()

    @pytest.mark.bad_input
    def test_a_half_metric_reproduces_the_float64_result(self):
        """The issue's case: float16 sums stop growing (0.668 for 0.559 after 3000 updates)."""
        img1, img2, valid = pairs(n=6, h=16, w=24)
        plain, half = RegistrationQualityMetric(), RegistrationQualityMetric().half()
        for i in range(300):
            j = i % 6
            for m in (plain, half):
                m.update(img1[j : j + 1], img2[j : j + 1], valid[j : j + 1])
        a, b = plain.compute_details(), half.compute_details()
        assert int(b.num_pairs) == 300
        assert abs(float(a.quality_index) - float(b.quality_index)) < 1e-12
        torch.testing.assert_close(b.registration_map, a.registration_map, atol=1e-12, rtol=0)
        # and the hand-worked mean: 50 times each of the 6 pairs
        q, _ = functional(img1, img2, valid)
        assert abs(float(b.quality_index) - float(q)) < 1e-6

    @pytest.mark.bad_input
    def test_device_moves_still_apply(self):
        metric = RegistrationQualityMetric(map_shape=(2, 3)).to("meta", torch.float16)
        for name in ("quality_sum", "map_sum", "num_pairs", "num_skipped"):
            assert getattr(metric, name).is_meta, name
        assert metric.quality_sum.dtype == torch.float64 and metric.map_sum.shape == (1, 2, 3)


# ----------------------------------------------------------------------------- loading a state (issue 19)


def _state(**changes):
    img1, img2, valid = pairs(n=4, h=16, w=24)
    metric = RegistrationQualityMetric()
    feed(metric, img1, img2, valid, [4])
    state = metric.state_dict()
    state.update(changes)
    return metric, state


class TestLoadedState:
    @pytest.mark.bad_input
    @pytest.mark.parametrize(
        "field,value,exc,words",
        [
            ("num_pairs", torch.tensor(-3), ValueError, ["num_pairs", ">= 0", "-3"]),
            ("num_pairs", torch.tensor(4.0), ValueError, ["num_pairs", "integer"]),
            ("num_pairs", torch.tensor([4]), ValueError, ["num_pairs", "0-dim"]),
            ("num_pairs", torch.tensor(True), ValueError, ["num_pairs", "integer"]),
            ("num_pairs", 4, TypeError, ["num_pairs", "tensor"]),
            ("num_pairs", torch.tensor(5), ValueError, ["quality_sum", "num_pairs (5)"]),
            ("num_skipped", torch.tensor(-1), ValueError, ["num_skipped", ">= 0"]),
            ("quality_sum", torch.tensor(float("nan"), dtype=torch.float64), ValueError, ["quality_sum", "NaN"]),
            ("quality_sum", torch.tensor(float("inf"), dtype=torch.float64), ValueError, ["quality_sum", "Inf"]),
            ("quality_sum", torch.tensor(4.5, dtype=torch.float64), ValueError, ["quality_sum", "[0, 4]"]),
            ("quality_sum", torch.tensor(-0.5, dtype=torch.float64), ValueError, ["quality_sum", "[0, 4]"]),
            ("quality_sum", torch.tensor(3, dtype=torch.long), ValueError, ["quality_sum", "float"]),
            ("map_sum", torch.full((1, 2, 3), float("nan"), dtype=torch.float64), ValueError, ["map_sum", "NaN"]),
            ("map_sum", torch.full((1, 2, 3), 5.0, dtype=torch.float64), ValueError, ["map_sum", "[0, 4]"]),
            ("map_sum", torch.full((1, 2, 3), -1.0, dtype=torch.float64), ValueError, ["map_sum", "[0, 4]"]),
            ("map_sum", torch.zeros((2, 3), dtype=torch.float64), ValueError, ["map_sum", "(1, h, w)"]),
            ("map_sum", torch.zeros((), dtype=torch.float64), ValueError, ["map_sum", "num_pairs 4"]),
        ],
    )
    def test_a_state_no_update_can_give_is_refused(self, field, value, exc, words):
        _, state = _state(**{field: value})
        target = RegistrationQualityMetric()
        before = {k: v.clone() for k, v in target.state_dict().items()}
        with pytest.raises(exc) as info:
            target.load_state_dict(state)
        message = str(info.value)
        assert "\n" not in message
        for w in words:
            assert w in message, (w, message)
        after = target.state_dict()  # nothing loaded
        assert set(after) == set(before) and all(torch.equal(after[k], before[k]) for k in before)

    @pytest.mark.bad_input
    def test_sums_that_do_not_match_the_count_are_refused(self):
        """Within the ranges, but quality_sum + mean(map_sum) != num_pairs: a tampered sum."""
        metric, state = _state()
        state["quality_sum"] = state["quality_sum"] - 0.25
        assert 0 <= float(state["quality_sum"]) <= 4
        with pytest.raises(ValueError, match=r"quality_sum .* does not match map_sum"):
            RegistrationQualityMetric().load_state_dict(state)

    @pytest.mark.bad_input
    def test_a_map_of_another_shape_than_map_shape_is_refused(self):
        _, state = _state()
        assert state["map_sum"].shape == (1, 2, 3)
        with pytest.raises(ValueError, match=r"map_sum must have shape \(1, 5, 6\).*map_shape"):
            RegistrationQualityMetric(map_shape=(5, 6)).load_state_dict(state)

    def test_good_states_load(self):
        metric, state = _state()
        for target in (RegistrationQualityMetric(), RegistrationQualityMetric(map_shape=(2, 3))):
            target.load_state_dict(state)
            for a, b in zip(target.compute_details(), metric.compute_details()):
                assert torch.equal(a, b)
        # a fresh metric's state, and one saved before num_skipped existed (no pair skipped)
        RegistrationQualityMetric().load_state_dict(RegistrationQualityMetric().state_dict())
        old = {k: v for k, v in state.items() if k != "num_skipped"}
        target = RegistrationQualityMetric()
        target.load_state_dict(old)
        assert int(target.num_skipped) == 0 and int(target.compute_details().num_pairs) == 4


# ----------------------------------------------------------------------------- torchmetrics


def test_one_class_a_torchmetrics_metric_where_installed():
    assert "RegistrationQualityTorchMetric" not in stateful.__all__
    assert not hasattr(stateful, "RegistrationQualityTorchMetric")
    if importlib.util.find_spec("torchmetrics") is None:
        assert RegistrationQualityMetric.__mro__[1].__bases__ == (torch.nn.Module,)
    else:
        import torchmetrics

        assert issubclass(RegistrationQualityMetric, torchmetrics.Metric)
        metric = RegistrationQualityMetric(sync_on_compute=False)  # the Metric's options pass through
        assert metric.sync_on_compute is False and metric._reductions["map_sum"] is not None


def _without_torchmetrics(monkeypatch):
    """The metric's class as it is defined where torchmetrics cannot be imported."""
    monkeypatch.setitem(sys.modules, "torchmetrics", None)  # import raises ImportError
    modules = {}
    for name in ("_state", "stateful"):
        full = f"lensdist_torch.metric.{name}"
        spec = importlib.util.spec_from_file_location(full, importlib.util.find_spec(full).origin)
        modules[name] = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, full, modules[name])
        spec.loader.exec_module(modules[name])
    return modules["stateful"].RegistrationQualityMetric


def test_without_torchmetrics_the_same_class_on_nn_module(monkeypatch):
    cls = _without_torchmetrics(monkeypatch)
    assert cls.__mro__[1].__bases__ == (torch.nn.Module,)
    assert cls.higher_is_better and not cls.is_differentiable
    img1, img2, valid = pairs()
    q, m = functional(img1, img2, valid)
    metric = cls()
    res = feed(metric, img1, img2, valid, [1, 3, 7])
    torch.testing.assert_close(res.quality_index, q, atol=1e-7, rtol=0)
    torch.testing.assert_close(res.registration_map, m, atol=1e-7, rtol=0)
    assert set(dict(metric.named_buffers())) == {"quality_sum", "map_sum", "num_pairs", "num_skipped"}
    fresh = cls()  # a lazily shaped map takes the saved shape
    fresh.load_state_dict(metric.state_dict())
    assert torch.equal(fresh.compute_details().registration_map, res.registration_map)
    metric.reset()
    assert int(metric.num_pairs) == 0 and metric.map_sum.shape == ()
    res = feed(metric, img1, img2, valid, [11])
    torch.testing.assert_close(res.quality_index, q, atol=1e-7, rtol=0)
    batch = metric(img1[:3], img2[:3], valid[:3])  # forward: the batch's index, and accumulates
    torch.testing.assert_close(batch, functional(img1[:3], img2[:3], valid[:3])[0], atol=1e-7, rtol=0)
    assert int(metric.num_pairs) == 14
    for cast in (lambda x: x.to(torch.float16), lambda x: x.bfloat16(), lambda x: x.half()):
        metric = cast(cls())
        metric.reset()
        assert metric.quality_sum.dtype == torch.float64 and metric.num_skipped.dtype == torch.long
    assert cls().to("meta").quality_sum.is_meta
    with pytest.raises(TypeError, match=r"^RegistrationQualityMetric: sync_on_compute are torchmetrics.Metric options"):
        cls(sync_on_compute=False)


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
