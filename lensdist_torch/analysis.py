"""Analyse a user's own image pair: registration, quality map, distortion class and Delta.

``analyze_pair(img1, img2)`` brings both images to the analysis size (centre crop to the
aspect ratio, then area resampling), registers them with an estimated homography, computes the
quality map and asks the eigen-space classifiers (Delta_avg and Delta_max checkpoints) for the
distortion class and size. Offsets are reported in analysis pixels and in the user's pixels.
"""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from .config import LensdistConfig
from .distortion import CLASS_LABELS
from .eigenspace import EigenSpaceClassifier
from .images import as_batch, check_image, load_image, resize_to, to_grey
from .quality import counts_to_map, registration_error_counts
from .registration import estimate_homography, warp_to_reference

__all__ = ["analyze_pair", "default_checkpoint", "MIN_OVERLAP"]

MIN_OVERLAP = 0.5  # below this share of valid pixels the map is too small to judge
_CKPT_DIR = Path(__file__).resolve().parent.parent / "checkpoints"


def default_checkpoint(metric: str = "delta_avg") -> Path:
    """The shipped checkpoint of the default protocol for a metric (10 eigenvectors)."""
    path = _CKPT_DIR / f"eigenspace_{metric}_10ev.pt"
    if not path.is_file():
        raise FileNotFoundError(
            f"shipped checkpoint {path} not found (it lives in the repository's checkpoints/); "
            "pass checkpoint=PATH, e.g. one written by `lensdist reproduce`"
        )
    return path


@functools.lru_cache(maxsize=8)
def _load_model(path: str) -> EigenSpaceClassifier:
    return EigenSpaceClassifier.load(path).eval()


def _as_image(img, name: str) -> torch.Tensor:
    if isinstance(img, (str, Path)):
        return load_image(img, grey=True)
    x = as_batch(img, name)
    check_image(x, name)
    return to_grey(x).float()


def analyze_pair(
    img1,
    img2,
    checkpoint: str | Path | None = None,
    checkpoint_max: str | Path | None = None,
) -> dict:
    """Analyse one overlapping pair of photographs of a roughly planar scene.

    Args:
        img1, img2: file paths, or tensors (H, W), (C, H, W) or (1, C, H, W); colour or grey,
            any size (both the same size).
        checkpoint: eigen-space checkpoint for Delta_avg (default: the shipped one).
        checkpoint_max: checkpoint for Delta_max (default: the shipped one).

    Returns:
        A dict with ``class`` ("1"-"4" or "R"), ``delta_avg`` and ``delta_max`` (analysis px),
        the same in the user's pixels, ``distances`` (per class), ``registration_ok``,
        ``in_domain``, ``overlap``, ``warnings`` and more.
    """
    a, b = _as_image(img1, "img1"), _as_image(img2, "img2")
    if a.shape[-2:] != b.shape[-2:]:
        raise ValueError(f"img1 and img2 must have the same size, got {tuple(a.shape[-2:])} and {tuple(b.shape[-2:])}")
    m_avg = _load_model(str(checkpoint or default_checkpoint("delta_avg")))
    m_max = _load_model(str(checkpoint_max or default_checkpoint("delta_max")))
    cfg: LensdistConfig = m_avg.config
    h, w = cfg.image.height, cfg.image.width
    orig_h, orig_w = a.shape[-2:]
    # user px per analysis px (the centre crop keeps the analysis aspect ratio)
    scale = min(orig_w / w, orig_h / h)
    a, b = resize_to(a, h, w).clamp(0, 1), resize_to(b, h, w).clamp(0, 1)
    H, info = estimate_homography(a, b)
    warped, valid = warp_to_reference(b, H)
    overlap = float(valid.mean())
    counts = registration_error_counts(a, warped, valid, cfg.quality)
    qmap = counts_to_map(counts, cfg.quality)
    with torch.no_grad():
        r_avg = m_avg(qmap.flatten(1))
        r_max = m_max(qmap.flatten(1))
    ok = bool(info.converged[0])
    min_dist = float(r_avg.distances.min())
    in_domain = ok and overlap >= MIN_OVERLAP and min_dist <= 2.0 * float(m_avg.reject_threshold)
    warnings = []
    if not ok:
        warnings.append("registration failed: the pair could not be aligned by a homography; the result is not meaningful")
    if overlap < MIN_OVERLAP:
        warnings.append(f"the images overlap on {100 * overlap:.0f} % only (< {100 * MIN_OVERLAP:.0f} %): too little to judge")
    if ok and min_dist > 2.0 * float(m_avg.reject_threshold):
        warnings.append("the quality map is unlike every training map (out of domain): treat the class with caution")
    d_avg, d_max = float(r_avg.delta[0]), float(r_max.delta[0])
    return {
        "class": CLASS_LABELS[int(r_avg.label[0])],
        "class_delta_max": CLASS_LABELS[int(r_max.label[0])],
        "delta_avg": d_avg,
        "delta_max": d_max,
        "delta_avg_user_px": d_avg * scale,
        "delta_max_user_px": d_max * scale,
        "distances": [float(v) for v in r_avg.distances[0]],
        "reject_threshold": float(m_avg.reject_threshold),
        "registration_ok": ok,
        "registration_residual": float(info.residual[0]),
        "overlap": overlap,
        "in_domain": in_domain,
        "error_blocks": int((qmap > 0).sum()),
        "analysis_size": [h, w],
        "input_size": [int(orig_h), int(orig_w)],
        "user_px_per_analysis_px": scale,
        "homography": H[0].tolist(),
        "warnings": warnings,
        "_map": qmap,
    }
