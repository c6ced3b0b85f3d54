"""Registration of far-apart pairs: hand-crafted features, then the direct refinement (docs/method.md, section 10).

:func:`~lensdist_torch.registration.direct.estimate_homography` starts from a translation (phase
correlation) and its inverse-compositional Gauss-Newton only reaches homographies near it; its pixel
rectangle, inscribed in the overlap corner by corner, also empties past ~35 degrees of rotation even
from the true H. :func:`estimate_homography_robust` keeps its answer for every pair it registers and,
for the others:

1. :func:`feature_homography`: kornia's weight-free SIFT (multi-resolution DoG detector, dominant
   gradient orientation, RootSIFT descriptor; nothing is downloaded), mutual nearest neighbours
   with the second-nearest ratio test (``match_smnn``), and RANSAC (MSAC, Levenberg-Marquardt
   local optimisation, a fixed seed) for H; a pair without :data:`MIN_INLIERS` inliers, or whose H
   sends a corner of img1 behind the camera, has no feature estimate.
2. The refinement in img1's frame: the largest axis-aligned rectangle of img1 whose pixels the feature H maps at
   least :data:`~lensdist_torch.registration.direct.MARGIN` px inside img2 (exact for the convex overlap, on a 4 px
   grid), img2 warped into it by the feature H (bilinear), and ``estimate_homography`` of that
   crop against the warped crop from the identity: the remaining motion is small, so its own
   checks (texture, divergence, residual, step) decide. H = H_f T H_r T^-1, T the crop's offset.
3. ``converged`` also needs the final H to map ``direct.MIN_OVERLAP`` of img1 inside img2; ``overlap``
   is that fraction (img1's pixels on a 4 px grid), ``residual`` and ``textured`` are the crop's,
   ``iterations`` both runs'. A pair that fails again keeps the first run's H and diagnostics
   (``converged=False``: could not register).

The fallback loops over its pairs (mostly the descriptors); pairs that the first run registers
cost nothing more. A :class:`SiftMemo` passed as ``memo`` describes each distinct image once: a
sequence's frames recur in several pairs.
"""

from __future__ import annotations

import functools
import hashlib

import torch
from kornia.feature import SIFTFeature, get_laf_center, match_smnn
from kornia.geometry import RANSAC

from lensdist_torch.config import RegistrationConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.images import check_image_pair, to_grey
from lensdist_torch.registration.direct import (
    MARGIN,
    MIN_OVERLAP,
    RegistrationInfo,
    estimate_homography,
    warp_to_reference,
)

__all__ = [
    "FEATURE_FALLBACK", "MATCH_RATIO", "MAX_KEYPOINTS", "MIN_INLIERS", "RANSAC_THRESHOLD", "SiftMemo",
    "estimate_homography_robust", "feature_homography",
]

_GRID = 4  # px: the grid on which the overlap and the refinement rectangle are measured
#: The pairs the direct registration did not register are retried from SIFT matches (docs/method.md, section 10).
FEATURE_FALLBACK = True
#: SIFT keypoints kept per image (the strongest responses).
MAX_KEYPOINTS = 2000
#: Second-nearest-neighbour ratio of the mutual matches, in ]0, 1].
MATCH_RATIO = 0.9
#: px: one-way transfer error of a RANSAC inlier.
RANSAC_THRESHOLD = 2.0
#: Fewest RANSAC inliers for a feature homography.
MIN_INLIERS = 15


@functools.lru_cache(maxsize=4)
def _sift(max_keypoints: int, device: torch.device) -> SIFTFeature:
    """The detector and descriptor (pure computation, no weights), built once per setting."""
    return SIFTFeature(num_features=max_keypoints, upright=False, rootsift=True, device=device).eval()


