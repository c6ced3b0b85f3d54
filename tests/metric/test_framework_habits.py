"""The metric and the loss as torchmetrics, Lightning and kornia / piq users expect (issue 22):
``compute()`` a 0-dim tensor, ``MetricCollection`` and ``log_dict``, a (B,) loss reduction."""

from __future__ import annotations

import pytest
import torch
from metric_helpers import textured

from lensdist_torch import (
    QualityConfig,
    RegistrationQualityLoss,
    RegistrationQualityMetric,
    registration_quality,
    registration_quality_loss,
)


def pairs(n: int = 5, h: int = 32, w: int = 40):
    img1 = textured(n, h, w, seed=3, dtype=torch.float32)
    img2 = torch.stack([torch.roll(img1[i], (i % 2, i % 3), dims=(-2, -1)) for i in range(n)])
    valid = torch.ones(n, 1, h, w)
    valid[1, ..., :, : w // 2] = 0
    return img1, img2, valid


def mean_index(img1, img2, valid, config=None):
    return float(registration_quality(img1, img2, valid, config=config).quality_index.double().mean())


# ----------------------------------------------------------------------------- metric


def test_compute_is_the_index_and_details_are_behind_a_method():
    img1, img2, valid = pairs()
    metric = RegistrationQualityMetric()
    metric.update(img1, img2, valid)
    index = metric.compute()
    assert isinstance(index, torch.Tensor) and index.shape == () and index.dtype == torch.float64
    assert float(index) == pytest.approx(mean_index(img1, img2, valid), abs=1e-7)
    assert 0.2 < float(index) < 0.95  # four of five pairs misregistered
    details = metric.compute_details()
    assert torch.equal(details.quality_index, index)
    assert details.registration_map.shape == (1, 4, 5) and int(details.num_pairs) == 5


class TestTorchmetrics:
    @pytest.fixture(autouse=True)
    def _tm(self):
        self.tm = pytest.importorskip("torchmetrics")
        self.cls = RegistrationQualityMetric

    def test_metric_collection_and_log_dict(self):
        img1, img2, valid = pairs()
        strict = QualityConfig(theta_g=0.05)
        collection = self.tm.MetricCollection(
            {"quality": self.cls(), "quality_strict": self.cls(config=strict)}, prefix="val/"
        )
        batch = collection(img1[:2], img2[:2], valid[:2])  # forward: the batch's values
        assert set(batch) == {"val/quality", "val/quality_strict"}
        assert float(batch["val/quality"]) == pytest.approx(mean_index(img1[:2], img2[:2], valid[:2]), abs=1e-7)
        collection.update(img1[2:], img2[2:], valid[2:])
        logged = collection.compute()  # what Lightning's self.log_dict(...) receives
        assert set(logged) == {"val/quality", "val/quality_strict"}
        for value in logged.values():
            assert isinstance(value, torch.Tensor) and value.dim() == 0 and torch.isfinite(value)
        assert float(logged["val/quality"]) == pytest.approx(mean_index(img1, img2, valid), abs=1e-7)
        assert float(logged["val/quality_strict"]) == pytest.approx(mean_index(img1, img2, valid, strict), abs=1e-7)
        assert float(logged["val/quality"]) != pytest.approx(float(logged["val/quality_strict"]), abs=1e-4)
        # Lightning's log_dict takes a dict of str -> 0-dim tensor or number; float() of each works
        assert {k: round(float(v), 6) for k, v in logged.items()}
        collection.reset()
        collection.update(img1[:1], img1[:1], valid[:1])
        assert float(collection.compute()["val/quality"]) == 1.0

    def test_with_a_torchmetrics_image_metric(self):
        """Beside a built-in metric: the mask goes by keyword, which SSIM's update does not take."""
        from torchmetrics.image import StructuralSimilarityIndexMeasure

        img1, img2, valid = pairs()
        collection = self.tm.MetricCollection(
            {"quality": self.cls(), "ssim": StructuralSimilarityIndexMeasure(data_range=1.0)}
        )
        collection.update(img1, img2, valid=valid)
        out = collection.compute()
        assert float(out["quality"]) == pytest.approx(mean_index(img1, img2, valid), abs=1e-7)
        assert out["ssim"].dim() == 0 and 0.0 < float(out["ssim"]) < 1.0

    def test_details_and_forward(self):
        img1, img2, valid = pairs()
        metric = self.cls()
        first = metric(img1[:3], img2[:3], valid[:3])
        assert first.shape == () and float(first) == pytest.approx(mean_index(img1[:3], img2[:3], valid[:3]), abs=1e-7)
        metric.update(img1[3:], img2[3:], valid[3:])
        details = metric.compute_details()
        assert int(details.num_pairs) == 5 and details.registration_map.shape == (1, 4, 5)
        assert torch.equal(details.quality_index, metric.compute())


# ----------------------------------------------------------------------------- loss


def test_per_sample_reduction_is_each_samples_masked_mean():
    img1, img2, valid = pairs()
    valid[3] = 0  # a sample with no valid block
    per = registration_quality_loss(img1, img2, valid, reduction="per_sample")
    assert per.shape == (5,)
    for i in (0, 1, 2, 4):
        alone = registration_quality_loss(img1[i : i + 1], img2[i : i + 1], valid[i : i + 1])
        torch.testing.assert_close(per[i], alone, atol=1e-6, rtol=0)
    assert float(per[3]) == 0.0
    assert float(per[0]) < 0.01 and float(per[2]) > 0.3  # pair 0 is not moved, pair 2 is by (0, 2) px
    # the map is still there, as in torch.nn and kornia ("none" reduces nothing)
    assert registration_quality_loss(img1, img2, valid, reduction="none").shape == (5, 1, 4, 5)
    # with no mask: the plain mean of each sample's map
    blocks = registration_quality_loss(img1, img2, reduction="none")
    torch.testing.assert_close(
        registration_quality_loss(img1, img2, reduction="per_sample"), blocks.mean(dim=(1, 2, 3)), atol=1e-7, rtol=0
    )


def test_per_sample_mean_equals_masked_mean_when_samples_have_as_many_blocks():
    img1, img2, _ = pairs()
    valid = torch.ones(5, 1, 32, 40)
    valid[..., 16:, :] = 0
    per = RegistrationQualityLoss(reduction="per_sample")(img1, img2, valid)
    torch.testing.assert_close(per.mean(), RegistrationQualityLoss()(img1, img2, valid), atol=1e-6, rtol=0)


def test_per_sample_gradients_stay_in_their_sample():
    img1, img2, valid = pairs()
    x = img1.clone().requires_grad_()
    per = registration_quality_loss(x, img2, valid, reduction="per_sample")
    per[2].backward()
    grad = x.grad.abs().sum(dim=(1, 2, 3))
    assert float(grad[2]) > 0 and float(grad[[0, 1, 3, 4]].sum()) == 0.0


@pytest.mark.bad_input
def test_an_unknown_reduction_names_the_choices():
    img1, img2, _ = pairs(2)
    with pytest.raises(ValueError, match=r"^reduction must be one of .*'per_sample'.*got 'batchmean'$") as info:
        registration_quality_loss(img1, img2, reduction="batchmean")
    assert "\n" not in str(info.value)
