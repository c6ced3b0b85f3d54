"""The paper's pair protocol (paper 4.1, docs/method.md, section 7): draw, render, register, measure.

Pair i of a set is a pure function of (protocol seed, set name, i): every random number of a
pair comes from its own ``torch.Generator``, drawn in a fixed order, so a pair is the same
whatever the batch size, the number of workers or the shard it falls in. ``protocol.realistic``
(off by default) adds a photograph's effects to both views (``data.realism``).

Geometry. A view maps its ideal pixel coordinates q into the scene by the placement
``P(q) = c + z (q - p0)`` (zoom z, scene point c under the view centre). I1 samples the scene
at ``P(q)`` and I2 at ``P(M q)``, q being the ideal point of each distorted pixel (eq. 4).
Distortion, motion and placement are composed into one sampling grid per image. The zoom is
fixed per scene (the largest <= 1 that keeps the worst-case footprint inside the scene),
so that texture scale never correlates with the distortion level; the position is random.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.realism import Realism, degrade, draw_realism, height_field
from lensdist_torch.data.relief import HeightField, homography_view_points
from lensdist_torch.geometry.distortion import METRICS, REJECT, delta_metric, delta_top, distortion_center
from lensdist_torch.geometry.distortion import distortion_class, distortion_grid
from lensdist_torch.geometry.frame import pixel_grid
from lensdist_torch.geometry.homography import apply_homography
from lensdist_torch.registration.direct import estimate_homography, perturb_homography, warp_to_reference
from lensdist_torch.metric.quality import registration_error_counts

__all__ = [
    "SETS", "PairParams", "PairBatch", "pair_seed", "set_size", "is_distorted", "draw_pairs", "motion_matrix",
    "footprint", "scene_zoom", "render_pairs", "make_pairs", "render_sequence_pairs", "sequence_footprint",
]

SETS = ("train", "test")
_N_DRAWS = 11  # scene, k2, k4, ty, tx, rotation, scale, h31, h32, position x, position y
#: Half-width of a pair's perspective terms h31, h32 (1 / px, about the image centre): each uniform in [-this, this].
PERSPECTIVE = 2e-5
#: The class-R perturbation: each free parameter of the estimated homography times (1 + e), e ~ U[-this, this].
PERTURBATION = 0.01
TY_RANGE = (0.0, 40.0)  # px: a pair's translation along y, uniform in [low, high]
TX_RANGE = (-4.0, 4.0)  # px: its translation along x, uniform in [low, high]
ROTATION_DEG = 1.0  # degrees: its rotation, uniform in [-this, this]
SCALE_RANGE = (0.98, 1.02)  # its scale, uniform in [low, high]


@dataclass
class PairParams:
    """Everything drawn for a batch of pairs (all float64 unless said otherwise).

    index, seed, scene: (B,) int64. k2, k4: (B,). motion: (B, 6) = (t_y, t_x, rotation in
    degrees, scale, h31, h32). M: (B, 3, 3), I2's ideal coordinates -> I1's. position: (B, 2)
    uniform draws in [0, 1) placing the view in its scene. perturbed: (B,) bool, class-R pairs
    whose estimated homography is perturbed. generators: one per pair, for later draws.
    realism: what the realistic protocol drew (``data.realism.Realism``), None when it is off.

    Example:
        >>> from lensdist_torch.config import LensdistConfig
        >>> p = draw_pairs(LensdistConfig(), "test", [0, 499], 2)
        >>> tuple(p.M.shape), p.perturbed.tolist(), p.realism is None  # pair 499 is class R
        ((2, 3, 3), [False, True], True)
    """

    index: torch.Tensor
    seed: torch.Tensor
    scene: torch.Tensor
    k2: torch.Tensor
    k4: torch.Tensor
    motion: torch.Tensor
    M: torch.Tensor
    position: torch.Tensor
    perturbed: torch.Tensor
    generators: list
    realism: Realism | None = None


@dataclass
class PairBatch:
    """Generated pairs: their parameters, ground truth, registration and quality counts.

    Example:
        >>> from lensdist_torch import ImageConfig, LensdistConfig, load_scene
        >>> cfg = LensdistConfig(image=ImageConfig(64, 96))
        >>> batch = make_pairs([load_scene("gravel")], config=cfg, set_name="train", indices=[0])
        >>> tuple(batch.counts.shape), batch.img1 is None, sorted(batch.delta)
        ((1, 1, 8, 12), True, ['delta_avg', 'delta_max'])
    """

    params: PairParams
    delta: dict  # metric name -> (B,) float64
    classes: dict  # metric name -> (B,) int64 class index (REJECT for undistorted)
    H: torch.Tensor  # (B, 3, 3) float64, the homography used for the warp (perturbed for R)
    converged: torch.Tensor  # (B,) bool
    residual: torch.Tensor  # (B,) float32
    counts: torch.Tensor  # (B, 1, H/b, W/b) uint8 registration-error pixels per block
    img1: torch.Tensor | None = None
    img2: torch.Tensor | None = None


def pair_seed(seed: int, set_name: str, index: int) -> int:
    """The seed of pair ``index`` of ``set_name``: a hash, so sets and seeds never overlap."""
    if set_name not in SETS:
        raise ValueError(f"set_name must be one of {SETS}, got {set_name!r}")
    digest = hashlib.blake2b(f"lensdist:{seed}:{set_name}:{index}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & ((1 << 63) - 1)


def set_size(config: LensdistConfig, set_name: str) -> int:
    """The number of pairs of ``set_name`` under ``config``."""
    p = config.protocol
    if set_name == "train":
        return p.n_train
    if set_name == "test":
        return p.n_test_distorted + p.n_test_undistorted
    raise ValueError(f"set_name must be one of {SETS}, got {set_name!r}")


def is_distorted(config: LensdistConfig, set_name: str, index: int) -> bool:
    """Training pairs are all distorted; test pairs after the first n_test_distorted are class R."""
    return set_name == "train" or index < config.protocol.n_test_distorted


def draw_pairs(config: LensdistConfig, set_name: str, indices, n_scenes: int) -> PairParams:
    """Draw the parameters of pairs ``indices`` of a set (docs/method.md, section 7), one generator per pair.

    A pair is a pure function of (protocol seed, set, index): the same pair alone or in any batch.

    Example:
        >>> from lensdist_torch import LensdistConfig
        >>> a, b = draw_pairs(LensdistConfig(), "train", [3], 2), draw_pairs(LensdistConfig(), "train", [2, 3], 2)
        >>> bool(torch.equal(a.k2, b.k2[1:])), bool(a.k2[0] > 0)
        (True, True)
    """
    p, dcfg = config.protocol, config.distortion
    rows, seeds, gens, distorted = [], [], [], []
    n = set_size(config, set_name)
    for i in indices:
        i = int(i)
        if not 0 <= i < n:
            raise ValueError(f"pair index {i} is outside the {set_name} set of {n} pairs")
        s = pair_seed(p.seed, set_name, i)
        g = torch.Generator().manual_seed(s)
        rows.append(torch.rand(_N_DRAWS, generator=g, dtype=torch.float64))
        seeds.append(s)
        gens.append(g)
        distorted.append(is_distorted(config, set_name, i))
    u = torch.stack(rows)
    dist = torch.tensor(distorted)

    def between(col, lo, hi):
        return lo + (hi - lo) * u[:, col]

    scene = torch.clamp((u[:, 0] * n_scenes).long(), max=n_scenes - 1)
    # ]0, max]: 1 - u lies in ]0, 1]
    k2 = torch.where(dist, (1.0 - u[:, 1]) * dcfg.k2_max, torch.zeros(()).double())
    k4 = torch.where(dist, (1.0 - u[:, 2]) * dcfg.k4_max, torch.zeros(()).double())
    motion = torch.stack(
        [
            between(3, *TY_RANGE),
            between(4, *TX_RANGE),
            between(5, -ROTATION_DEG, ROTATION_DEG),
            between(6, *SCALE_RANGE),
            between(7, -PERSPECTIVE, PERSPECTIVE),
            between(8, -PERSPECTIVE, PERSPECTIVE),
        ],
        dim=1,
    )
    M = motion_matrix(motion, config.image.height, config.image.width)
    return PairParams(
        index=torch.tensor([int(i) for i in indices], dtype=torch.int64),
        seed=torch.tensor(seeds, dtype=torch.int64),
        scene=scene,
        k2=k2,
        k4=k4,
        motion=motion,
        M=M,
        position=u[:, 9:11].clone(),
        perturbed=~dist,
        generators=gens,
        realism=draw_realism(config, seeds) if p.realistic else None,
    )


def _translation(x: float, y: float, batch: int) -> torch.Tensor:
    t = torch.eye(3, dtype=torch.float64).repeat(batch, 1, 1)
    t[:, 0, 2], t[:, 1, 2] = x, y
    return t


def motion_matrix(motion: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """M = T(p0) A T(-p0) from (B, 6) motion parameters (t_y, t_x, degrees, s, h31, h32)."""
    ty, tx, deg, s, h31, h32 = motion.double().unbind(1)
    t = torch.deg2rad(deg)
    a = torch.zeros(motion.shape[0], 3, 3, dtype=torch.float64)
    a[:, 0, 0], a[:, 0, 1], a[:, 0, 2] = s * torch.cos(t), -s * torch.sin(t), tx
    a[:, 1, 0], a[:, 1, 1], a[:, 1, 2] = s * torch.sin(t), s * torch.cos(t), ty
    a[:, 2, 0], a[:, 2, 1], a[:, 2, 2] = h31, h32, 1.0
    x0, y0 = distortion_center(height, width)
    b = motion.shape[0]
    return _translation(x0, y0, b) @ a @ _translation(-x0, -y0, b)


@functools.lru_cache(maxsize=16)
def _ideal_box(config: LensdistConfig) -> tuple[float, float, float, float]:
    """Box (x_lo, x_hi, y_lo, y_hi), in pixels, of the ideal points at the largest coefficients."""
    d = config.distortion
    ideal = distortion_grid([d.k2_max], [d.k4_max], config.image.height, config.image.width, dtype=torch.float64)[0]
    lo, hi = ideal.reshape(-1, 2).amin(0), ideal.reshape(-1, 2).amax(0)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


@functools.lru_cache(maxsize=4)
def _centred_radii(h: int, w: int) -> tuple[torch.Tensor, ...]:
    """Per pixel centre, flattened, float32: dx, dy from p0, r^2 and r^4 (shared by every pair)."""
    x0, y0 = distortion_center(h, w)
    d = pixel_grid(h, w, torch.float64).reshape(-1, 2) - torch.tensor([x0, y0], dtype=torch.float64)
    r2 = (d * d).sum(-1)
    return d[:, 0].float(), d[:, 1].float(), r2.float(), (r2 * r2).float()


@functools.lru_cache(maxsize=16)
def footprint(config: LensdistConfig) -> tuple[float, float, float, float]:
    """Worst-case box (x_lo, x_hi, y_lo, y_hi), relative to p0, of every sample of both views.

    The ideal box at the largest coefficients, moved by every extreme of the motion ranges
    (the border of a box maps to a quadrilateral whose extremes lie at its corners), plus a
    2 px margin for bilinear support and rounding, plus, in the realistic protocol, the
    parallax: at most relief / (1 - relief) times a sample's distance from camera 2's nadir,
    bounded by 1.1 times the farthest extreme from p0 (the nadirs lie inside the moved frame).
    """
    h, w = config.image.height, config.image.width
    x0, y0 = distortion_center(h, w)
    xl, xh, yl, yh = _ideal_box(config)
    corners = torch.tensor([[xl, yl], [xh, yl], [xh, yh], [xl, yh]], dtype=torch.float64)
    p = config.protocol
    extremes = list(
        itertools.product(
            TY_RANGE, TX_RANGE, (-ROTATION_DEG, ROTATION_DEG), SCALE_RANGE,
            (-PERSPECTIVE, PERSPECTIVE), (-PERSPECTIVE, PERSPECTIVE),
        )
    )
    M = motion_matrix(torch.tensor(extremes, dtype=torch.float64), h, w)
    moved = apply_homography(M, corners).reshape(-1, 2)
    allp = torch.cat([corners, moved])
    reach = float((allp - torch.tensor([x0, y0], dtype=torch.float64)).norm(dim=1).max())
    margin = 2.0 + (1.1 * reach * p.relief / (1 - p.relief) if p.realistic else 0.0)
    return (
        float(allp[:, 0].min()) - x0 - margin,
        float(allp[:, 0].max()) - x0 + margin,
        float(allp[:, 1].min()) - y0 - margin,
        float(allp[:, 1].max()) - y0 + margin,
    )


def scene_zoom(scene_hw: tuple[int, int], box: tuple[float, float, float, float]) -> float:
    """The largest zoom <= 1 (scene px per view px) that fits the footprint inside the scene."""
    hs, ws = scene_hw
    return min(1.0, (ws - 1) / (box[1] - box[0]), (hs - 1) / (box[3] - box[2]))


def render_pairs(scenes: list[torch.Tensor], params: PairParams, config: LensdistConfig):
    """Render (I1, I2), each (B, 1, H, W) float32, with one grid_sample per image.

    Per pair, placement, motion and grid_sample's normalisation fold into one 3 x 3 matrix
    per image (float64), applied to the ideal points of the distorted pixel grid (eq. 4,
    centred), so each image costs a few elementwise passes and one grid_sample. With
    ``params.realism`` (the realistic protocol) I2's samples follow the pair's relief, if any
    (``data.relief.second_view_points``), and both views are degraded (``data.realism.degrade``).

    Example:
        >>> from lensdist_torch import ImageConfig, LensdistConfig, load_scene
        >>> cfg = LensdistConfig(image=ImageConfig(64, 96))
        >>> img1, img2 = render_pairs([load_scene("gravel")], draw_pairs(cfg, "train", [0, 1], 1), cfg)
        >>> tuple(img1.shape), bool(0 <= img2.min() and img2.max() <= 1)
        ((2, 1, 64, 96), True)
    """
    h, w = config.image.height, config.image.width
    x0, y0 = distortion_center(h, w)
    box = footprint(config)
    b = params.k2.shape[0]
    dx, dy, r2, r4 = _centred_radii(h, w)
    centre = _translation(x0, y0, b)
    a = torch.linalg.inv(centre) @ params.M @ centre  # the motion in centred coordinates
    img1 = torch.empty(b, 1, h, w)
    img2 = torch.empty(b, 1, h, w)
    for s in params.scene.unique().tolist():
        sel = (params.scene == s).nonzero().flatten()
        n = len(sel)
        hs, ws = scenes[s].shape[-2:]
        z = scene_zoom((hs, ws), box)
        # c ranges so that c + z * box stays inside [0, size - 1]
        cx = -z * box[0] + params.position[sel, 0] * ((ws - 1) - z * (box[1] - box[0]))
        cy = -z * box[2] + params.position[sel, 1] * ((hs - 1) - z * (box[3] - box[2]))
        # q -> c + z q, then scene pixels -> grid_sample's [-1, 1] (align_corners=True)
        place = torch.zeros(n, 3, 3, dtype=torch.float64)
        sx, sy = 2.0 / (ws - 1), 2.0 / (hs - 1)
        place[:, 0, 0], place[:, 0, 2] = sx * z, sx * cx - 1.0
        place[:, 1, 1], place[:, 1, 2] = sy * z, sy * cy - 1.0
        place[:, 2, 2] = 1.0
        m = place @ a[sel]
        g1 = torch.empty(n, 2, h, w)
        g2 = torch.empty(n, 2, h, w)
        for j in range(n):  # per-pair scalars: plain vectorised kernels, no broadcasting
            i = int(sel[j])
            field = None if params.realism is None else height_field(params.realism, i, h, w)
            _pair_grid(dx, dy, r2, r4, float(params.k2[i]), float(params.k4[i]), place[j], m[j], g1[j], g2[j],
                       None if field is None else (a[i], field))
        src = scenes[s].float().expand(n, -1, -1, -1)
        # (n, 2, H, W) viewed as (n, H, W, 2): grid_sample takes the strided grid as it is
        r1 = F.grid_sample(src, g1.permute(0, 2, 3, 1), mode="bilinear", padding_mode="zeros", align_corners=True)
        r2_ = F.grid_sample(src, g2.permute(0, 2, 3, 1), mode="bilinear", padding_mode="zeros", align_corners=True)
        if n == b:
            img1, img2 = r1, r2_
        else:
            img1[sel], img2[sel] = r1, r2_
    return (img1, img2) if params.realism is None else degrade(img1, img2, params.realism)


def _pair_grid(dx, dy, r2, r4, k2: float, k4: float, place: torch.Tensor, m: torch.Tensor, out1, out2,
               relief: tuple[torch.Tensor, HeightField] | None = None) -> None:
    """One pair's two sampling grids, written into out1, out2 (2, H, W) in grid_sample units.

    Ideal points relative to p0 (eq. 4): (x, y) = f (dx, dy), f = 1 + k2 r^2 + k4 r^4; then
    I1 samples at ``place`` (x, y, 1) and I2 at ``place @ A`` (x, y, 1), A the centred motion.
    f is :func:`~lensdist_torch.geometry.distortion.radial_factor` as one fused kernel on cached
    float32 r^2, r^4 (fast; radial_factor itself would change the last bit of ~1/4 of the
    factors, and rendered pairs, hence shards, must stay bit-identical). ``relief`` (A, the
    pair's height field): I2 samples where camera 1 sees what camera 2 sees (float64;
    ``data.relief.homography_view_points``).
    """
    f = torch.add(r2 * k2, r4, alpha=k4).add_(1.0)
    x, y = dx * f, dy * f
    p, q = place.tolist(), m.tolist()
    torch.add(x * p[0][0], p[0][2], out=out1[0].view(-1))
    torch.add(y * p[1][1], p[1][2], out=out1[1].view(-1))
    if relief is not None:
        xs, ys = homography_view_points(relief[0], x.double(), y.double(), relief[1])
        out2[0].view(-1).copy_(xs * p[0][0] + p[0][2])
        out2[1].view(-1).copy_(ys * p[1][1] + p[1][2])
        return
    den = torch.add(x * q[2][0], y, alpha=q[2][1]).add_(q[2][2])
    torch.div(torch.add(x * q[0][0], y, alpha=q[0][1]).add_(q[0][2]), den, out=out2[0].view(-1))
    torch.div(torch.add(x * q[1][0], y, alpha=q[1][1]).add_(q[1][2]), den, out=out2[1].view(-1))


def sequence_footprint(config: LensdistConfig) -> tuple[float, float, float, float]:
    """Box of the ideal points at the largest coefficients, relative to p0, + 2 px (no motion)."""
    x0, y0 = distortion_center(config.image.height, config.image.width)
    xl, xh, yl, yh = _ideal_box(config)
    return (xl - x0 - 2, xh - x0 + 2, yl - y0 - 2, yh - y0 + 2)


def _sequence_params(params: PairParams, n_frames: int) -> PairParams:
    """Pair i of a sequence is frames (i mod (n - 1), i mod (n - 1) + 1): motion unknown (NaN), M = I."""
    if n_frames < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {n_frames}")
    b = params.index.shape[0]
    params.scene = params.index % (n_frames - 1)
    params.motion = torch.full((b, 6), float("nan"), dtype=torch.float64)
    params.M = torch.eye(3, dtype=torch.float64).repeat(b, 1, 1)
    return params


def render_sequence_pairs(frames: list[torch.Tensor], params: PairParams, config: LensdistConfig):
    """Distort consecutive frames (I1 = frame s, I2 = frame s + 1) with the pair's (k2, k4).

    Each frame is viewed about its centre at the zoom that keeps the distorted footprint inside
    it (never padded); one grid_sample per image.
    """
    h, w = config.image.height, config.image.width
    box = sequence_footprint(config)
    dx, dy, r2, r4 = _centred_radii(h, w)
    b = params.k2.shape[0]
    hs, ws = frames[0].shape[-2:]
    z = scene_zoom((hs, ws), box)
    place = torch.tensor([[2.0 / (ws - 1) * z, 0.0, 0.0], [0.0, 2.0 / (hs - 1) * z, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    grid = torch.empty(b, 2, h, w)
    unused = torch.empty(b, 2, h, w)
    for j in range(b):
        _pair_grid(dx, dy, r2, r4, float(params.k2[j]), float(params.k4[j]), place, place, grid[j], unused[j])
    first = torch.cat([frames[int(s)] for s in params.scene]).float()
    second = torch.cat([frames[int(s) + 1] for s in params.scene]).float()
    g = grid.permute(0, 2, 3, 1)
    img1 = F.grid_sample(first, g, mode="bilinear", padding_mode="zeros", align_corners=True)
    img2 = F.grid_sample(second, g, mode="bilinear", padding_mode="zeros", align_corners=True)
    return img1, img2


def make_pairs(
    scenes: list[torch.Tensor],
    *,
    config: LensdistConfig,
    set_name: str,
    indices,
    keep_images: bool = False,
    sequence: bool = False,
) -> PairBatch:
    """Draw, render, register (estimated homography only) and measure a batch of pairs.

    With ``sequence``, ``scenes`` are consecutive frames of a real, undistorted sequence and
    pair i is frames (i mod (n-1), i mod (n-1) + 1), distorted, instead of synthetic motion.

    Example:
        >>> from lensdist_torch import ImageConfig, LensdistConfig, load_scene
        >>> cfg = LensdistConfig(image=ImageConfig(64, 96))
        >>> batch = make_pairs([load_scene("gravel")], config=cfg, set_name="test", indices=[0], keep_images=True)
        >>> tuple(batch.img2.shape), batch.classes["delta_avg"].tolist() != [-1]
        ((1, 1, 64, 96), True)
    """
    if sequence and config.protocol.realistic:
        raise ValueError("protocol.realistic is for synthetic pairs; a real sequence's frames are photographs already")
    params = draw_pairs(config, set_name, indices, len(scenes))
    if sequence:
        params = _sequence_params(params, len(scenes))
        img1, img2 = render_sequence_pairs(scenes, params, config)
    else:
        img1, img2 = render_pairs(scenes, params, config)
    H, info = estimate_homography(img1, img2, config=config.registration)
    H = H.double()
    if bool(params.perturbed.any()):
        sel = params.perturbed.nonzero().flatten()
        gens = [params.generators[i] for i in sel.tolist()]
        size = (config.image.height, config.image.width)
        H[sel] = perturb_homography(H[sel], gens, PERTURBATION, size=size).double()
    warped, valid = warp_to_reference(img2, H.float())
    counts = registration_error_counts(img1, warped, valid, config=config.quality, validate=False)
    h, w = config.image.height, config.image.width
    delta, classes = {}, {}
    for metric in METRICS:
        delta[metric] = delta_metric(params.k2, params.k4, h, w, metric=metric)
        classes[metric] = distortion_class(delta[metric], delta_top(metric, config))
        classes[metric] = torch.where(params.perturbed, torch.full_like(classes[metric], REJECT), classes[metric])
    return PairBatch(
        params=params,
        delta=delta,
        classes=classes,
        H=H,
        converged=info.converged.bool(),
        residual=info.residual.float(),
        counts=counts,
        img1=img1 if keep_images else None,
        img2=img2 if keep_images else None,
    )
