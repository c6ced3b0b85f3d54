"""The eigen-space classifier (SPEC 8), its checkpoints, and the evaluation metrics."""

import dataclasses

import pytest
import torch

from lensdist_torch.classify import eigenspace
from lensdist_torch.classify.eigenspace import CHECKPOINT_VERSION, CheckpointError, EigenSpaceClassifier
from lensdist_torch.config import ClassifierConfig, ImageConfig, LensdistConfig, QualityConfig
from lensdist_torch.geometry.distortion import REJECT
from lensdist_torch.metric.classification import ClassRMSE, ConfusionMatrix
from lensdist_torch.workflows.reports import CANNOT_TELL, evaluate_predictions, report_markdown


def _cfg(n_ev=2):
    return LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=n_ev))


def _subspace_data(n_per=30, d=20, n_ev=2, noise=0.0, seed=0):
    """Four classes, each on its own affine 2-D subspace of R^d, inside the quality maps' [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    xs, cs, ds, spaces = [], [], [], []
    for c in range(4):
        mu = torch.randn(d, generator=g, dtype=torch.float64) * 3
        basis, _ = torch.linalg.qr(torch.randn(d, n_ev, generator=g, dtype=torch.float64))
        coef = torch.randn(n_per, n_ev, generator=g, dtype=torch.float64)
        x = mu + coef @ basis.T + noise * torch.randn(n_per, d, generator=g, dtype=torch.float64)
        x = 0.5 + x / 40  # an affine map keeps each class on an affine 2-D subspace
        xs.append(x)
        cs.append(torch.full((n_per,), c))
        ds.append(torch.rand(n_per, generator=g, dtype=torch.float64) + c)
        spaces.append((mu, basis))
    return torch.cat(xs).float(), torch.cat(cs), torch.cat(ds).float(), spaces


class TestFit:
    def test_buffers_not_parameters(self):
        clf = EigenSpaceClassifier(20, _cfg())
        assert list(clf.parameters()) == []
        names = set(dict(clf.named_buffers()))
        assert {"means", "bases", "train_coeffs", "train_class", "train_delta", "reject_threshold"} <= names

    def test_recovers_class_subspaces(self):
        x, c, d, spaces = _subspace_data()
        clf = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
        for k, (_mu, basis) in enumerate(spaces):
            # the fitted projector equals the true subspace's projector
            u = clf.bases[k].double()
            assert torch.allclose(u.T @ u, basis @ basis.T, atol=1e-4)
            assert torch.allclose(u @ u.T, torch.eye(2, dtype=torch.float64), atol=1e-5)
        res = clf(x)
        assert torch.equal(res.nearest, c)
        assert float(res.distances.gather(1, c[:, None]).max()) < 1e-3

    def test_distance_formula(self):
        x, c, d, _ = _subspace_data(noise=0.3)
        clf = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
        q = torch.randn(5, 20, generator=torch.Generator().manual_seed(2))
        dist = clf.distances(q)
        for k in range(4):
            u, mu = clf.bases[k].double(), clf.means[k].double()
            xc = q.double() - mu
            eps = (xc - xc @ u.T @ u).norm(dim=1)
            assert torch.allclose(dist[:, k].double(), eps, atol=1e-4)

    def test_reject_threshold_is_training_quantile(self, monkeypatch):
        monkeypatch.setattr(eigenspace, "REJECT_QUANTILE", 0.8)
        x, c, d, _ = _subspace_data(noise=0.3)
        clf = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
        own = clf.distances(x).min(1).values.double()
        assert float(clf.reject_threshold) == pytest.approx(float(torch.quantile(own, 0.8)), rel=1e-6)
        far = clf.means[0:1] + 100.0
        assert int(clf(far).label[0]) == REJECT
        # about 20 % of the training pairs lie beyond the 0.8 quantile
        assert 0.15 <= float((clf(x).label == REJECT).float().mean()) <= 0.25

    def test_delta_inverse_distance_weights(self, monkeypatch):
        # class 0 training coefficients at known positions; check the 2-NN weighted mean by hand
        monkeypatch.setattr(eigenspace, "N_NEIGHBOURS", 2)
        d_feat = 6
        cfg = _cfg(n_ev=1)
        x = torch.zeros(4 * 5, d_feat)
        cls = torch.arange(4).repeat_interleave(5)
        for k in range(4):
            x[cls == k, k] = (torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0]) + 10 * k) / 40  # a line per class, in [0, 1]
        deltas = torch.arange(20, dtype=torch.float32)
        clf = EigenSpaceClassifier(d_feat, cfg).fit(x, cls, deltas)
        q = torch.zeros(1, d_feat)
        q[0, 0] = 1.25 / 40  # between training points 1 (delta 1) and 2 (delta 2) of class 0
        res = clf(q)
        assert int(res.nearest[0]) == 0
        w1, w2 = 1 / (0.25 / 40 + 1e-6), 1 / (0.75 / 40 + 1e-6)
        expected = (w1 * 1 + w2 * 2) / (w1 + w2)
        assert float(res.delta[0]) == pytest.approx(expected, rel=1e-4)
        assert sorted(res.neighbours[0].tolist()) == [1, 2]

    def test_batched_equals_single(self):
        x, c, d, _ = _subspace_data(noise=0.2)
        clf = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
        q = torch.randn(7, 20, generator=torch.Generator().manual_seed(3)) + x[:7]
        full = clf(q)
        for i in range(7):
            one = clf(q[i : i + 1])
            assert int(one.label[0]) == int(full.label[i])
            assert float(one.delta[0]) == pytest.approx(float(full.delta[i]), rel=1e-5)


class TestErrors:
    def test_unfitted(self):
        with pytest.raises(RuntimeError, match="not fitted"):
            EigenSpaceClassifier(20, _cfg())(torch.zeros(1, 20))

    def test_feature_shape(self):
        x, c, d, _ = _subspace_data()
        clf = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
        with pytest.raises(ValueError, match="features"):
            clf(torch.zeros(1, 19))
        with pytest.raises(ValueError, match="features"):
            clf.fit(torch.zeros(5, 19), torch.zeros(5, dtype=torch.long), torch.zeros(5))

    def test_too_few_per_class(self):
        x, c, d, _ = _subspace_data(n_per=2)
        with pytest.raises(ValueError, match="class 1 has 2 training vectors"):
            EigenSpaceClassifier(20, _cfg()).fit(x, c, d)

    def test_bad_classes(self):
        x, c, d, _ = _subspace_data()
        with pytest.raises(ValueError, match="classes must lie"):
            EigenSpaceClassifier(20, _cfg()).fit(x, c + 1, d)


class TestCheckpoint:
    def _fitted(self, cfg=None):
        x, c, d, _ = _subspace_data(noise=0.2)
        return EigenSpaceClassifier(20, cfg or _cfg()).fit(x, c, d), x

    def test_round_trip(self, tmp_path):
        clf, x = self._fitted()
        clf.save(tmp_path / "m.pt")
        raw = torch.load(tmp_path / "m.pt", weights_only=True)
        assert raw["format_version"] == CHECKPOINT_VERSION
        assert raw["config"]["classifier"]["n_eigenvectors"] == 2
        back = EigenSpaceClassifier.load(tmp_path / "m.pt", expected=LensdistConfig())
        a, b = clf(x), back(x)
        assert torch.equal(a.label, b.label) and torch.equal(a.delta, b.delta)
        assert back.config == clf.config

    def test_version_mismatch(self, tmp_path):
        clf, _ = self._fitted()
        clf.save(tmp_path / "m.pt")
        raw = torch.load(tmp_path / "m.pt", weights_only=True)
        raw["format_version"] = CHECKPOINT_VERSION + 1
        torch.save(raw, tmp_path / "v.pt")
        with pytest.raises(CheckpointError, match="format version"):
            EigenSpaceClassifier.load(tmp_path / "v.pt")

    @pytest.mark.parametrize(
        "other, what",
        [
            (LensdistConfig(image=ImageConfig(height=240, width=320)), "image size"),
            (LensdistConfig(quality=QualityConfig(block_size=4)), "block size"),
        ],
    )
    def test_config_mismatch(self, tmp_path, other, what):
        clf, _ = self._fitted()
        clf.save(tmp_path / "m.pt")
        with pytest.raises(CheckpointError, match=what):
            EigenSpaceClassifier.load(tmp_path / "m.pt", expected=other)

    def test_foreign_file(self, tmp_path):
        torch.save({"a": torch.zeros(1)}, tmp_path / "f.pt")
        with pytest.raises(CheckpointError, match="not a lensdist"):
            EigenSpaceClassifier.load(tmp_path / "f.pt")
        (tmp_path / "g.pt").write_bytes(b"garbage")
        with pytest.raises(CheckpointError, match="corrupted"):
            EigenSpaceClassifier.load(tmp_path / "g.pt")

    @pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
    def test_cuda(self):
        clf, x = self._fitted()
        a = clf(x)
        b = clf.to("cuda")(x.cuda())
        assert torch.equal(a.label, b.label.cpu())


class TestEvaluation:
    def test_confusion_by_hand(self):
        cm = ConfusionMatrix()
        cm.update(torch.tensor([0, 1, 1, 4]), torch.tensor([0, 1, 2, 4]))
        cm.update(torch.tensor([3]), torch.tensor([4]))
        m = cm.compute()
        assert m.dtype == torch.long and m.shape == (5, 5)
        expected = torch.zeros(5, 5, dtype=torch.long)
        expected[0, 0] = expected[1, 1] = expected[2, 1] = expected[4, 4] = expected[4, 3] = 1
        assert torch.equal(m, expected)
        assert cm.rate() == pytest.approx(3 / 5)
        with pytest.raises(ValueError, match="class indices"):
            cm.update(torch.tensor([5]), torch.tensor([0]))

    def test_rmse_by_hand(self):
        r = ClassRMSE()
        r.update(torch.tensor([1.0, 3.0, 5.0, 9.0]), torch.tensor([2.0, 2.0, 5.0, 0.0]), torch.tensor([0, 0, 1, 4]))
        out = r.compute()
        assert out["rmse"][0] == pytest.approx(1.0)
        assert out["rmse"][1] == pytest.approx(0.0)
        assert out["n"] == [2, 1, 0, 0]  # class R is not part of the Delta RMSE
        assert out["bias"][0] == pytest.approx(0.0)

    def test_report(self):
        fig = evaluate_predictions(
            torch.tensor([0, 1, 4, 4]), torch.tensor([1.0, 2.0, 0.0, 0.0]),
            torch.tensor([0, 1, 1, 4]), torch.tensor([1.5, 2.0, 4.0, 0.0]), delta_range=14.4,
            registration_ok=torch.tensor([True, True, False, True]),
        )
        assert fig["rate"] == pytest.approx(75.0)
        assert fig["registration_failed"] == 1
        assert fig["rmse_px"][0] == pytest.approx(0.5)
        assert fig["rmse_pct"][0] == pytest.approx(100 * 0.5 / 14.4)
        fig["paper_key"] = "10ev_delta_avg"
        md = report_markdown({"title": "t", "settings": {"10 EV, delta_avg": fig}})
        assert "67.8 %" in md and "| R |" in md

    def test_cannot_tell_is_its_own_outcome(self):
        """A "cannot tell" is neither right nor a hidden wrong class: its own column, its own share."""
        t = CANNOT_TELL
        fig = evaluate_predictions(
            torch.tensor([0, t, 2, t, 4]), torch.tensor([1.0, float("nan"), 9.0, 3.0, 0.0]),
            torch.tensor([0, 1, 1, 2, 4]), torch.tensor([1.5, 4.0, 4.0, 8.0, 0.0]), delta_range=14.4,
        )
        conf = torch.tensor(fig["confusion"])
        assert conf.shape == (5, 6) and int(conf[:, 5].sum()) == 2 and int(conf[1, 2]) == 1
        assert fig["rate"] == pytest.approx(40.0)  # 2 right of 5
        assert fig["cannot_tell_share"] == pytest.approx(40.0) and fig["confident_share"] == pytest.approx(60.0)
        assert fig["confident_rate"] == pytest.approx(100 * 2 / 3) and fig["confident_wrong"] == 1
        assert fig["n_per_class"] == [1, 1, 1, 0]  # the pair without an estimate is not in the RMSE
        md = report_markdown({"title": "t", "settings": {"x": fig}})
        assert "cannot tell" in md and "40.0 %" in md
        with pytest.raises(ValueError, match="cannot tell"):
            evaluate_predictions(
                torch.tensor([6]), torch.tensor([1.0]), torch.tensor([0]), torch.tensor([1.0]), delta_range=14.4
            )


def test_fit_is_float64_on_cpu_invariant_to_order():
    x, c, d, _ = _subspace_data(noise=0.2)
    perm = torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(1))
    a = EigenSpaceClassifier(20, _cfg()).fit(x, c, d)
    b = EigenSpaceClassifier(20, _cfg()).fit(x[perm], c[perm], d[perm])
    q = torch.randn(6, 20, generator=torch.Generator().manual_seed(4))
    assert torch.allclose(a.distances(q), b.distances(q), atol=1e-4)
    assert dataclasses.asdict(a.config) == dataclasses.asdict(b.config)
