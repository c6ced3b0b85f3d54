"""Sub-pixel matches: each feature match moved to where the two views' patches align.

A SIFT keypoint sits where a blob of some scale peaks; under the perspective and the lens between
two views the same blob peaks at a slightly different place, so a match's two points are not the
same point of the scene to well under a pixel (on real views of a chessboard the refinement
below moves them by most of a pixel: docs/method.md, section 12). Once a fit has the lens and
each pair's homography, the second view's neighbourhood of a match is the first view's under a
known local map; aligning the two patches pins the partner of the first view's point to a few
hundredths of a pixel on texture (the idea of feature-metric refinement in structure from
motion).
docs/method.md, section 12, step 11.

For each match (x1 in view i, x2 in view j) of a pair with homography H between ideal points:

1. **The local map**: the affine A = d/dx of x -> lens^-1(H lens(x)) at x1 (central differences
   of :func:`~lensdist_torch.geometry.radial_lens.lens_ideal_points` and its inverse), so the
   first view's offset d from x1 lands at A d from x2.
2. **Alignment** (:func:`align_patches`): the first view's (2 ``half`` + 1)^2 patch about x1
   (Gaussian window of standard deviation ``half`` / 2) against the second view sampled at
   x2 + t + A d, Gauss-Newton on t and a gain and offset of the intensities (exposure changes
   between views), both images smoothed by a Gaussian of ``PLANAR_REFINE_BLUR`` px, gradients by
   kornia's normalised Sobel.
3. **Kept** where the alignment converged (last step under 0.02 px), moved at most
   ``PLANAR_INLIER_PX``, both patches lie inside their frames, the patch has texture in both
   directions (the smaller eigenvalue of its gradients' moment matrix), and the aligned patches'
   windowed normalised cross-correlation is at least ``PLANAR_REFINE_NCC``; the others are dropped.

The first view's point stays where it was: the pair's correspondence is what the fit needs, not
a keypoint's detection.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, spatial_gradient

from lensdist_torch.calibration.matches import PLANAR_MIN_MATCHES, PlanarMatches
from lensdist_torch.calibration.planar_features import PLANAR_INLIER_PX
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.geometry.radial_lens import lens_distorted_points, lens_ideal_points

__all__ = ["PLANAR_REFINE_BLUR", "PLANAR_REFINE_NCC", "PLANAR_REFINE_PX", "align_patches", "local_affines",
           "refine_matches"]

#: The half size (px) of the patches that move each match to where the two views align; 0: no refinement.
PLANAR_REFINE_PX = 7
#: The Gaussian's standard deviation (px) that smooths the frames for the refinement.
PLANAR_REFINE_BLUR = 1.0
#: A refined match is kept where its aligned patches correlate at least this much (normalised cross-correlation).
PLANAR_REFINE_NCC = 0.9

_CONVERGED_PX = 0.02  # the last Gauss-Newton step of a kept match is shorter than this (px)
_MIN_TEXTURE = (
    1e-5  # the smaller eigenvalue of a kept patch's windowed mean gradient moments (intensity in [0, 1] per px)
)


def _sample(image: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of a (C, H, W) image at (K, P, 2) pixel coordinates (centres at integers), (C, K, P) float64."""
    _, h, w = image.shape
    grid = torch.stack([2 * points[..., 0] / (w - 1) - 1, 2 * points[..., 1] / (h - 1) - 1], -1)
    out = F.grid_sample(image[None], grid.reshape(1, -1, 1, 2).to(image.dtype), mode="bilinear",
                        padding_mode="zeros", align_corners=True)
    return out.reshape(image.shape[0], *points.shape[:-1]).double()


def _prepared(image: torch.Tensor, blur: float) -> torch.Tensor:
    """(3, H, W): a (H, W) grey image smoothed by a Gaussian of ``blur`` px (none at 0), its x and y gradients."""
    x = image.float()[None, None]
    if blur > 0:
        k = 2 * int(3 * blur + 0.5) + 1
        x = gaussian_blur2d(x, (k, k), (blur, blur))
    return torch.cat([x[0], spatial_gradient(x, "sobel", normalized=True)[0, 0]], 0)


