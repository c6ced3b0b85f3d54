"""A sequence's pairs for the direct path: which frames pair by their motion, and why none does.

Step 2 of :mod:`~lensdist_torch.calibration.direct`: a camera path from consecutive phase
correlations (a running median of 5 against a broken frame); each frame is paired with the
first later frame that moved by each fraction :data:`MOTION_STEPS` of the half diagonal R
(little motion cancels the distortion), at most :data:`MAX_MOTION` R. Where no pair is found,
:func:`no_pairs_reason` says why: no texture, too little motion, or no registration.
"""

from __future__ import annotations

import torch

from lensdist_torch.config import CalibrationConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.phase import phase_correlation

__all__ = ["FLAT_TEXTURE", "MAX_MOTION", "MOTION_STEPS", "NO_TEXTURE", "TOO_LITTLE_MOTION", "choose_pairs",
           "no_pairs_reason"]

#: Each frame's pairs: the first later frames moved by these shares of the half diagonal R.
MOTION_STEPS = (0.14, 0.22)
#: No pair moves by more than this share of the half diagonal R.
MAX_MOTION = 0.35


def choose_pairs(frames: torch.Tensor, config: CalibrationConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pairs of frames that moved enough (module docstring).

    Args:
        frames: (N, 1, h, w) analysis frames, float.
        config: :class:`~lensdist_torch.config.CalibrationConfig`.

    Returns:
        pairs: (P, 2) int64 frame indices (i, j), i < j, sorted.
        shifts: (P, 2) float64 translations t (x, y), frame i (p) ~ frame j (p + t), each pair's
            own phase correlation.

    Example:
        >>> x = torch.rand(1, 1, 200, 200)
        >>> frames = torch.cat([torch.roll(x, -8 * i, dims=2) for i in range(12)])  # 8 px a frame
        >>> choose_pairs(frames)[0][:3].tolist()  # 0.14 and 0.22 of R = 141 px: 24 and 32 px apart
        [[0, 3], [0, 4], [1, 4]]
    """
    cfg = or_defaults(config, CalibrationConfig)
    n, _, h, w = frames.shape
    if n < 2:
        return torch.zeros(0, 2, dtype=torch.int64), torch.zeros(0, 2, dtype=torch.float64)
    steps = torch.cat(
        [_translation(frames[i : min(i + 16, n - 1)], frames[i + 1 : i + 17]) for i in range(0, n - 1, 16)]
    )
    if n > 5:  # a running median of 5 steps: a broken frame (two wrong steps) leaves the path whole
        steps = torch.cat([steps[:1]] * 2 + [steps] + [steps[-1:]] * 2).unfold(0, 5, 1).median(-1).values
    path = torch.cat([torch.zeros(1, 2, dtype=torch.float64), steps.cumsum(0)])
    r = half_diagonal(h, w)
    moved = (path[None] - path[:, None]).norm(dim=-1)  # (N, N): |path_j - path_i|
    chosen: set[tuple[int, int]] = set()
    for i in range(n - 1):
        for step in MOTION_STEPS:
            far = (moved[i, i + 1 :] >= step * r).nonzero()
            if len(far) and moved[i, i + 1 + int(far[0])] <= MAX_MOTION * r:
                chosen.add((i, i + 1 + int(far[0])))
    pairs = torch.tensor(sorted(chosen), dtype=torch.int64).reshape(-1, 2)
    if len(pairs) > cfg.max_pairs:
        pairs = pairs[torch.linspace(0, len(pairs) - 1, cfg.max_pairs).round().long()]
    shifts = [_translation(frames[p[:, 0]], frames[p[:, 1]]) for p in pairs.split(16) if len(p)]  # each its own
    return pairs, torch.cat(shifts) if shifts else torch.zeros(0, 2, dtype=torch.float64)


#: How :func:`no_pairs_reason` begins where the frames did not move enough (``calibrate`` then runs no mapping).
TOO_LITTLE_MOTION = "too little motion"
#: How it begins where no frame has texture to register (``calibrate`` then runs no mapping either).
NO_TEXTURE = "no texture"
#: A frame is flat where it differs from itself moved by 2 px by less than this (mean absolute, on [0, 1]): one grey
#: level of an 8-bit frame.
FLAT_TEXTURE = 1 / 255


def no_pairs_reason(frames: torch.Tensor) -> str:
    """Why :func:`choose_pairs` found no pair: no texture, too little motion, or no registration.

    No texture where every frame differs from itself moved by 2 px by less than
    :data:`FLAT_TEXTURE` (nothing to register, however the camera moved). Too little motion
    where neighbouring frames differ less than half as much as a frame
    differs from itself moved by 2 px (they did not move), or where every neighbour, moved back by
    its phase-correlation translation, matches that well (they moved, and consistently) but the
    camera path never spans ``MOTION_STEPS[0]`` of the half diagonal; otherwise they changed
    and the phase correlation could not relate them: a registration failure (views too far
    apart, or unrelated).

    Example:
        >>> x = torch.rand(1, 1, 64, 64)
        >>> no_pairs_reason(torch.cat([x, x + 0.01]))
        'too little motion: no two frames moved enough apart'
        >>> no_pairs_reason(torch.cat([x, torch.rand(1, 1, 64, 64)]))[:30]
        'the frames could not be regist'
        >>> no_pairs_reason(torch.full((3, 1, 64, 64), 0.5))[:40]
        'no texture: every frame is flat (it diff'
    """
    x = frames.float()
    a, b = x[:-1], x[1:]
    static = (a - b).abs().mean(dim=(1, 2, 3))
    every = (x - torch.roll(x, (2, 2), dims=(2, 3))).abs()[..., 2:, 2:].mean(dim=(1, 2, 3))  # each frame's texture
    texture = every[:-1]
    if bool((every < FLAT_TEXTURE).all()):
        return (f"{NO_TEXTURE}: every frame is flat (it differs from itself moved by 2 px by less than one grey "
                "level): nothing to register, however the camera moved")
    if bool((static <= 0.5 * texture).all()):
        return f"{TOO_LITTLE_MOTION}: no two frames moved enough apart"
    t = _translation(a, b)  # a(p) ~ b(p + t): b moved back by t matches a where they were registered
    m = int(t.abs().max().ceil()) + 2
    back = torch.stack(
        [torch.roll(b[i], (-round(float(t[i, 1])), -round(float(t[i, 0]))), dims=(1, 2)) for i in range(len(b))]
    )
    aligned = (a - back).abs()[..., m:-m, m:-m].mean(dim=(1, 2, 3)) if 2 * m < min(a.shape[-2:]) else static
    if bool((aligned <= 0.5 * texture).all()):
        path = torch.cat([torch.zeros(1, 2, dtype=torch.float64), t.cumsum(0)])
        span = float((path[None] - path[:, None]).norm(dim=-1).max())
        need = min(MOTION_STEPS) * half_diagonal(*frames.shape[-2:])
        return (
            f"{TOO_LITTLE_MOTION}: the camera moved {span:.1f} px at most between two frames "
            f"(a pair needs {need:.1f} px)"
        )
    return ("the frames could not be registered: they change, but phase correlation finds no consistent motion "
            "between neighbours (views too far apart or unrelated)")


def _translation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(n, 1, h, w) twice -> (n, 2) float64 t on the CPU with a(p) ~ b(p + t) (phase correlation)."""
    return phase_correlation(a[:, 0], b[:, 0]).double().cpu()
