"""Checkpoints are untrusted input: every malformed payload is one CheckpointError naming the
file and what is wrong, raised before anything is allocated from the payload's sizes.

The payloads here are written with their content digest recomputed (``_write``), as a tamperer
who knows the format would: the content checks must hold on their own."""

from __future__ import annotations

import time

import pytest
import torch

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import ClassifierConfig, LensdistConfig
from lensdist_torch.core.storage import DIGEST_KEY, CheckpointError, content_digest

pytestmark = pytest.mark.bad_input


#: Texture statistics of the form of workflows.texture.texture_statistics (two scenes, three bins).
TEXTURE = {
    "names": ["a", "b"],
    "edges": [0.01, 0.1],
    "reference": [[0.25, 0.5, 0.25], [0.5, 0.25, 0.25]],
    "spread": 0.05,
}


def _cfg(n=2):
    return LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=n))


@pytest.fixture(scope="module")
def eig_payload(tmp_path_factory):
    g = torch.Generator().manual_seed(0)
    x, c = torch.rand(40, 12, generator=g), torch.arange(40) % 4
    path = tmp_path_factory.mktemp("eig") / "m.pt"
    EigenSpaceClassifier(12, _cfg()).fit(x, c, torch.rand(40, generator=g)).save(path)
    return torch.load(path, weights_only=True)


@pytest.fixture(scope="module")
def reg_payload(tmp_path_factory):
    g = torch.Generator().manual_seed(1)
    path = tmp_path_factory.mktemp("reg") / "r.pt"
    DeltaRegressor(12, n_components=3, k=4).fit(torch.rand(30, 12, generator=g), torch.rand(30), torch.rand(30)).save(
        path
    )
    return torch.load(path, weights_only=True)


def _write(tmp_path, payload, name="bad.pt"):
    """torch.save of ``payload`` with its content digest recomputed."""
    path = tmp_path / name
    torch.save({**payload, DIGEST_KEY: content_digest(payload)}, path)
    return path


def _edit(payload, **changes):
    """A copy of ``payload`` with top-level and ``state_dict`` entries replaced (None: removed)."""
    out = {k: v for k, v in payload.items() if k != "state_dict"}
    sd = dict(payload["state_dict"])
    for key, value in changes.items():
        target = sd if key in sd else out
        if value is None:
            target.pop(key, None)
        else:
            target[key] = value
    out["state_dict"] = sd
    return out


def _fails(cls, tmp_path, payload, match):
    path = _write(tmp_path, payload)
    with pytest.raises(CheckpointError, match=match) as info:
        cls.load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def test_good_payloads_load(tmp_path, eig_payload, reg_payload):
    assert EigenSpaceClassifier.load(_write(tmp_path, eig_payload)).n_features == 12
    assert DeltaRegressor.load(_write(tmp_path, reg_payload, "r.pt")).n_components == 3


@pytest.mark.parametrize("key", ["n_features", "config", "state_dict"])
def test_eigenspace_missing_payload_key(tmp_path, eig_payload, key):
    _fails(EigenSpaceClassifier, tmp_path, {k: v for k, v in eig_payload.items() if k != key}, f"lacks {key}")


@pytest.mark.parametrize("key", ["means", "bases", "train_class", "reject_threshold", "fitted"])
def test_eigenspace_missing_buffer(tmp_path, eig_payload, key):
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, **{key: None}), f"state_dict lacks {key}")


def test_eigenspace_unexpected_buffer(tmp_path, eig_payload):
    payload = _edit(eig_payload)
    payload["state_dict"]["surprise"] = torch.zeros(1)
    _fails(EigenSpaceClassifier, tmp_path, payload, "unexpected entries surprise")


def test_oversize_n_features_fails_fast(tmp_path, eig_payload):
    """A tiny file claiming 10**12 features (4 x 2 x 10**12 floats = 32 TB) is refused from the
    stored shapes before any buffer is allocated."""
    t0 = time.perf_counter()
    msg = _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, n_features=10**12), r"means has shape \(4, 12\)")
    assert "1000000000000" in msg
    assert time.perf_counter() - t0 < 5.0


