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
from .distortion import CLASS_LABELS, delta_avg, delta_max, delta_top, distortion_class
from .eigenspace import EigenSpaceClassifier
from .images import as_batch, check_image, load_image, resize_to, to_grey
from .quality import counts_to_map, registration_error_counts
from .methods import NO_DISTORTION_PX
from .registration import estimate_homography, warp_to_reference
from .selfcal import estimate_distortion

__all__ = ["analyze_pair", "default_checkpoint", "MIN_OVERLAP", "METHODS"]

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


@functools.lru_cache(maxsize=4)
def _load_regressor(path: str):
    from .regression import DeltaRegressor

    return DeltaRegressor.load(path).eval()


def _as_image(img, name: str) -> torch.Tensor:
    if isinstance(img, (str, Path)):
        return load_image(img, grey=True)
    x = as_batch(img, name)
    check_image(x, name)
    return to_grey(x).float()


def _regression_checkpoint() -> Path:
    path = _CKPT_DIR / "regression.pt"
    if not path.is_file():
        raise FileNotFoundError(f"shipped regression checkpoint {path} not found; pass checkpoint=PATH")
    return path


METHODS = ("selfcal", "regression", "eigenspace")


def analyze_pair(
    img1,
    img2,
    checkpoint: str | Path | None = None,
    checkpoint_max: str | Path | None = None,
    method: str = "selfcal",
) -> dict:
    """Analyse one overlapping pair of photographs of a roughly planar scene.

    Args:
        img1, img2: file paths, or tensors (H, W), (C, H, W) or (1, C, H, W); colour or grey,
            any size (both the same size).
        checkpoint: for ``eigenspace`` the Delta_avg checkpoint, for ``regression`` the
            regressor (default: the shipped ones in checkpoints/).
        checkpoint_max: for ``eigenspace``, the Delta_max checkpoint (default: shipped).
        method: ``selfcal`` (the default and the most accurate: (k2, k4) estimated with the
            homography, with a confidence), ``regression`` (Delta from the quality map), or
            ``eigenspace`` (the paper's classifier).

    Returns:
        A dict with ``class`` ("1"-"4" or "R"), ``delta_avg`` and ``delta_max`` (analysis px),
        the same in the user's pixels, ``distances`` (eigen-space, per class), ``confidence``,
        ``cannot_tell``, ``registration_ok``, ``in_domain``, ``overlap``, ``warnings`` and more.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    a, b = _as_image(img1, "img1"), _as_image(img2, "img2")
    if a.shape[-2:] != b.shape[-2:]:
        raise ValueError(f"img1 and img2 must have the same size, got {tuple(a.shape[-2:])} and {tuple(b.shape[-2:])}")
    cfg = LensdistConfig()
    eigen = None
    if method == "eigenspace" or (checkpoint is None and (_CKPT_DIR / "eigenspace_delta_avg_10ev.pt").is_file()):
        eigen = _load_model(str(checkpoint if method == "eigenspace" and checkpoint else default_checkpoint("delta_avg")))
        cfg = eigen.config
    h, w = cfg.image.height, cfg.image.width
    orig_h, orig_w = a.shape[-2:]
    scale = min(orig_w / w, orig_h / h)  # user px per analysis px (the crop keeps the aspect)
    a, b = resize_to(a, h, w).clamp(0, 1), resize_to(b, h, w).clamp(0, 1)
    H, info = estimate_homography(a, b)
    warped, valid = warp_to_reference(b, H)
    overlap = float(valid.mean())
    qmap = counts_to_map(registration_error_counts(a, warped, valid, cfg.quality), cfg.quality)
    ok = bool(info.converged[0])
    warnings = []
    out = {"method": method, "distances": [], "reject_threshold": None, "confidence": None, "cannot_tell": False}
    if eigen is not None:
        with torch.no_grad():
            r_e = eigen(qmap.flatten(1))
        out["distances"] = [float(v) for v in r_e.distances[0]]
        out["reject_threshold"] = float(eigen.reject_threshold)
    in_domain = ok and overlap >= MIN_OVERLAP
    if method == "eigenspace":
        m_max = _load_model(str(checkpoint_max or default_checkpoint("delta_max")))
        with torch.no_grad():
            r_max = m_max(qmap.flatten(1))
        d_avg, d_max = float(r_e.delta[0]), float(r_max.delta[0])
        label = CLASS_LABELS[int(r_e.label[0])]
        far = min(out["distances"]) > 2.0 * out["reject_threshold"]
        in_domain = in_domain and not far
        if ok and far:
            warnings.append("the quality map is unlike every training map (out of domain): treat the class with caution")
    elif method == "regression":
        reg = _load_regressor(str(checkpoint or _regression_checkpoint()))
        with torch.no_grad():
            r = reg(qmap.flatten(1))
        d_avg, d_max = float(r.delta_avg[0]), float(r.delta_max[0])
        label = "R" if d_avg < NO_DISTORTION_PX else CLASS_LABELS[int(r.class_avg[0])]
        out["confidence"], out["cannot_tell"] = float(r.confidence[0]), not bool(r.confident[0])
    else:
        k2, k4, _, sc = estimate_distortion(a, b, init=H.double() if ok else None)
        if not bool(sc.converged[0]):
            warnings.append("self-calibration diverged: no estimate from this pair")
            d_avg = d_max = float("nan")
            label = "R"
            out["cannot_tell"] = True
            out["confidence"] = 0.0
        else:
            d_avg = float(delta_avg(k2, k4, h, w)[0])
            d_max = float(delta_max(k2, k4, h, w)[0])
            label = "R" if d_avg < NO_DISTORTION_PX else CLASS_LABELS[int(distortion_class(torch.tensor([d_avg]), delta_top("delta_avg", h, w))[0])]
            out["confidence"], out["cannot_tell"] = float(sc.confidence[0]), not bool(sc.confident[0])
            out.update(k2=float(k2[0]), k4=float(k4[0]), delta_avg_std=float(sc.delta_avg_std[0]))
    if not ok:
        warnings.append("registration failed: the pair could not be aligned by a homography; the result is not meaningful")
    if overlap < MIN_OVERLAP:
        warnings.append(f"the images overlap on {100 * overlap:.0f} % only (< {100 * MIN_OVERLAP:.0f} %): too little to judge")
    if out["cannot_tell"]:
        warnings.append("cannot tell from this pair: too little motion or texture to see the distortion (low confidence)")
    out.update(
        {
            "class": label,
            "delta_avg": d_avg,
            "delta_max": d_max,
            "delta_avg_user_px": d_avg * scale,
            "delta_max_user_px": d_max * scale,
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
    )
    return out