def align_patches(
    image1: torch.Tensor,
    image2: torch.Tensor,
    x1: torch.Tensor,
    x2: torch.Tensor,
    *,
    affine: torch.Tensor,
    half: int = 7,
    iterations: int = 15,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each point of the second view moved to where its patch aligns with the first view's (module docstring, step 2).

    Args:
        image1: the first view, (3, H, W): the smoothed image, its x and y gradients (the gradients unused).
        image2: the second view, the same.
        x1: (K, 2) float64 points of the first view (pixels, centres at integers).
        x2: (K, 2) their partners' starting points in the second view.
        affine: (K, 2, 2) the local map: offset d from x1 lands at affine @ d from x2.
        half: the patch's half size (px); a (2 half + 1)^2 patch, Gaussian window of std half / 2.
        iterations: Gauss-Newton steps at most on the shift, a gain and an offset (fewer once every
            step is under a tenth of the convergence test's 0.02 px).

    Returns:
        (x2 refined (K, 2), normalised cross-correlation of the aligned patches (K,), a (K,) bool:
        converged, with texture in both directions).

    Example:
        >>> yy, xx = torch.meshgrid(torch.arange(60.0), torch.arange(80.0), indexing="ij")
        >>> scene = lambda x, y: torch.sin(x / 3.0) * torch.cos(y / 4.0) + 0.3 * torch.sin((x + y) / 5.0)
        >>> a, b = _prepared(scene(xx, yy), 0.0), _prepared(0.8 * scene(xx - 2.3, yy + 1.6) + 0.1, 0.0)
        >>> x1 = torch.tensor([[30.0, 25.0], [40.0, 30.0]], dtype=torch.float64)
        >>> out, ncc, ok = align_patches(a, b, x1, x1 + torch.tensor([3.0, -1.0], dtype=torch.float64),
        ...                              affine=torch.eye(2, dtype=torch.float64).expand(2, 2, 2))
        >>> [[round(v, 2) for v in p] for p in (out - x1).tolist()], ok.tolist()  # the shift (2.3, -1.6) under gain 0.8
        ([[2.3, -1.6], [2.3, -1.6]], [True, True])
    """
    r = torch.arange(-half, half + 1, dtype=torch.float64)
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    offsets = torch.stack([dx.reshape(-1), dy.reshape(-1)], -1)
    window = torch.exp(-(offsets ** 2).sum(1) / (2 * (half / 2) ** 2))
    template = _sample(image1[:1], x1[:, None] + offsets)[0]
    spread = torch.einsum("kab,pb->kpa", affine, offsets)
    t = x2.clone()
    gain = torch.ones(len(t), dtype=torch.float64)
    offset = torch.zeros(len(t), dtype=torch.float64)
    step = torch.full((len(t), 2), float("inf"), dtype=torch.float64)
    eye = 1e-9 * torch.eye(4, dtype=torch.float64)
    active = torch.arange(len(t))
    for _ in range(iterations):  # the matches whose last step was under a tenth of the test's stay where they are
        a = active
        value, gx, gy = _sample(image2, t[a, None] + spread[a])
        jac = torch.stack([gx, gy, -template[a], -torch.ones_like(gx)], -1)  # d residual / d (t_x, t_y, gain, offset)
        res = value - gain[a, None] * template[a] - offset[a, None]
        jw = jac * window[None, :, None]
        delta = -torch.linalg.solve(jw.transpose(1, 2) @ jac + eye, (jw * res[..., None]).sum(1)[..., None])[..., 0]
        move = delta[:, :2].clamp(-1.0, 1.0)  # a step of at most a pixel: the linearisation holds about that far
        t[a], gain[a], offset[a], step[a] = t[a] + move, gain[a] + delta[:, 2], offset[a] + delta[:, 3], move
        active = a[move.norm(dim=1) >= 0.1 * _CONVERGED_PX]
        if len(active) == 0:
            break
    value, gx, gy = _sample(image2, t[:, None] + spread)
    wsum = window.sum()
    tc = template - (template * window).sum(1, keepdim=True) / wsum
    vc = value - (value * window).sum(1, keepdim=True) / wsum
    ncc = (tc * vc * window).sum(1) / torch.sqrt((tc * tc * window).sum(1) * (vc * vc * window).sum(1)).clamp_min(1e-12)
    g = torch.stack([gx, gy], -1)
    texture = torch.linalg.eigvalsh((g * window[None, :, None]).transpose(1, 2) @ g / wsum)[:, 0]
    ok = torch.isfinite(t).all(1) & (step.norm(dim=1) < _CONVERGED_PX) & (texture > _MIN_TEXTURE)
    return t, ncc, ok


def local_affines(x1: torch.Tensor, homography: torch.Tensor, coefficients, *, centre, size: tuple[int, int],
                  eps: float = 0.5) -> torch.Tensor:
    """(K, 2, 2): the derivative at ``x1`` (K, 2) of x -> lens^-1(H lens(x)), H (3, 3) between ideal points (step 1).

    Example:
        >>> x = torch.tensor([[100.0, 80.0]], dtype=torch.float64)
        >>> h = torch.tensor([[2.0, 0.0, 5.0], [0.0, 2.0, -3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> local_affines(x, h, [0.0], centre=None, size=(240, 320)).squeeze(0).tolist()  # no lens: H's scale
        [[2.0, 0.0], [0.0, 2.0]]
    """
    h, w = size

    def f(x):
        ideal = lens_ideal_points(x, coefficients, h, w, centre=centre)
        return lens_distorted_points(apply_homography(homography[None], ideal)[0], coefficients, h, w, centre=centre)[0]

    cols = []
    for e in torch.eye(2, dtype=x1.dtype):
        cols.append((f(x1 + eps * e) - f(x1 - eps * e)) / (2 * eps))
    return torch.stack(cols, -1)


def refine_matches(matches, images: Callable[[int], torch.Tensor], homographies: dict, coefficients, *, centre,
                   size: tuple[int, int], min_matches: int = PLANAR_MIN_MATCHES, cache_mb: float = 256.0):
    """Every match of a pair with a homography moved to sub-pixel agreement (module docstring); the others dropped.

    Args:
        matches: :class:`~lensdist_torch.calibration.matches.PlanarMatches`.
        images: view index -> its (H, W) grey image in [0, 1] (called again for a view only once it has left
            the cache).
        homographies: {(i, j): 3 x 3 homography from view i's ideal pixels to view j's}; a pair
            without one is dropped.
        coefficients: the lens's a_1 .. a_n (:func:`~lensdist_torch.geometry.radial_lens.lens_ideal_points`).
        centre: its distortion centre (x, y) in pixels; None: the frame centre.
        size: the frames' (H, W).
        min_matches: a pair keeping fewer refined matches is dropped (the constants :data:`PLANAR_REFINE_PX`,
            :data:`PLANAR_REFINE_BLUR`, :data:`PLANAR_REFINE_NCC` and ``PLANAR_INLIER_PX`` shape the refinement).
        cache_mb: the prepared views (the smoothed frame and its gradients, 12 bytes a pixel) kept at once,
            in MB, at least two; the least recently used leaves first (pairs in order of their first view).
            A cache too small for the views a pair sequence revisits reads the frames again and again.

    Returns:
        (matches, info): the refined matches (pairs keeping ``min_matches``, renumbered),
        and {"matches", "kept", "median_shift_px"}.
    """
    h, w = size
    half = PLANAR_REFINE_PX
    ready: OrderedDict = OrderedDict()
    most = max(2, int(cache_mb * 2**20 // (12 * h * w)))

    def view(v):
        if v not in ready:
            image = images(v)
            if tuple(image.shape) != (h, w):
                raise ValueError(f"images: view {v} is {tuple(image.shape)}, expected the frames' (H, W) = {(h, w)}")
            ready[v] = _prepared(image, PLANAR_REFINE_BLUR)
            if len(ready) > most:
                ready.popitem(last=False)
        ready.move_to_end(v)
        return ready[v]

    def inside(x):  # the whole patch within the frame
        return (x[:, 0] >= half) & (x[:, 1] >= half) & (x[:, 0] <= w - 1 - half) & (x[:, 1] <= h - 1 - half)

    x1s, x2s, pairs, first, second, shifts = [], [], [], [], [], []
    order = sorted(range(len(matches.first)), key=lambda p: (int(matches.first[p]), int(matches.second[p])))
    for p in order:
        i, j = int(matches.first[p]), int(matches.second[p])
        hm = homographies.get((i, j))
        if hm is None:
            continue
        sel = (matches.pair == p).nonzero()[:, 0]
        x1, x2 = matches.x1[sel], matches.x2[sel]
        affine = local_affines(x1, hm, coefficients, centre=centre, size=size)
        moved, ncc, ok = align_patches(view(i), view(j), x1, x2, affine=affine, half=half)
        shift = (moved - x2).norm(dim=1)
        keep = ok & (ncc >= PLANAR_REFINE_NCC) & (shift <= PLANAR_INLIER_PX) & inside(x1) & inside(moved)
        if int(keep.sum()) < min_matches:
            continue
        x1s.append(x1[keep])
        x2s.append(moved[keep])
        shifts.append(shift[keep])
        pairs.append(torch.full((int(keep.sum()),), len(first), dtype=torch.long))
        first.append(i)
        second.append(j)
    empty = torch.zeros(0, 2, dtype=torch.float64)
    out = PlanarMatches(
        x1=torch.cat(x1s) if x1s else empty, x2=torch.cat(x2s) if x2s else empty,
        pair=torch.cat(pairs) if pairs else torch.zeros(0, dtype=torch.long),
        first=torch.tensor(first, dtype=torch.long), second=torch.tensor(second, dtype=torch.long),
        names=matches.names)
    info = {"matches": len(matches.pair), "kept": len(out.pair),
            "median_shift_px": float(torch.cat(shifts).median()) if shifts else float("nan")}
    return out, info
