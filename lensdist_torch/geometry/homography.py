"""Homography helpers on (B, 3, 3) tensors: checks, the class-R perturbation, corner error, motion.

The perturbation is that of docs/method.md, section 7.
"""

from __future__ import annotations

from typing import Sequence

import torch

__all__ = ["perturb_homography", "corner_error", "check_homography", "apply_homography", "mean_displacement"]


def apply_homography(hn: torch.Tensor, pts: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) homographies applied to (K, 2) points -> (B, K, 2).

    Example:
        >>> shift = torch.tensor([[1.0, 0, 3], [0, 1, 4], [0, 0, 1]])  # moves every point by (3, 4)
        >>> half = torch.diag(torch.tensor([1.0, 1.0, 2.0]))  # w = 2: every point halved
        >>> apply_homography(torch.stack([shift, half]), torch.tensor([[0.0, 0.0], [10.0, 20.0]])).tolist()
        [[[3.0, 4.0], [13.0, 24.0]], [[0.0, 0.0], [5.0, 10.0]]]
    """
    q = hn[:, None, :, :2] @ pts[None, :, :, None] + hn[:, None, :, 2:]
    return q[..., :2, 0] / q[..., 2:, 0]


def check_homography(h: object, name: str, batch: int | None = None) -> torch.Tensor:
    """``h`` itself if it is a finite float (B, 3, 3) tensor (B = ``batch`` when given), else a one-line error."""
    if not isinstance(h, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(h).__name__}")
    if h.dim() != 3 or h.shape[1:] != (3, 3) or (batch is not None and h.shape[0] != batch):
        raise ValueError(f"{name} must have shape ({'B' if batch is None else batch}, 3, 3), got {tuple(h.shape)}")
    if not h.is_floating_point() or not bool(torch.isfinite(h).all()):
        raise ValueError(f"{name} must be a finite float tensor")
    return h


def perturb_homography(
    H: torch.Tensor,
    generator: torch.Generator | Sequence[torch.Generator],
    amount: float = 0.01,
    *,
    size: tuple[int, int],
) -> torch.Tensor:
    """The class-R perturbation (docs/method.md, section 7), in centred coordinates.

    H_c = T(-p0) H T(p0) with h33 = 1; each of its 8 free parameters (row-major h11..h32) is
    multiplied by (1 + e), e = amount * (2 * torch.rand(8, dtype=float64) - 1) drawn from the
    pair's generator in one call; the result is T(p0) H_c T(-p0) with h33 = 1, and
    p0 = ((W - 1) / 2, (H - 1) / 2).

    Args:
        H: (3, 3), or (B, 3, 3) with one generator per pair (section 7: a pair's draw must not
            depend on the batch, so a single generator is accepted for B = 1 only).
        generator: a torch.Generator, or a sequence of B of them.
        amount: half-width of the relative perturbation, in [0, 1).
        size: (height, width) of the images H applies to (keyword only).

    Returns:
        The perturbed homographies, H's shape and dtype.

    Example:
        >>> H = torch.tensor([[1.0, 0, 3], [0, 1, 4], [0, 0, 1]], dtype=torch.float64)
        >>> Hp = perturb_homography(H, torch.Generator().manual_seed(0), 0.01, size=(320, 424))
        >>> round(float(corner_error(Hp, H, 320, 424)[0]), 2)  # px, how far its corners moved on average
        2.04
    """
    if not isinstance(H, torch.Tensor):
        raise TypeError(f"H must be a torch.Tensor, got {type(H).__name__}")
    if H.dim() not in (2, 3) or H.shape[-2:] != (3, 3) or not H.is_floating_point():
        raise ValueError(f"H must be a float tensor of shape (3, 3) or (B, 3, 3), got {tuple(H.shape)} {H.dtype}")
    gens = [generator] if isinstance(generator, torch.Generator) else list(generator)
    hb = H if H.dim() == 3 else H[None]
    if len(gens) != hb.shape[0] or not all(isinstance(g, torch.Generator) for g in gens):
        raise ValueError(f"generator must be one torch.Generator per pair ({hb.shape[0]}), got {generator!r}")
    if isinstance(amount, bool) or not isinstance(amount, (int, float)) or not 0 <= amount < 1:
        raise ValueError(f"amount must be a number in [0, 1), got {amount!r}")
    if not (isinstance(size, (tuple, list)) and len(size) == 2 and all(type(s) is int and s > 0 for s in size)):
        raise ValueError(f"size must be (height, width) of positive ints, got {size!r}")
    e = torch.stack([torch.rand(8, generator=g, dtype=torch.float64, device=g.device) for g in gens])
    e = (2 * e - 1).to(H.device) * amount
    t_plus, t_minus = (torch.tensor([[1, 0, k * (size[1] - 1) / 2], [0, 1, k * (size[0] - 1) / 2], [0, 0, 1]],
                                    dtype=torch.float64, device=H.device) for k in (1, -1))
    hc = t_minus @ hb.double() @ t_plus
    hc = (hc / hc[:, 2:, 2:]).flatten(1)
    out = t_plus @ torch.cat([hc[:, :8] * (1 + e), hc[:, 8:]], 1).view(-1, 3, 3) @ t_minus
    out = (out / out[:, 2:, 2:]).to(H.dtype)
    return out if H.dim() == 3 else out[0]


def corner_error(H_est: torch.Tensor, H_true: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Mean distance (px) between the image corners mapped by H_est and by H_true.

    Corners (0, 0), (W-1, 0), (W-1, H-1), (0, H-1); H_est, H_true (B, 3, 3) or (3, 3) -> (B,)
    float64 (B = 1 for (3, 3)).

    Example:
        >>> shift = torch.tensor([[1.0, 0, 3], [0, 1, 4], [0, 0, 1]])  # every corner moved by (3, 4)
        >>> corner_error(shift, torch.eye(3), 32, 32).tolist()
        [5.0]
    """
    a, b = (x[None] if isinstance(x, torch.Tensor) and x.dim() == 2 else x for x in (H_est, H_true))
    a = check_homography(a, "H_est")
    b = check_homography(b, "H_true", a.shape[0]).to(a.device)
    pts = [[0, 0], [width - 1, 0], [width - 1, height - 1], [0, height - 1]]
    pts = torch.tensor(pts, dtype=torch.float64, device=a.device)
    return (apply_homography(a.double(), pts) - apply_homography(b.double(), pts)).norm(dim=-1).mean(1)


