"""Shared by the self-calibration tests: a smooth test image, a level of central samples on it, the
finite-difference check of the model's Jacobian columns, and rendered pairs of a scene with relief."""

from __future__ import annotations

import pytest
import torch

from lensdist_torch.config import LensdistConfig, ProtocolConfig
from lensdist_torch.core.images import load_scene
from lensdist_torch.data import realism
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.distortion import delta_avg
from lensdist_torch.geometry.frame import half_diagonal, level_to_grid, normalized_grid
from lensdist_torch.selfcal import model as selfcal_model


def smooth(h: int, w: int, dx: float, dy: float) -> torch.Tensor:
    """(1, 1, h, w) float32 sum of sinusoids shifted by (dx, dy) px: smooth enough for finite differences."""
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    x, y = xx + dx, yy + dy
    return (0.5 + 0.2 * torch.sin(x / 15) * torch.cos(y / 21) + 0.1 * torch.sin((x + 0.5 * y) / 12)).float()[None, None]


def central_level(photometric: str, *, relief_n: int = 0, direction=None, h: int = 60, w: int = 80):
    """(level, samples N) of :func:`smooth` shifted by (1.5, 2.0) px, sampled within 0.4 half-diagonals
    of the centre (8 Newton steps, margin 4 px, floor 1e-6); with ``relief_n`` a relief_n^2-bump basis
    (width 0.3) moving img2's points along ``direction`` (1, 2)."""
    i1, i2 = smooth(h, w, 0, 0), smooth(h, w, 1.5, 2.0)
    ud = normalized_grid(0, h, w, full_height=h, full_width=w).view(-1, 2)
    idx = torch.nonzero(ud.norm(dim=-1) < 0.4).flatten()[None]
    ux, uy = ud[idx, 0], ud[idx, 1]
    basis = selfcal_model.relief_basis(ux, uy, n=relief_n, width=0.3, h0=h, w0=w) if relief_n else None
    lv = selfcal_model.Level(
        i1=torch.gather(i1.flatten(1), 1, idx), stack2=selfcal_model.with_gradients(i2), ux_d=ux, uy_d=uy,
        rho=ux * ux + uy * uy, px=half_diagonal(h, w), to_grid=level_to_grid(0, h, w, full_height=h, full_width=w),
        newton=8, margin=4.0, photometric=photometric, floor=1e-6, basis=basis, direction=direction,
    )
    return lv, idx.shape[1]


def assert_columns_match_finite_differences(
    theta: torch.Tensor, lv: selfcal_model.Level, columns, eps: float = 1e-3
) -> None:
    """Each listed column of ``evaluate``'s Jacobian against central differences of its residual
    (relative L2 error < 6 %; the valid set must not change with the steps)."""
    _, valid, J = selfcal_model.evaluate(theta, lv)
    for k in columns:
        step = torch.zeros_like(theta)
        step[0, k] = eps
        (rp, vp, _), (rm, vm, _) = (selfcal_model.evaluate(theta + s, lv, jac=False) for s in (step, -step))
        assert bool((vp & vm & valid).all())
        fd = (rp - rm) / (2 * eps)
        assert float((J[0, k] - fd[0]).norm() / fd[0].norm()) < 0.06, k


#: realism's constants with every effect of the realistic protocol off (JPEG at quality 100, no occluder).
NEUTRAL = {"GAIN_RANGE": (1.0, 1.0), "OFFSET_RANGE": (0.0, 0.0), "GAMMA_RANGE": (1.0, 1.0), "ILLUMINATION": 0.0,
           "NOISE_RANGE": (0.0, 0.0), "JPEG_QUALITY": (100, 100), "OCCLUDER_RATE": 0.0}


def relief_only_pairs(relief: float, n: int):
    """The first n test pairs of the realistic protocol with every effect off but the scene's
    relief (up to ``relief`` of camera 1's height; the parallax follows each pair's motion):
    img1, img2 (n, 1, H, W) and their true Delta_avg (n,)."""
    cfg = LensdistConfig(protocol=ProtocolConfig(realistic=True, relief=relief))
    with pytest.MonkeyPatch.context() as mp:  # realism's constants: every effect off
        for name, value in NEUTRAL.items():
            mp.setattr(realism, name, value)
        p = draw_pairs(cfg, "test", list(range(n)), 2)
        i1, i2 = render_pairs([load_scene("gravel"), load_scene("grass")], p, cfg)
    return i1, i2, delta_avg(p.k2, p.k4, *cfg.image.size)
