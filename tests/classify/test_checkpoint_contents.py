"""Checkpoints that were tampered with (issue 19): a flipped value is caught by the content
digest, and values no fit can produce are refused even where the digest was recomputed.

Every refusal is one CheckpointError naming the file and the field; on the command line it is
exit 2 with one line.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import ClassifierConfig, LensdistConfig, RegressionConfig
from lensdist_torch.core.storage import DIGEST_KEY, CheckpointError, content_digest

pytestmark = pytest.mark.bad_input

SHIPPED = Path(__file__).resolve().parents[2] / "lensdist_torch" / "checkpoints"
TEXTURE = {"names": ["gravel"], "edges": [0.01, 0.1], "reference": [[0.25, 0.5, 0.25]], "spread": 0.05}


def _eigenspace(d=12) -> EigenSpaceClassifier:
    g = torch.Generator().manual_seed(0)
    cfg = LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=2))
    model = EigenSpaceClassifier(d, cfg).fit(
        torch.rand(40, d, generator=g), torch.arange(40) % 4, torch.rand(40, generator=g) * 9
    )
    model.extra = {"scenes": ["gravel"], "texture": TEXTURE}
    return model


def _regressor(d=12) -> DeltaRegressor:
    g = torch.Generator().manual_seed(1)
    model = DeltaRegressor(d, n_components=3, k=4).fit(
        torch.rand(30, d, generator=g), torch.rand(30) * 9, torch.rand(30) * 40
    )
    model.extra = {"scenes": ["gravel"], "texture": TEXTURE}
    return model


@pytest.fixture(scope="module")
def saved(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ck")
    _eigenspace().save(d / "e.pt")
    _regressor().save(d / "r.pt")
    return {"eig": d / "e.pt", "reg": d / "r.pt"}


def _raw(path: Path) -> dict:
    return torch.load(path, weights_only=True)


def _rewrite(raw: dict, path: Path, resign: bool) -> Path:
    """Write ``raw`` to ``path``; with ``resign`` the digest is recomputed (a tamperer who knows the format)."""
    payload = {k: v for k, v in raw.items() if k != DIGEST_KEY}
    if resign:
        payload[DIGEST_KEY] = content_digest(payload)
    elif DIGEST_KEY in raw:
        payload[DIGEST_KEY] = raw[DIGEST_KEY]
    torch.save(payload, path)
    return path


def _refused(cls, path: Path, match: str) -> str:
    with pytest.raises(CheckpointError, match=match) as info:
        cls.load(path)
    msg = str(info.value)
    assert str(path) in msg and "\n" not in msg, msg
    return msg


# ------------------------------------------------------------------ the content digest
@pytest.mark.parametrize("which", ["eig", "reg"])
def test_one_flipped_value_is_caught(saved, tmp_path, which):
    raw = _raw(saved[which])
    assert isinstance(raw[DIGEST_KEY], str) and len(raw[DIGEST_KEY]) == 64
    name = "means" if which == "eig" else "mean"
    raw["state_dict"][name].view(-1)[3] += 1e-3  # one fitted value, still plausible
    cls = EigenSpaceClassifier if which == "eig" else DeltaRegressor
    _refused(cls, _rewrite(raw, tmp_path / "x.pt", resign=False), "does not match the digest")


def test_edited_metadata_is_caught(saved, tmp_path):
    raw = _raw(saved["eig"])
    raw["extra"]["scenes"] = ["brick"]
    _refused(EigenSpaceClassifier, _rewrite(raw, tmp_path / "x.pt", resign=False), "does not match the digest")
    raw = _raw(saved["reg"])
    raw["k"] = 3
    _refused(DeltaRegressor, _rewrite(raw, tmp_path / "y.pt", resign=False), "does not match the digest")


def test_flipped_byte_in_the_file(saved, tmp_path):
    """A bit flipped in the stored tensor bytes (torch.load itself does not notice)."""
    data = bytearray(saved["eig"].read_bytes())
    bases = _raw(saved["eig"])["state_dict"]["bases"].numpy().tobytes()
    offset = data.find(bases[:32])
    assert offset > 0
    data[offset + 5] ^= 0x01
    path = tmp_path / "x.pt"
    path.write_bytes(bytes(data))
    _refused(EigenSpaceClassifier, path, "corrupted")


@pytest.mark.parametrize("which", ["eig", "reg"])
def test_digest_removed_or_not_a_string(saved, tmp_path, which):
    cls = EigenSpaceClassifier if which == "eig" else DeltaRegressor
    raw = _raw(saved[which])
    del raw[DIGEST_KEY]
    torch.save(raw, tmp_path / "x.pt")
    _refused(cls, tmp_path / "x.pt", "carries no content digest")
    torch.save({**raw, DIGEST_KEY: 12}, tmp_path / "y.pt")
    _refused(cls, tmp_path / "y.pt", "does not match the digest")


def test_previous_format_version_is_refused(saved, tmp_path):
    """A file of the format before the digest (eigen-space 1, regression 2) cannot be verified:
    refused with its version, never loaded."""
    for which, cls, old in (("eig", EigenSpaceClassifier, 1), ("reg", DeltaRegressor, 2)):
        raw = _raw(saved[which])
        raw["format_version"] = old
        del raw[DIGEST_KEY]
        torch.save(raw, tmp_path / "old.pt")
        _refused(cls, tmp_path / "old.pt", f"format version {old}, this library reads {old + 1}")


@pytest.mark.parametrize("name", ["eigenspace_delta_avg_10ev.pt", "eigenspace_delta_max_10ev.pt", "regression.pt"])
def test_shipped_checkpoints_carry_their_digest(name, tmp_path):
    raw = _raw(SHIPPED / name)
    assert raw[DIGEST_KEY] == content_digest(raw)
    cls = DeltaRegressor if name == "regression.pt" else EigenSpaceClassifier
    assert cls.load(SHIPPED / name).extra["scenes"] == ["gravel", "grass"]
    key = "train_delta"
    raw["state_dict"][key].view(-1)[0] += 0.5
    _refused(cls, _rewrite(raw, tmp_path / name, resign=False), "does not match the digest")


# ------------------------------------------------------------------ absurd but finite, digest recomputed
def _edit_state(raw: dict, name: str, fn) -> dict:
    raw["state_dict"][name] = fn(raw["state_dict"][name].clone())
    return raw


def _set(t: torch.Tensor, value: float) -> torch.Tensor:
    t.view(-1)[0] = value
    return t


EIG_EDITS = [
    (
        "means 1e30",
        lambda r: _edit_state(r, "means", lambda t: _set(t, 1e30)),
        r"means holds values .*outside \[-0.1, 1.1\]",
    ),
    ("bases scaled", lambda r: _edit_state(r, "bases", lambda t: t * 3), "rows of bases are not orthonormal"),
    ("explained above 1", lambda r: _edit_state(r, "explained", lambda t: _set(t, 4.0)), "explained holds values"),
    (
        "train_coeffs huge",
        lambda r: _edit_state(r, "train_coeffs", lambda t: _set(t, 1e6)),
        "train_coeffs has a row of norm",
    ),
    (
        "reject_threshold huge",
        lambda r: _edit_state(r, "reject_threshold", lambda t: t * 0 + 1e9),
        "reject_threshold holds values",
    ),
    (
        "reject_threshold negative",
        lambda r: _edit_state(r, "reject_threshold", lambda t: t * 0 - 1),
        "reject_threshold holds values",
    ),
    (
        "train_delta negative",
        lambda r: _edit_state(r, "train_delta", lambda t: _set(t, -2.0)),
        "train_delta holds values",
    ),
    (
        "train_delta beyond the frame",
        lambda r: _edit_state(r, "train_delta", lambda t: _set(t, 1e5)),
        r"train_delta .*image diagonal",
    ),
    (
        "a class with too few pairs",
        lambda r: _edit_state(
            r, "train_class", lambda t: torch.where(t == 3, 2, t).index_fill(0, torch.tensor([3]), 3)
        ),
        "more than n_eigenvectors=2 times",
    ),
]


@pytest.mark.parametrize("how,edit,match", EIG_EDITS, ids=[e[0] for e in EIG_EDITS])
def test_eigenspace_absurd_values(saved, tmp_path, how, edit, match):
    _refused(EigenSpaceClassifier, _rewrite(edit(_raw(saved["eig"])), tmp_path / "x.pt", resign=True), match)


def _top_level(raw: dict, **changes) -> dict:
    raw.update(changes)
    return raw


REG_EDITS = [
    (
        "k 100000",
        lambda r: _top_level(r, k=100000),
        r"k=100000 neighbours needs more than k training pairs, it holds 30",
    ),
    ("k equal to the pairs", lambda r: _top_level(r, k=30), "k=30 neighbours"),
    (
        "n_components larger than kept",
        lambda r: _top_level(r, n_components=9),
        "components has 3 rows; a fit of n_components=9",
    ),
    ("mean out of range", lambda r: _edit_state(r, "mean", lambda t: _set(t, -5.0)), "mean holds values"),
    (
        "components scaled",
        lambda r: _edit_state(r, "components", lambda t: t * 2),
        "rows of components are not orthonormal",
    ),
    (
        "train_coeffs huge",
        lambda r: _edit_state(r, "train_coeffs", lambda t: _set(t, 6e4)),
        "train_coeffs has a row of norm",
    ),
    (
        "negative residual",
        lambda r: _edit_state(r, "train_coeffs", lambda t: t.index_fill(1, torch.tensor([3]), -0.5)),
        "negative residual",
    ),
    ("train_delta absurd", lambda r: _edit_state(r, "train_delta", lambda t: _set(t, 7e4)), "train_delta holds values"),
]


@pytest.mark.parametrize("how,edit,match", REG_EDITS, ids=[e[0] for e in REG_EDITS])
def test_regressor_absurd_values(saved, tmp_path, how, edit, match):
    _refused(DeltaRegressor, _rewrite(edit(_raw(saved["reg"])), tmp_path / "x.pt", resign=True), match)


def _extra(raw: dict, **changes) -> dict:
    raw["extra"] = {**raw["extra"], **changes}
    return raw


def _texture(**changes) -> dict:
    return {**TEXTURE, **changes}


EXTRA_EDITS = [
    ("fitted_on a string", {"scenes": "gravel"}, "extra.scenes must be a list of scene names"),
    ("scenes of numbers", {"scenes": [1, 2]}, "extra.scenes"),
    ("texture NaN spread", {"texture": _texture(spread=math.nan)}, "extra.texture spread must be a number in"),
    ("texture infinite spread", {"texture": _texture(spread=math.inf)}, "extra.texture spread"),
    ("texture spread a string", {"texture": _texture(spread="0.05")}, "extra.texture spread"),
    ("texture not a dict", {"texture": [1, 2]}, "extra.texture must be a dict"),
    (
        "texture without reference",
        {"texture": {k: v for k, v in TEXTURE.items() if k != "reference"}},
        "extra.texture lacks reference",
    ),
    ("texture NaN histogram", {"texture": _texture(reference=[[math.nan, 0.5, 0.5]])}, "extra.texture reference"),
    ("texture histogram of the wrong length", {"texture": _texture(reference=[[0.5, 0.5]])}, "extra.texture reference"),
    (
        "texture histogram not summing to 1",
        {"texture": _texture(reference=[[0.5, 0.5, 0.5]])},
        "extra.texture reference",
    ),
    ("texture one histogram for two names", {"texture": _texture(names=["a", "b"])}, "one histogram per name"),
    ("texture edges decreasing", {"texture": _texture(edges=[0.1, 0.01])}, "extra.texture edges"),
]


@pytest.mark.parametrize("which", ["eig", "reg"])
@pytest.mark.parametrize("how,changes,match", EXTRA_EDITS, ids=[e[0] for e in EXTRA_EDITS])
def test_extra_fields(saved, tmp_path, which, how, changes, match):
    cls = EigenSpaceClassifier if which == "eig" else DeltaRegressor
    _refused(cls, _rewrite(_extra(_raw(saved[which]), **changes), tmp_path / "x.pt", resign=True), match)


def test_fit_refuses_what_load_would_refuse():
    """fit and load agree: features outside the quality maps' range and implausible Deltas are refused up front."""
    g = torch.Generator().manual_seed(0)
    x, c = torch.rand(40, 12, generator=g), torch.arange(40) % 4
    cfg = LensdistConfig(classifier=ClassifierConfig(n_eigenvectors=2))
    with pytest.raises(ValueError, match=r"features must be quality maps"):
        EigenSpaceClassifier(12, cfg).fit(x * 3, c, torch.rand(40))
    with pytest.raises(ValueError, match=r"deltas must lie in \[0, 531.2\] px"):
        EigenSpaceClassifier(12, cfg).fit(x, c, -torch.rand(40))
    with pytest.raises(ValueError, match="features must be quality maps"):
        DeltaRegressor(12, n_components=3, k=4).fit(x - 2, torch.rand(40), torch.rand(40))
    with pytest.raises(ValueError, match="deltas must lie"):
        DeltaRegressor(12, n_components=3, k=4).fit(x, torch.rand(40) * 1e6, torch.rand(40))


