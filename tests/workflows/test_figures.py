"""Figures: the format the suffix names, invalid blocks distinct from "no error", and the atomic
writer's refusals (a figure never replaces a FIFO or a directory)."""

from __future__ import annotations

import os

import pytest
import torch

pytest.importorskip("matplotlib")

from lensdist_torch.workflows import figures  # noqa: E402


def _maps():
    maps = torch.zeros(2, 1, 5, 6)
    maps[:, :, 3:] = 0.5
    valid = torch.ones(2, 1, 5, 6, dtype=torch.bool)
    valid[:, :, 0] = False
    return maps, valid


def test_suffix_names_the_format(tmp_path):
    maps, valid = _maps()
    png = figures.save_map_grid(maps, ["a", "b"], tmp_path / "m.png", valid=valid, classes=["2", "R"])
    jpg = figures.save_map_grid(maps, ["a", "b"], tmp_path / "m.jpg")
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert jpg.read_bytes()[:2] == b"\xff\xd8"  # JPEG, not PNG bytes under .jpg
    assert ".svg" in figures.figure_formats()


@pytest.mark.bad_input
def test_unknown_suffix_and_non_regular_targets(tmp_path):
    maps, _ = _maps()
    with pytest.raises(ValueError, match="cannot write a figure as m.xyz"):
        figures.save_map_grid(maps, ["a", "b"], tmp_path / "m.xyz")
    os.mkfifo(tmp_path / "pipe.png")
    with pytest.raises(OSError, match="not a regular file"):
        figures.save_map_grid(maps, ["a", "b"], tmp_path / "pipe.png")
    with pytest.raises(IsADirectoryError):
        figures.save_map_grid(maps, ["a", "b"], tmp_path)
    with pytest.raises(ValueError, match="one label"):
        figures.save_map_grid(maps, ["a"], tmp_path / "x.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe.png"]


def test_invalid_blocks_are_grey_not_black(tmp_path, monkeypatch):
    """Blocks without a valid pixel are masked (NaN -> the colour map's grey 'bad' colour); a
    pixel-sized mask is pooled to blocks."""
    shown = []
    real = figures._map_image

    def spy(ax, m, ok):
        im = real(ax, m, ok)
        shown.append((im.get_array(), im.get_cmap()))
        return im

    monkeypatch.setattr(figures, "_map_image", spy)
    maps, valid = _maps()
    pixel_valid = valid.repeat_interleave(8, -2).repeat_interleave(8, -1)
    figures.save_map_grid(maps, ["a", "b"], tmp_path / "m.png", valid=pixel_valid)
    arr, cmap = shown[0]
    assert arr.mask[0].all() and not arr.mask[1:].any()  # first row: no valid pixel
    assert tuple(cmap.get_bad()[:3]) != tuple(cmap(0.0)[:3])  # grey differs from the colour of 0 ("no error")
    with pytest.raises(ValueError, match="block-sized"):
        figures.save_map_grid(maps, ["a", "b"], tmp_path / "m.png", valid=torch.ones(2, 1, 7, 6))


def test_confusion_and_eigenvectors(tmp_path):
    conf = torch.tensor([[9, 1], [0, 3]])
    assert figures.save_confusion(conf, ["1", "R"], tmp_path / "c.png", "t").read_bytes()[:4] == b"\x89PNG"
    ev = figures.save_eigenvectors({"class 1": torch.randn(2, 30)}, (5, 6), tmp_path / "e.pdf")
    assert ev.read_bytes()[:4] == b"%PDF"


def test_reliability_diagram(tmp_path):
    from lensdist_torch.workflows.confidence import reliability

    conf = torch.linspace(0.01, 0.99, 50)
    right = torch.arange(50) % 3 != 0
    curves = {"before": reliability(conf, right), "after": reliability(conf.clamp(0.6, 0.7), right)}
    path = figures.save_reliability(curves, tmp_path / "r.png", "reliability")
    assert path.read_bytes()[:4] == b"\x89PNG"
