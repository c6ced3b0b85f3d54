"""The realistic pair protocol (docs/method.md, section 7, "the realistic protocol").

The paper's pairs are clean renders of a planar scene. With ``protocol.realistic`` a pair also
gets what a photograph pair has: per view a photometric change (gain, offset, gamma, a smooth
illumination ramp / vignetting), Gaussian sensor noise, 8-bit quantisation and JPEG compression;
per pair, with ``relief`` > 0, a scene that is not a plane (a smooth random height field of up to
``relief`` of camera 1's height: I2's parallax follows from the pair's own motion,
:func:`~lensdist_torch.data.relief.second_view_points`) and, in ``occluder_rate`` of the pairs, a patch present in one view only or at different places
in both (an occluder or a moving object).

Draws. Every number of pair i comes from the pair's realism generator, seeded by a hash of the
pair's own seed (:func:`realism_seed`), so the protocol's draws (placement, distortion, motion,
the class-R perturbation) are exactly those of the clean protocol, and a pair is still a pure
function of (seed, set, i). All ``N_UNIFORMS`` uniforms are drawn whether an effect is on or not,
then two int64 seeds (noise, occluder texture): switching one effect off shifts no other draw.

JPEG. A grey JPEG holds one component, luminance, so the codec is: round to 8 bits, subtract
128, 8 x 8 DCT-II, divide by the standard luminance table scaled by the quality (libjpeg's rule,
steps clamped to [1, 255]), round, multiply back, inverse DCT, add 128, round and clamp to
[0, 255]. kornia 0.9's ``jpeg_codec_differentiable`` was not used: it rounds with a cubic
(differentiable) approximation and codes RGB with chroma; on the embedded scene it lies about
1 grey level from libjpeg on average where this codec lies about 0.3 (the tests compare with
OpenCV's libjpeg).
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.relief import HeightField, scaled_field
from lensdist_torch.geometry.distortion import distortion_center
from lensdist_torch.geometry.frame import half_diagonal, pixel_grid

__all__ = [
    "PHOTOMETRIC",
    "N_BUMPS",
    "N_UNIFORMS",
    "Realism",
    "realism_seed",
    "draw_realism",
    "height_field",
    "illumination_field",
    "jpeg_table",
    "jpeg",
    "occluder_patch",
    "degrade",
]

#: The columns of ``Realism.photometric`` (per view): I' = L gain I^gamma + offset, L in
#: [1 - illumination, 1] from a ramp at ``ramp_angle`` degrees (weight ``ramp_weight``) and a
#: radial falloff (weight 1 - ramp_weight); then noise of std ``noise_sigma`` and JPEG.
PHOTOMETRIC = ("gain", "offset", "gamma", "illumination", "ramp_weight", "ramp_angle", "noise_sigma", "jpeg_quality")
N_BUMPS = 4  # Gaussian bumps of a pair's height field
_BUMP_WIDTH = (0.15, 0.4)  # bump sigma, in half-diagonals: low frequency only
_RATIO = (0.5, 2.0)  # occluder width / height, log-uniform
#: An occluding patch's area, a share of the frame, uniform in [low, high].
OCCLUDER_AREA = (0.05, 0.15)
#: The share of pairs with a moving or occluding patch.
OCCLUDER_RATE = 0.2
#: Per view: I' = L gain I^gamma + offset, gain uniform in [low, high].
GAIN_RANGE = (0.7, 1.3)
#: Per view: the offset, uniform in [low, high] (intensities in [0, 1]).
OFFSET_RANGE = (-0.1, 0.1)
#: Per view: gamma, log-uniform in [low, high].
GAMMA_RANGE = (0.8, 1.25)
#: Per view: the largest share a ramp / vignetting darkens, L in [1 - s, 1], s uniform in [0, this].
ILLUMINATION = 0.25
#: Per view: the Gaussian sensor noise's sigma, uniform in [low, high] (intensities in [0, 1]).
NOISE_RANGE = (0.0, 0.02)
#: Per view: the JPEG quality, an int uniform in [low, high].
JPEG_QUALITY = (60, 95)
_CONTRAST = (0.2, 0.5)  # texture amplitude of a textured occluder
_TEXTURE_PX = 6  # feature size of a textured occluder, px
_OCC = 16 + 1 + 4 * N_BUMPS  # first occluder uniform
N_UNIFORMS = _OCC + 11

#: The standard JPEG luminance quantisation table (ITU-T T.81, Annex K, table K.1).
_LUMA = (
    (16, 11, 10, 16, 24, 40, 51, 61),
    (12, 12, 14, 19, 26, 58, 60, 55),
    (14, 13, 16, 24, 40, 57, 69, 56),
    (14, 17, 22, 29, 51, 87, 80, 62),
    (18, 22, 37, 56, 68, 109, 103, 77),
    (24, 35, 55, 64, 81, 104, 113, 92),
    (49, 64, 78, 87, 103, 121, 120, 101),
    (72, 92, 95, 98, 112, 100, 103, 99),
)


@dataclass
class Realism:
    """What the realistic protocol drew for a batch of pairs.

    photometric: (B, 2, 8) float64, per view (I1, I2) the columns :data:`PHOTOMETRIC`.
    relief: (B, 1 + 4 N_BUMPS) float64: the largest |height| over I1's view as a fraction of
    camera 1's height (0: a plane), then per bump its centre (x, y) as a share of the half
    width / height from p0, its sigma in half-diagonals and its weight in [-1, 1]. occluded: (B,) bool. occluder: (B, 2, 4) int64, per view the
    patch (x0, y0, width, height) in pixels, width = height = 0 where the view has none.
    look: (B, 3) float64: textured (1) or flat (0), grey level, texture contrast.
    seeds: (B, 2) int64, the noise and the texture generators' seeds.
    """

    photometric: torch.Tensor
    relief: torch.Tensor
    occluded: torch.Tensor
    occluder: torch.Tensor
    look: torch.Tensor
    seeds: torch.Tensor


def realism_seed(pair_seed: int) -> int:
    """The seed of a pair's realism generator, a hash of the pair's own seed."""
    digest = hashlib.blake2b(f"lensdist:realism:{int(pair_seed)}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") & ((1 << 63) - 1)


def _log_uniform(u: torch.Tensor, lo: float, hi: float) -> torch.Tensor:
    return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)


def draw_realism(config: LensdistConfig, seeds: Sequence[int]) -> Realism:
    """Draw the realistic effects of the pairs whose own seeds are ``seeds`` (docs/method.md, section 7).

    Per pair, from its realism generator: ``N_UNIFORMS`` uniforms in one call (per view the 8
    columns of :data:`PHOTOMETRIC`; the relief fraction; per bump x, y, width, weight; the
    occluder's presence, views (I1 only, both, I2 only: a third each), area, aspect, position in
    I1, position in I2, flat or textured, level, contrast), then the noise and texture seeds.

    Example:
        >>> from lensdist_torch.config import LensdistConfig, ProtocolConfig
        >>> real = draw_realism(LensdistConfig(protocol=ProtocolConfig(realistic=True)), [11, 12])
        >>> tuple(real.photometric.shape), tuple(real.occluder.shape), real.relief[:, 0].tolist()  # a plane
        ((2, 2, 8), (2, 2, 4), [0.0, 0.0])
    """
    p, h, w = config.protocol, config.image.height, config.image.width
    rows, sub = [], []
    for s in seeds:
        g = torch.Generator().manual_seed(realism_seed(s))
        rows.append(torch.rand(N_UNIFORMS, generator=g, dtype=torch.float64))
        sub.append(torch.randint(0, 1 << 62, (2,), generator=g))
    u = torch.stack(rows).reshape(len(rows), N_UNIFORMS)
    b = u.shape[0]

    def lin(x, rng):
        return rng[0] + (rng[1] - rng[0]) * x

    v = u[:, :16].reshape(b, 2, 8)  # per view, the columns of PHOTOMETRIC
    q_lo, q_hi = JPEG_QUALITY
    photometric = torch.stack(
        [
            lin(v[..., 0], GAIN_RANGE),
            lin(v[..., 1], OFFSET_RANGE),
            _log_uniform(v[..., 2], *GAMMA_RANGE),
            ILLUMINATION * v[..., 3],
            v[..., 4],
            360.0 * v[..., 5],
            lin(v[..., 6], NOISE_RANGE),
            torch.clamp(q_lo + torch.floor(v[..., 7] * (q_hi - q_lo + 1)), max=q_hi),
        ],
        dim=-1,
    )
    bumps = u[:, 17:_OCC].reshape(b, N_BUMPS, 4)
    bumps = torch.stack(
        [2 * bumps[..., 0] - 1, 2 * bumps[..., 1] - 1, lin(bumps[..., 2], _BUMP_WIDTH), 2 * bumps[..., 3] - 1], -1
    )
    relief = torch.cat([p.relief * u[:, 16:17], bumps.flatten(1)], 1)

    o = u[:, _OCC:]
    occluded = o[:, 0] < OCCLUDER_RATE
    area = lin(o[:, 2], OCCLUDER_AREA) * h * w
    aspect = _log_uniform(o[:, 3], *_RATIO)
    pw = torch.clamp(torch.round(torch.sqrt(area * aspect)), 1, w)
    ph = torch.clamp(torch.round(area / pw), 1, h)
    views = torch.stack([o[:, 1] < 2 / 3, o[:, 1] >= 1 / 3], 1) & occluded[:, None]  # I1 only, I2 only, both
    x0 = torch.minimum(torch.floor(o[:, 4:8:2] * (w - pw[:, None] + 1)), w - pw[:, None])
    y0 = torch.minimum(torch.floor(o[:, 5:8:2] * (h - ph[:, None] + 1)), h - ph[:, None])
    occluder = torch.stack([x0, y0, pw[:, None].expand(b, 2), ph[:, None].expand(b, 2)], -1).long()
    occluder = torch.where(views[..., None], occluder, torch.zeros_like(occluder))
    look = torch.stack([(o[:, 8] < 0.5).double(), o[:, 9], lin(o[:, 10], _CONTRAST)], 1)
    return Realism(
        photometric=photometric,
        relief=relief,
        occluded=occluded,
        occluder=occluder,
        look=look,
        seeds=torch.stack(sub).reshape(b, 2),
    )


def height_field(real: Realism, i: int, height: int, width: int) -> HeightField | None:
    """Pair ``i``'s height field in I1's ideal frame (pixels from p0), or None for a plane.

    The N_BUMPS Gaussian bumps drawn for the pair, scaled so that the largest |rho| over I1's
    view is the pair's relief fraction (:func:`~lensdist_torch.data.relief.scaled_field`).

    Example:
        >>> from lensdist_torch.config import LensdistConfig, ProtocolConfig
        >>> cfg = LensdistConfig(protocol=ProtocolConfig(realistic=True, relief=0.03))
        >>> real = draw_realism(cfg, [7])
        >>> f = height_field(real, 0, 320, 424)
        >>> len(f.weights), round(float(real.relief[0, 0]), 4) <= 0.03
        (4, True)
    """
    rho = float(real.relief[i, 0])
    if rho <= 0:
        return None
    x0, y0 = distortion_center(height, width)
    bumps = real.relief[i, 1:].reshape(N_BUMPS, 4)
    centres = torch.stack([bumps[:, 0] * (width - 1) / 2, bumps[:, 1] * (height - 1) / 2], 1)
    field = HeightField(
        centres=centres, sigmas=bumps[:, 2] * half_diagonal(height, width), weights=bumps[:, 3])
    return scaled_field(field, (-x0, width - 1 - x0, -y0, height - 1 - y0), rho)


@functools.lru_cache(maxsize=4)
def _frame(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel centres relative to p0, (H*W,) float64 each."""
    x0, y0 = distortion_center(h, w)
    g = pixel_grid(h, w, torch.float64).reshape(-1, 2)
    return g[:, 0] - x0, g[:, 1] - y0


