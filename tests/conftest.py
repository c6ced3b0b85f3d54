"""Shared fixtures: the embedded scene at the default analysis size (docs/method.md, section 1)."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.core.images import load_scene


@pytest.fixture(scope="session")
def scene() -> torch.Tensor:
    """The embedded 'gravel' scene cropped to 320 x 424, (1, 1, 320, 424) float32 in [0, 1]."""
    return load_scene("gravel")[..., 40:360, 44:468].contiguous()


@pytest.fixture(scope="session")
def scene_pair(scene) -> tuple[torch.Tensor, torch.Tensor]:
    """The scene and the same scene shifted by 1 px right and 2 px down (float32, 320 x 424).

    The shift is taken from a larger crop, so both images hold real content everywhere.
    """
    full = load_scene("gravel")
    return scene, full[..., 38:358, 43:467].contiguous()


@pytest.fixture(scope="module")
def one_thread_module():
    """One intra-op thread for a module: on two shared cores extra threads only add contention
    at these small sizes (restored afterwards)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def planar_constant(monkeypatch):
    """``planar_constant(NAME, value)``: a constant of the sequence calibration's features and homography model,
    set in every calibration module that imported it (restored afterwards)."""
    from lensdist_torch.calibration import features, guided_matching, match_refinement, matches, planar_features
    from lensdist_torch.calibration.controllers import multiview_path

    def set_constant(name: str, value) -> None:
        found = [m for m in (matches, planar_features, guided_matching, match_refinement, multiview_path, features)
                 if hasattr(m, name)]
        if not found:
            raise AttributeError(f"no calibration module has {name}")
        for module in found:
            monkeypatch.setattr(module, name, value)

    return set_constant