def mean_displacement(H: torch.Tensor, height: int, width: int, step: int = 4) -> torch.Tensor:
    """How far a pair moved: the mean of |H p - p| (px) over the frame, on a grid of every ``step`` px.

    This is the motion that reveals a lens's distortion: both views carry the same distortion,
    which cancels where a point did not move (docs/method.md, section 10). NaN where H is not
    finite.

    Args:
        H: (B, 3, 3) or (3, 3) homographies img1 -> img2, in pixels of a height x width frame.
        height: the frame's height (px).
        width: the frame's width (px).
        step: the grid's spacing (px).

    Returns:
        (B,) float64 (B = 1 for (3, 3)).

    Example:
        >>> H = torch.tensor([[1.0, 0, 3], [0, 1, 4], [0, 0, 1]])
        >>> float(mean_displacement(H, 32, 32)[0])
        5.0
    """
    hb = H[None] if isinstance(H, torch.Tensor) and H.dim() == 2 else H
    if not isinstance(hb, torch.Tensor) or hb.dim() != 3 or hb.shape[1:] != (3, 3) or not hb.is_floating_point():
        raise ValueError(
            f"H must be a float tensor of shape (3, 3) or (B, 3, 3), got {getattr(H, 'shape', type(H).__name__)}"
        )
    hb = hb.double()
    ys = torch.arange(0, height, step, dtype=torch.float64, device=hb.device)
    xs = torch.arange(0, width, step, dtype=torch.float64, device=hb.device)
    pts = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), -1).reshape(-1, 2)
    return (apply_homography(hb, pts) - pts).norm(dim=-1).mean(1)