def test_expanded_views_cannot_claim_sizes(tmp_path, eig_payload):
    """Stored tensors that are zero-stride views of one float would match a huge n_features."""
    d = 10**13  # far beyond any memory: the old loader failed at once instead of thrashing
    payload = _edit(
        eig_payload,
        n_features=d,
        means=torch.zeros(1).expand(4, d),
        bases=torch.zeros(1).expand(4, 2, d),
    )
    _fails(EigenSpaceClassifier, tmp_path, payload, "view larger than its stored data")


@pytest.mark.parametrize("value", [0, -3, 2.5, True, "12"])
def test_eigenspace_bad_n_features(tmp_path, eig_payload, value):
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, n_features=value), "n_features")


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("means", torch.zeros(4, 11), r"means has shape \(4, 11\), expected \(4, 12\)"),
        ("bases", torch.zeros(4, 3, 12), r"bases has shape \(4, 3, 12\)"),
        ("train_delta", torch.zeros(39), r"train_delta has shape \(39,\), expected \(40,\)"),
        ("means", torch.zeros(4, 12, dtype=torch.float64), "means has dtype torch.float64"),
        ("train_class", torch.zeros(40), "train_class has dtype torch.float32"),
        ("reject_threshold", torch.zeros(1), "reject_threshold has shape"),
        ("bases", [[0.0]], "bases is not a dense tensor"),
    ],
)
def test_eigenspace_wrong_shape_or_dtype(tmp_path, eig_payload, key, value, match):
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, **{key: value}), match)


@pytest.mark.parametrize("key", ["means", "bases", "train_coeffs", "train_delta", "reject_threshold"])
def test_eigenspace_non_finite_buffers(tmp_path, eig_payload, key):
    t = eig_payload["state_dict"][key].clone()
    t.view(-1)[0] = float("nan")
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, **{key: t}), f"{key} holds NaN or infinite")


def test_eigenspace_class_indices(tmp_path, eig_payload):
    cls = eig_payload["state_dict"]["train_class"].clone()
    cls[0] = 7
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, train_class=cls), "train_class")
    _fails(
        EigenSpaceClassifier, tmp_path, _edit(eig_payload, train_class=torch.zeros(40, dtype=torch.long)), "every class"
    )


def test_unfitted_invalid_config_and_extra(tmp_path, eig_payload):
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, fitted=torch.tensor(False)), "unfitted")
    cfg = {**eig_payload["config"], "classifier": {"metric": "delta_median"}}
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, config=cfg), "invalid config.*delta_median")
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, config=[1, 2]), "invalid config")
    _fails(EigenSpaceClassifier, tmp_path, _edit(eig_payload, extra=[1]), "extra must be a dict")


#: Shares and probabilities of the stored config, out of range: a checkpoint holding one is refused
#: at load, by the config's own checks, naming the field. cannot_tell_fraction = 1000 loaded: the
#: regressor's confidence at a neighbour spread of the whole class range (14.4 px) read 0.999, not 0.11.
OUT_OF_RANGE = [
    ("regression", "cannot_tell_fraction", 1000.0),
    ("regression", "cannot_tell_fraction", 1.5),
    ("regression", "cannot_tell_fraction", -0.5),
    ("regression", "confidence_threshold", 1.5),
    ("classifier", "reject_quantile", 2.0),
    ("analysis", "min_confidence", -0.1),
    ("analysis", "interval_confidence", 1.0),  # constants of the method now: refused at another value, named
    ("analysis", "max_delta_disagreement", 3.0),
    ("analysis", "max_cannot_tell", 1.5),
    ("registration", "max_step", 2.0),  # a constant of the method now: refused at another value, named
    ("registration", "min_overlap", 1.5),
    ("multiview", "planar_guided_below", 5.0),
    ("calibration", "confidence", 1.5),
]


@pytest.mark.parametrize("section,field,value", OUT_OF_RANGE, ids=[f"{s}.{f}={v}" for s, f, v in OUT_OF_RANGE])
@pytest.mark.parametrize("kind", ["regression", "eigenspace"])
def test_stored_fraction_out_of_range(tmp_path, reg_payload, eig_payload, kind, section, field, value):
    payload = reg_payload if kind == "regression" else eig_payload
    cfg = {**payload["config"], section: {**payload["config"][section], field: value}}
    cls = DeltaRegressor if kind == "regression" else EigenSpaceClassifier
    msg = _fails(cls, tmp_path, _edit(payload, config=cfg), "invalid config")
    assert field in msg and repr(value) in msg


