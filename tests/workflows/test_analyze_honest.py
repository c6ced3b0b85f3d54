"""analyze never answers confidently when the pair cannot support an answer."""

from __future__ import annotations

import json
import struct
import zlib

import pytest

from lensdist_torch.cli import main
from lensdist_torch.core.images import load_scene
from lensdist_torch.workflows.analyze import analyze_pair


def _unrelated():
    return load_scene("gravel")[..., :320, :424], load_scene("grass")[..., :320, :424]


@pytest.mark.bad_input
@pytest.mark.parametrize("method", ["selfcal", "regression", "eigenspace"])
def test_unrelated_images_cannot_tell(method):
    a, b = _unrelated()
    r = analyze_pair(a, b, method=method)
    assert r.registration_ok is False
    assert r.class_label is None and r.cannot_tell is True
    assert r.delta_avg is None and r.delta_avg_user_px is None
    assert any("registration failed" in w for w in r.warnings)


def test_a_good_pair_still_answers():
    scene = load_scene("gravel")
    r = analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424])
    assert r.registration_ok and not r.cannot_tell and r.class_label == "R"


@pytest.mark.bad_input
def test_strict_exits_3_and_json_says_null(tmp_path, capsys):
    out = tmp_path
    a, b = _unrelated()

    def png(path, img):
        h, w = img.shape[-2:]
        rows = (img[0, 0] * 255).round().byte().tolist()
        raw = b"".join(b"\x00" + bytes(r) for r in rows)

        def chunk(tag, data):
            return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

        path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                         + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))

    png(out / "a.png", a)
    png(out / "b.png", b)
    assert main(["analyze", str(out / "a.png"), str(out / "b.png"), "--json", "--strict"]) == 3
    res = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    assert res["class"] is None and res["cannot_tell"] is True
    assert main(["analyze", str(out / "a.png"), str(out / "b.png")]) == 0
    assert "cannot tell" in capsys.readouterr().out


def test_selfcal_answer_in_user_pixels_and_opencv_terms():
    """A distorted pair at twice the analysis size: the coefficients scale by s^2 and s^4, and
    the OpenCV block maps the user's pixels (its own fit error is reported and small)."""
    import torch.nn.functional as F

    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.data.synthesis import draw_pairs, render_pairs

    cfg = LensdistConfig()
    params = draw_pairs(cfg, "test", [3], 2)
    a, b = render_pairs([load_scene("gravel"), load_scene("grass")], params, cfg)
    big_a, big_b = (F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False) for x in (a, b))
    r = analyze_pair(big_a, big_b)
    s = r.user_px_per_analysis_px
    assert s == pytest.approx(2.0)
    assert r.k2_user == pytest.approx(r.k2 / s**2) and r.k4_user == pytest.approx(r.k4 / s**4)
    cv = r.opencv
    assert len(cv["camera_matrix"]) == 3 and len(cv["dist_coeffs"]) == 5
    assert cv["camera_matrix"][0][2] == pytest.approx((848 - 1) / 2) and cv["camera_matrix"][1][2] == pytest.approx(
        (640 - 1) / 2
    )
    assert cv["fit_error_mean_px"] < 0.1
    json.dumps(r.to_json(), allow_nan=False)


def test_the_answer_says_which_model_gave_it(monkeypatch):
    """With the plane + parallax model on every pair (selfcal.parallax, fit.PARALLAX_TEST = 0, and
    PARALLAX_SCORE_LEVEL = 1: fitted on this flat pair too) the answer says it came from that
    model; by default it never does."""
    import dataclasses

    from lensdist_torch.config import LensdistConfig
    from lensdist_torch.selfcal import fit

    scene = load_scene("gravel")
    a, b = scene[..., :320, :424], scene[..., 8:328, 4:428]
    base = LensdistConfig()
    every = dataclasses.replace(base.selfcal, parallax=5)
    relief = dataclasses.replace(base, selfcal=every)
    assert analyze_pair(a, b).relief is False
    monkeypatch.setattr(fit, "PARALLAX_TEST", 0.0)
    monkeypatch.setattr(fit, "PARALLAX_SCORE_LEVEL", 1.0)
    r = analyze_pair(a, b, config=relief)
    assert r.relief is True and r.estimated_class == "R"  # the wider relief interval may not support "R"