def test_command_line_exit_2_with_one_line(saved, tmp_path, capsys):
    """The audit's case: a malformed texture entry gave exit 1, "internal error"."""
    from kornia.io import write_image

    from lensdist_torch.cli import main
    from lensdist_torch.core.images import load_scene

    s = load_scene("gravel")[0, 0]
    for name, img in (("a.png", s[10:330, 20:444]), ("b.png", s[30:350, 22:446])):
        write_image(
            str(tmp_path / name), (img.clamp(0, 1) * 255).round().to(torch.uint8)[None].expand(3, -1, -1).contiguous()
        )
    raw = _raw(SHIPPED / "regression.pt")
    bad = _rewrite(
        _extra(raw, texture={**raw["extra"]["texture"], "reference": "gravel"}), tmp_path / "bad.pt", resign=True
    )
    code = main(
        [
            "analyze",
            str(tmp_path / "a.png"),
            str(tmp_path / "b.png"),
            "--method",
            "regression",
            "--checkpoint",
            str(bad),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "extra.texture reference" in err and "internal error" not in err


def test_regressor_k_beyond_a_local_median(tmp_path):
    """The re-audit's case: k = 11000 neighbours of 12000 training pairs (below N) loaded and answered
    the median of nearly the whole training set for every input; k is bounded like regression.k."""
    g = torch.Generator().manual_seed(3)
    model = DeltaRegressor(12, n_components=3, k=8).fit(
        torch.rand(12000, 12, generator=g), torch.rand(12000) * 9, torch.rand(12000) * 40
    )
    model.save(tmp_path / "r.pt")
    assert DeltaRegressor.load(tmp_path / "r.pt").k == 8
    bad = _rewrite(_top_level(_raw(tmp_path / "r.pt"), k=11000), tmp_path / "x.pt", resign=True)
    _refused(DeltaRegressor, bad, r"k=11000 neighbours of 12000 training pairs, expected at most 100 \(a local median")
    with pytest.raises(ValueError, match=r"regression.k must be a positive int <= 100"):
        LensdistConfig(regression=RegressionConfig(k=101))
    with pytest.raises(ValueError, match="k must be at most 100 neighbours"):
        DeltaRegressor(12, k=101)
    assert DeltaRegressor.load(SHIPPED / "regression.pt").k == 8  # the shipped checkpoint still loads