def _describe(img: torch.Tensor, max_keypoints: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One image (1, C, H, W) -> its keypoints' centres (K, 2), RootSIFT descriptors (K, 128); flat patches dropped."""
    lafs, resp, d = _sift(max_keypoints, img.device)(to_grey(img).float())
    keep = (resp[0] > 0) & torch.isfinite(d[0]).all(1)  # a flat patch has no response
    return get_laf_center(lafs)[0][keep], d[0][keep]


class SiftMemo:
    """Each distinct image's SIFT keypoints and descriptors, computed once.

    Keyed by a digest of the image's values, shape, dtype and device and the keypoint budget, so
    a frame gathered into several pair batches (a sequence's pairs share frames) is described
    once. Kept for the life of the object: make one per sequence.

    Example:
        >>> from lensdist_torch.core.images import load_scene
        >>> s = load_scene("gravel")
        >>> a, b, c = s[..., 100:300, 100:400], s[..., 80:280, 130:430], s[..., 60:260, 160:460]
        >>> memo = SiftMemo()
        >>> H, ok, _ = feature_homography(torch.cat([a, b]), torch.cat([b, c]), memo=memo)
        >>> ok.tolist(), len(memo)  # three distinct images in two pairs
        ([True, True], 3)
    """

    def __init__(self) -> None:
        self._store: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    def __len__(self) -> int:
        return len(self._store)

    def __call__(self, img: torch.Tensor, max_keypoints: int) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`_describe` of ``img`` (1, C, H, W), from the memo where these values were described before."""
        digest = hashlib.blake2b(
            img.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes(), digest_size=16
        ).hexdigest()
        key = (digest, tuple(img.shape), str(img.dtype), str(img.device), max_keypoints)
        if key not in self._store:
            self._store[key] = _describe(img, max_keypoints)
        return self._store[key]


def _config(config: object) -> RegistrationConfig:
    return or_defaults(config, RegistrationConfig)


def _corners(h: int, w: int, **kw) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0], [w - 1.0, 0.0], [w - 1.0, h - 1.0], [0.0, h - 1.0]], **kw)


def _in_front(m: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """(B,) bool: m is finite and maps img1's four corners to w > 0 (no line at infinity inside img1)."""
    den = m[:, 2:, :2] @ _corners(h, w, dtype=m.dtype, device=m.device).T + m[:, 2:, 2:]
    return torch.isfinite(m).all(dim=(1, 2)) & (den[:, 0] > 0).all(1)


@torch.no_grad()
def feature_homography(
    img1: torch.Tensor, img2: torch.Tensor, config: RegistrationConfig | None = None, validate: bool = True, *,
    memo: SiftMemo | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per pair, a homography from SIFT matches and RANSAC, img1(p) = img2(H p).

    The coarse estimate of the fallback (docs/method.md, section 10): a fraction of a pixel to a
    pixel from the truth on rendered pairs; :func:`estimate_homography_robust` refines it. Pairs
    are processed one by one, on grey images at the size given (the analysis size).

    Args:
        img1: (B, C, H, W) float in [0, 1] or uint8, C in {1, 3}.
        img2: the same shape and dtype as img1.
        config: a :class:`~lensdist_torch.config.RegistrationConfig` or None; none of its fields changes the
            features (:data:`MAX_KEYPOINTS`, :data:`MATCH_RATIO`, :data:`RANSAC_THRESHOLD`, :data:`MIN_INLIERS`).
        validate: check the images' values (one host sync); False for images already checked.
        memo: a :class:`SiftMemo` that describes each distinct image once (None: every image
            of every pair is described).

    Returns:
        H: (B, 3, 3) float64 with H[:, 2, 2] = 1, img1 pixel coordinates -> img2's; the identity
            where ``ok`` is False.
        ok: (B,) bool, at least :data:`MIN_INLIERS` inliers and img1's corners in front of the camera.
        n_inliers: (B,) int64 RANSAC inliers (0 without enough matches).

    Example:
        >>> from lensdist_torch.core.images import load_scene
        >>> s = load_scene("gravel")
        >>> img1, img2 = s[..., 100:300, 100:400], s[..., 80:280, 130:430]  # img1(p) = img2(p + (-30, 20))
        >>> H, ok, n = feature_homography(img1, img2)
        >>> bool(ok), [round(float(v)) for v in H[0, :2, 2]]
        (True, [-30, 20])
    """
    _config(config)  # its type: the features' settings are this module's constants
    check_image_pair(img1, img2, finite=validate)
    bsz, _, h0, w0 = img1.shape
    dev = img1.device
    out = torch.eye(3, dtype=torch.float64, device=dev).repeat(bsz, 1, 1)
    ok = torch.zeros(bsz, dtype=torch.bool, device=dev)
    n_inl = torch.zeros(bsz, dtype=torch.int64, device=dev)
    describe = memo if memo is not None else _describe
    ransac = RANSAC("homography", inl_th=RANSAC_THRESHOLD, seed=0)
    for i in range(bsz):
        pts, desc = zip(*(describe(img[i : i + 1], MAX_KEYPOINTS) for img in (img1, img2)))
        if min(len(d) for d in desc) < 4:
            continue
        _, idx = match_smnn(desc[0], desc[1], MATCH_RATIO)
        if len(idx) < max(4, MIN_INLIERS):
            continue
        m, inliers = ransac(pts[0][idx[:, 0]], pts[1][idx[:, 1]])
        m = m.to(torch.float64)[None]
        n_inl[i] = int(inliers.sum())
        if n_inl[i] >= MIN_INLIERS and float(m[0, 2, 2].abs()) > 0:
            m = m / m[:, 2:, 2:]
            if bool(_in_front(m, h0, w0)[0]) and torch.linalg.matrix_rank(m[0]) == 3:
                out[i], ok[i] = m[0], True
    return out, ok, n_inl


def _grid_points(h: int, w: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Every ``_GRID``-th column and row of an h x w image, the last ones included (float64)."""
    kw = {"dtype": torch.float64, "device": device}
    xs, ys = (torch.cat([torch.arange(0, n - 1, _GRID, **kw), torch.tensor([n - 1.0], **kw)]) for n in (w, h))
    return xs, ys


def _inside(m: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor, h: int, w: int, margin: float) -> torch.Tensor:
    """(len(ys), len(xs)) bool: m (3, 3) maps the grid point in front, ``margin`` px inside h x w."""
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    p = torch.stack([xx, yy, torch.ones_like(xx)], -1) @ m.T
    x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
    return (p[..., 2] > 0) & (x >= margin) & (x <= w - 1 - margin) & (y >= margin) & (y <= h - 1 - margin)


def _overlap(H: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B,) fraction of img1's pixels (on a 4 px grid) that H (B, 3, 3) maps inside img2 (same size)."""
    xs, ys = _grid_points(height, width, H.device)
    return torch.stack([_inside(m, xs, ys, height, width, 0.0).double().mean() for m in H.double()])


def _rectangle(m: torch.Tensor, h: int, w: int, margin: float) -> tuple[int, int, int, int] | None:
    """The largest axis-aligned rectangle of img1 that m maps ``margin`` px inside img2, or None.

    (x0, y0, x1, y1), inclusive, on the 4 px grid; None when it is under 16 x 16 px.

    The region is convex (a projective image of a rectangle, within w > 0, cut by img1's frame), so
    the rectangle between two grid rows spans the intersection of those two rows' intervals.
    """
    xs, ys = _grid_points(h, w, m.device)
    inside = _inside(m, xs, ys, h, w, margin)
    rows = inside.any(1)
    if int(rows.sum()) < 2:
        return None
    col = torch.arange(len(xs), device=m.device)
    lo = torch.where(inside, col, len(xs)).amin(1)
    hi = torch.where(inside, col, -1).amax(1)
    left, right = torch.maximum(lo[:, None], lo[None]), torch.minimum(hi[:, None], hi[None])
    width_px = (xs[right.clamp(0, len(xs) - 1)] - xs[left.clamp(0, len(xs) - 1)]).where(right > left, -1.0)
    height_px = ys[None] - ys[:, None]  # [top, bottom]
    ok = rows[:, None] & rows[None] & (height_px >= 15) & (width_px >= 15)
    area = torch.where(ok, (width_px + 1) * (height_px + 1), -1.0)
    k = int(area.flatten().argmax())
    if float(area.flatten()[k]) < 0:
        return None
    top, bottom = divmod(k, len(ys))
    x0, x1 = int(xs[left[top, bottom]]), int(xs[right[top, bottom]])
    return x0, int(ys[top]), x1, int(ys[bottom])


def _shift(x: float, y: float, ref: torch.Tensor) -> torch.Tensor:
    return torch.tensor([[1.0, 0.0, x], [0.0, 1.0, y], [0.0, 0.0, 1.0]], dtype=ref.dtype, device=ref.device)


def _refine(g1: torch.Tensor, g2: torch.Tensor, hf: torch.Tensor, cfg: RegistrationConfig):
    """One pair (1, 1, h, w) grey float, feature H (3, 3) -> (H, RegistrationInfo of the crop) or None."""
    h0, w0 = g1.shape[-2:]
    box = _rectangle(hf, h0, w0, MARGIN)
    if box is None:
        return None
    x0, y0, x1, y1 = box
    t = _shift(x0, y0, hf)
    crop1 = g1[..., y0 : y1 + 1, x0 : x1 + 1].contiguous()
    crop2, _ = warp_to_reference(g2, (hf @ t)[None], (y1 - y0 + 1, x1 - x0 + 1), backend="grid")
    eye = torch.eye(3, dtype=torch.float64, device=g1.device)[None]
    hr, info = estimate_homography(crop1, crop2, init=eye, config=cfg)
    m = hf @ t @ hr[0] @ torch.linalg.inv(t)
    return m / m[2:, 2:], info


@torch.no_grad()
def estimate_homography_robust(
    img1: torch.Tensor, img2: torch.Tensor, config: RegistrationConfig | None = None, validate: bool = True, *,
    memo: SiftMemo | None = None,
) -> tuple[torch.Tensor, RegistrationInfo]:
    """:func:`~lensdist_torch.registration.direct.estimate_homography`, with a feature fallback.

    The batch is registered as usual; each pair it does not register (``converged`` False) gets a
    feature homography (:func:`feature_homography`) and a direct refinement from it (module
    docstring; docs/method.md, section 10). A pair that still fails keeps the first run's answer
    with ``converged=False``: could not register. :data:`FEATURE_FALLBACK` False returns the
    first run unchanged.

    Args:
        img1: (B, C, H, W) float in [0, 1] or uint8, C in {1, 3}, H and W >= 16.
        img2: the same shape and dtype as img1.
        config: :class:`~lensdist_torch.config.RegistrationConfig`; defaults when None.
        validate: check the images' values (one host sync); False for images already checked.
        memo: a :class:`SiftMemo` for the feature fallback (each distinct image described once).

    Returns:
        H: (B, 3, 3) float64 with H[:, 2, 2] = 1, img1 pixel coordinates -> img2's.
        info: :class:`~lensdist_torch.registration.direct.RegistrationInfo` of (B,) tensors.

    Example:
        >>> import math
        >>> from kornia.geometry import warp_perspective
        >>> from lensdist_torch.core.images import load_scene
        >>> from lensdist_torch.geometry.homography import corner_error
        >>> img1 = load_scene("gravel")[..., 96:416, 44:468]  # 320 x 424
        >>> c, s = math.cos(math.radians(40)), math.sin(math.radians(40))
        >>> H_true = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> centre = torch.tensor([[1.0, 0, 211.5], [0, 1, 159.5], [0, 0, 1]], dtype=torch.float64)
        >>> H_true = centre @ H_true @ torch.linalg.inv(centre)  # 40 degrees about the centre
        >>> img2 = warp_perspective(img1, H_true[None].float(), (320, 424), align_corners=True)
        >>> H, info = estimate_homography_robust(img1, img2)
        >>> bool(info.converged), float(corner_error(H, H_true[None], 320, 424)) < 0.5
        (True, True)
    """
    cfg = _config(config)
    h, info = estimate_homography(img1, img2, config=cfg, validate=validate)  # checks the images
    failed = (~info.converged).nonzero()[:, 0].tolist()
    if not FEATURE_FALLBACK or not failed:
        return h, info
    h, fields = h.clone(), [x.clone() for x in info]
    h0, w0 = img1.shape[-2:]
    idx = torch.tensor(failed, device=img1.device)
    hf, ok, _ = feature_homography(img1[idx], img2[idx], cfg, validate=False, memo=memo)  # checked above
    for j, i in enumerate(failed):
        if not bool(ok[j]):
            continue
        g1, g2 = (to_grey(x[i : i + 1]).float() for x in (img1, img2))
        res = _refine(g1, g2, hf[j], cfg)
        if res is None:
            continue
        m, sub = res
        ov = _overlap(m[None], h0, w0)[0]
        if not (bool(sub.converged[0]) and float(ov) >= MIN_OVERLAP and bool(_in_front(m[None], h0, w0)[0])):
            fields[2][i] += sub.iterations[0]
            continue
        h[i] = m
        for k, v in enumerate((True, sub.residual[0], fields[2][i] + sub.iterations[0], ov, sub.textured[0])):
            fields[k][i] = v
    return h, RegistrationInfo(*fields)