def illumination_field(photometric: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(B, 1, H, W) float32 illumination L in [1 - s, 1] of one view's (B, 8) photometric rows.

    L = 1 - s (w ramp + (1 - w) rho^2), ramp = (1 + cos(a) x + sin(a) y) / 2 and rho^2 = x^2 + y^2,
    (x, y) the pixel relative to p0 in half-diagonals (so ramp and rho^2 lie in [0, 1]).
    """
    dx, dy = _frame(height, width)
    r = half_diagonal(height, width)
    x, y = dx / r, dy / r
    s, wt, a = (photometric[:, i : i + 1] for i in (3, 4, 5))
    a = torch.deg2rad(a)
    ramp = 0.5 * (1 + torch.cos(a) * x + torch.sin(a) * y)
    field = 1 - s * (wt * ramp + (1 - wt) * (x * x + y * y))
    return field.float().reshape(-1, 1, height, width)


@functools.lru_cache(maxsize=1)
def _dct() -> torch.Tensor:
    """The orthonormal 8-point DCT-II matrix, float64 (JPEG's FDCT is C X C^T)."""
    n = torch.arange(8, dtype=torch.float64)
    scale = torch.where(n == 0, math.sqrt(1 / 8), math.sqrt(2 / 8))
    return torch.cos((2 * n[None, :] + 1) * n[:, None] * math.pi / 16) * scale[:, None]


def jpeg_table(quality: int) -> torch.Tensor:
    """(8, 8) float64 luminance quantisation steps at ``quality`` in [1, 100] (libjpeg's scaling)."""
    if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
        raise ValueError(f"quality must be an int in [1, 100], got {quality!r}")
    scale = 5000 / quality if quality < 50 else 200 - 2 * quality
    return torch.clamp(torch.floor((torch.tensor(_LUMA, dtype=torch.float64) * scale + 50) / 100), 1, 255)


def jpeg(img: torch.Tensor, quality: int) -> torch.Tensor:
    """One grey image (1, 1, H, W) in [0, 1] through an 8-bit baseline JPEG at ``quality``.

    Returns float32 multiples of 1/255. Sizes that are not multiples of 8 are padded by
    repeating the last row / column (as libjpeg does) and cropped back.
    """
    h, w = img.shape[-2:]
    x = torch.round(img[0, 0].double().clamp(0, 1) * 255)
    ph, pw = -h % 8, -w % 8
    if ph or pw:
        x = F.pad(x[None, None], (0, pw, 0, ph), mode="replicate")[0, 0]
    hh, ww = x.shape
    blocks = x.reshape(hh // 8, 8, ww // 8, 8).transpose(1, 2) - 128
    c, t = _dct(), jpeg_table(quality)
    coef = torch.round((c @ blocks @ c.T) / t) * t
    out = torch.clamp(torch.round(c.T @ coef @ c + 128), 0, 255)
    out = out.transpose(1, 2).reshape(hh, ww)[:h, :w]
    return (out / 255).float()[None, None]


def occluder_patch(real: Realism, j: int) -> torch.Tensor:
    """Pair j's patch, (ph, pw) float32 in [0, 1]: flat, or a coarse random texture (features ~6 px)."""
    pw, ph = (int(v) for v in real.occluder[j].amax(0)[2:])
    textured, level, contrast = real.look[j].tolist()
    if not textured:
        return torch.full((ph, pw), level)
    g = torch.Generator().manual_seed(int(real.seeds[j, 1]))
    coarse = torch.rand(1, 1, max(2, ph // _TEXTURE_PX), max(2, pw // _TEXTURE_PX), generator=g)
    tex = F.interpolate(coarse, size=(ph, pw), mode="bilinear", align_corners=True)[0, 0]
    return (level + contrast * (2 * tex - 1)).clamp(0, 1)


def degrade(img1: torch.Tensor, img2: torch.Tensor, real: Realism) -> tuple[torch.Tensor, torch.Tensor]:
    """Rendered (B, 1, H, W) views -> their realistic versions (new tensors, float32).

    Per pair and view, in order: the occluding patch, I' = L gain I^gamma + offset clipped to
    [0, 1], Gaussian noise clipped to [0, 1], then 8-bit JPEG. One pair at a time, so a pair's
    bytes do not depend on the batch.
    """
    h, w = img1.shape[-2:]
    out = [img1.clone(), img2.clone()]
    for j in range(img1.shape[0]):
        noise = torch.Generator().manual_seed(int(real.seeds[j, 0]))
        patch = occluder_patch(real, j) if bool(real.occluded[j]) else None
        for v in range(2):
            x = out[v][j : j + 1]
            x0, y0, pw, ph = real.occluder[j, v].tolist()
            if patch is not None and pw > 0:
                x[..., y0 : y0 + ph, x0 : x0 + pw] = patch
            gain, offset, gamma = real.photometric[j, v, :3].tolist()
            light = illumination_field(real.photometric[j, v][None], h, w)
            x = (light * gain * x.clamp(0, 1).pow(gamma) + offset).clamp(0, 1)
            sigma = float(real.photometric[j, v, 6])
            x = (x + sigma * torch.randn(x.shape, generator=noise)).clamp(0, 1)
            out[v][j : j + 1] = jpeg(x, int(real.photometric[j, v, 7]))
    return out[0], out[1]