def test_stored_fraction_out_of_range_cli(tmp_path, capsys, reg_payload):
    from kornia.io import write_image

    from lensdist_torch import cli

    cfg = {**reg_payload["config"], "regression": {**reg_payload["config"]["regression"], "cannot_tell_fraction": 1000}}
    path = _write(tmp_path, _edit(reg_payload, config=cfg))
    pngs = [tmp_path / "a.png", tmp_path / "b.png"]
    for p in pngs:
        write_image(str(p), torch.full((3, 32, 48), 90, dtype=torch.uint8))
    rc = cli.main(["analyze", *map(str, pngs), "--method", "regression", "--checkpoint", str(path)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert (
        err.startswith("lensdist analyze: error: ")
        and "regression.cannot_tell_fraction = 1000 cannot be set: a constant of the method now" in err
    )


@pytest.mark.parametrize("key", ["n_features", "n_components", "k", "config", "state_dict"])
def test_regressor_missing_payload_key(tmp_path, reg_payload, key):
    _fails(DeltaRegressor, tmp_path, {k: v for k, v in reg_payload.items() if k != key}, f"lacks {key}")


def test_regressor_oversize_and_inconsistent(tmp_path, reg_payload):
    t0 = time.perf_counter()
    _fails(DeltaRegressor, tmp_path, _edit(reg_payload, n_features=10**12), r"mean has shape \(12,\)")
    assert time.perf_counter() - t0 < 5.0
    _fails(DeltaRegressor, tmp_path, _edit(reg_payload, k=0), "k must be a positive int")
    _fails(DeltaRegressor, tmp_path, _edit(reg_payload, n_components=2), "n_components=2")
    coeffs = reg_payload["state_dict"]["train_coeffs"]
    _fails(DeltaRegressor, tmp_path, _edit(reg_payload, train_coeffs=coeffs[:, :3].contiguous()), "do not fit")
    _fails(
        DeltaRegressor, tmp_path, _edit(reg_payload, train_delta=torch.zeros(29, 2)), r"train_delta has shape \(29, 2\)"
    )
    _fails(
        DeltaRegressor,
        tmp_path,
        _edit(reg_payload, components=torch.zeros(3, 12)),
        "components has dtype torch.float32",
    )


@pytest.mark.parametrize("key", ["mean", "components", "train_coeffs", "train_delta"])
def test_regressor_non_finite_buffers(tmp_path, reg_payload, key):
    t = reg_payload["state_dict"][key].clone(memory_format=torch.contiguous_format)
    t.view(-1)[-1] = float("inf")
    _fails(DeltaRegressor, tmp_path, _edit(reg_payload, **{key: t}), f"{key} holds NaN or infinite")


def test_extra_is_saved_by_default_and_round_trips(tmp_path, eig_payload):
    """``save`` stores ``model.extra`` unless told otherwise; ``load`` gives it back."""
    model = EigenSpaceClassifier.load(_write(tmp_path, eig_payload))
    model.extra = {"scenes": ["a", "b"], "texture": TEXTURE}
    model.save(tmp_path / "e.pt")
    assert EigenSpaceClassifier.load(tmp_path / "e.pt").extra == model.extra
    model.save(tmp_path / "f.pt", extra={"scenes": ["c"]})
    assert EigenSpaceClassifier.load(tmp_path / "f.pt").extra == {"scenes": ["c"]}


@pytest.mark.parametrize("name", ["eigenspace_delta_avg_10ev.pt", "eigenspace_delta_max_10ev.pt", "regression.pt"])
def test_shipped_checkpoints_name_their_scenes(name):
    """The shipped checkpoints say what they were fitted on, with the texture statistics of those scenes."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "lensdist_torch" / "checkpoints" / name
    if not path.is_file():
        pytest.skip("shipped checkpoints not present")
    cls = DeltaRegressor if name == "regression.pt" else EigenSpaceClassifier
    extra = cls.load(path).extra
    assert extra["scenes"] == ["gravel", "grass"]
    tex = extra["texture"]
    assert tex["names"] == ["gravel", "grass"] and len(tex["reference"]) == 2 and 0 < tex["spread"] < 0.1
    assert all(abs(sum(h) - 1) < 1e-9 for h in tex["reference"])
