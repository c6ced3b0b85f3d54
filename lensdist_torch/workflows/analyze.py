"""Analyse a user's own image pair: registration, quality map, distortion class and Delta.

``analyze_pair(img1, img2)`` brings both images to the analysis size (centre crop to the
aspect ratio, then area resampling), registers them with an estimated homography, computes the
quality map and asks one estimator for the distortion: the self-calibration (default), the
Delta regression, or the paper's eigen-space classifiers. Offsets are reported in analysis
pixels and in the user's pixels. Every threshold of the decision is in
``config.analysis`` (:class:`~lensdist_torch.config.AnalysisConfig`).
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path

import torch

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import LensdistConfig
from lensdist_torch.core.images import as_batch, check_image, load_image, resize_to, to_grey
from lensdist_torch.core.storage import CheckpointError, check_compatible
from lensdist_torch.geometry.distortion import CLASS_LABELS, METRICS, delta_avg, delta_max, estimated_class
from lensdist_torch.geometry.registration import estimate_homography, warp_to_reference
from lensdist_torch.geometry.selfcal import estimate_distortion
from lensdist_torch.metric.quality import counts_to_map, registration_error_counts

__all__ = ["analyze_pair", "default_checkpoint", "METHODS"]

METHODS = ("selfcal", "regression", "eigenspace")
_CKPT_DIR = Path(str(resources.files("lensdist_torch") / "checkpoints"))  # package data: in the wheel too
_SHIPPED = {"delta_avg": "eigenspace_delta_avg_10ev.pt", "delta_max": "eigenspace_delta_max_10ev.pt", "regression": "regression.pt"}


def default_checkpoint(name: str = "delta_avg") -> Path:
    """The shipped checkpoint ``name``.

    ``delta_avg`` / ``delta_max`` (eigen-space, 10 eigenvectors) or ``regression``.
    """
    if name not in _SHIPPED:
        raise ValueError(f"name must be one of {sorted(_SHIPPED)}, got {name!r}")
    path = _CKPT_DIR / _SHIPPED[name]
    if not path.is_file():
        raise FileNotFoundError(f"shipped checkpoint {path} not found; pass checkpoint=PATH, e.g. one written by `lensdist reproduce`")
    return path


def _file_key(path) -> tuple[str, int, int]:
    """(resolved path, mtime_ns, size): the cache key of a checkpoint.

    A file replaced, rewritten or deleted is never answered from the cache.
    """
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"checkpoint not found: {p}") from None
    return str(p.resolve()), st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=8)
def _cached_eigenspace(path: str, mtime_ns: int, size: int) -> EigenSpaceClassifier:
    return EigenSpaceClassifier.load(path).eval()


@functools.lru_cache(maxsize=4)
def _cached_regressor(path: str, mtime_ns: int, size: int) -> DeltaRegressor:
    return DeltaRegressor.load(path).eval()


def _load_eigenspace(path) -> EigenSpaceClassifier:
    return _cached_eigenspace(*_file_key(path))


def _load_regressor(path) -> DeltaRegressor:
    return _cached_regressor(*_file_key(path))


def _eigenspace_models(checkpoint, checkpoint_max) -> tuple[EigenSpaceClassifier, EigenSpaceClassifier]:
    """The Delta_avg and Delta_max classifiers, each checked against its metric.

    Both must be fitted under the same image size, block size and thresholds.
    """
    paths = (checkpoint or default_checkpoint("delta_avg"), checkpoint_max or default_checkpoint("delta_max"))
    models = tuple(_load_eigenspace(p) for p in paths)
    for model, path, metric, option in zip(models, paths, METRICS, ("checkpoint (--checkpoint)", "checkpoint_max (--checkpoint-max)")):
        if model.config.classifier.metric != metric:
            raise CheckpointError(
                f"{path} is a {model.config.classifier.metric} classifier, but {option} needs a {metric} one"
            )
    check_compatible(models[1].config, models[0].config, paths[1])
    return models


def _as_image(img, name: str) -> torch.Tensor:
    """A path or an (H, W), (C, H, W), (1, C, H, W) tensor -> (1, 1, H, W) float grey."""
    if isinstance(img, (str, Path)):
        return load_image(img, grey=True)
    x = as_batch(img, name)
    check_image(x, name)
    return to_grey(x).float()


def _eigenspace(qmap: torch.Tensor, models, cfg: LensdistConfig) -> dict:
    """The paper's classifiers on a quality map: class, both Deltas, distances, domain check."""
    model, model_max = models
    with torch.no_grad():
        r_avg, r_max = model(qmap.flatten(1)), model_max(qmap.flatten(1))
    distances = [float(v) for v in r_avg.distances[0]]
    threshold = float(model.reject_threshold)
    far = min(distances) > cfg.analysis.out_of_domain_factor * threshold
    return {
        "class": CLASS_LABELS[int(r_avg.label[0])],
        "delta_avg": float(r_avg.delta[0]),
        "delta_max": float(r_max.delta[0]),
        "distances": distances,
        "reject_threshold": threshold,
        "far_from_training": far,
    }


def _regression(qmap: torch.Tensor, reg: DeltaRegressor, cfg: LensdistConfig) -> dict:
    """The Delta regressor on a quality map: both Deltas with a confidence."""
    with torch.no_grad():
        r = reg(qmap.flatten(1))
    return {
        "class": CLASS_LABELS[int(r.class_avg[0])],
        "delta_avg": float(r.delta_avg[0]),
        "delta_max": float(r.delta_max[0]),
        "confidence": float(r.confidence[0]),
        "cannot_tell": not bool(r.confident[0]),
    }


def _selfcal(a: torch.Tensor, b: torch.Tensor, H: torch.Tensor, registered: bool, cfg: LensdistConfig) -> dict:
    """Self-calibration of (k2, k4) on the pair, started from the registration when it worked."""
    k2, k4, _, sc = estimate_distortion(a, b, init=H.double() if registered else None, config=cfg.selfcal)
    if not bool(sc.converged[0]):  # flagged, never a number and never "R"
        return {"class": None, "delta_avg": None, "delta_max": None, "confidence": 0.0, "cannot_tell": True, "diverged": True}
    h, w = cfg.image.size
    d_avg, d_max = delta_avg(k2, k4, h, w), delta_max(k2, k4, h, w)
    return {
        "class": CLASS_LABELS[int(estimated_class(d_avg, d_avg, "delta_avg", cfg)[0])],
        "delta_avg": float(d_avg[0]),
        "delta_max": float(d_max[0]),
        "confidence": float(sc.confidence[0]),
        "cannot_tell": not bool(sc.confident[0]),
        "k2": float(k2[0]),
        "k4": float(k4[0]),
        "delta_avg_std": float(sc.delta_avg_std[0]),
    }


def _warnings(res: dict, far_from_training: bool, diverged: bool, cfg: LensdistConfig) -> list[str]:
    out = []
    if diverged:
        out.append("self-calibration diverged: no estimate from this pair")
    if far_from_training and res["registration_ok"]:
        out.append("the quality map is unlike every training map (out of domain): treat the class with caution")
    if not res["registration_ok"]:
        out.append("registration failed: the pair could not be aligned by a homography; the result is not meaningful")
    if res["overlap"] < cfg.analysis.min_overlap:
        out.append(
            f"the images overlap on {100 * res['overlap']:.0f} % only (< {100 * cfg.analysis.min_overlap:.0f} %): too little to judge"
        )
    if res["cannot_tell"]:
        out.append("cannot tell from this pair: too little motion or texture to see the distortion (low confidence)")
    return out


def analyze_pair(
    img1,
    img2,
    checkpoint: str | Path | None = None,
    checkpoint_max: str | Path | None = None,
    method: str = "selfcal",
    config: LensdistConfig | None = None,
    return_map: bool = False,
):
    """Analyse one overlapping pair of photographs of a roughly planar scene.

    Args:
        img1: a file path, or a tensor (H, W), (C, H, W) or (1, C, H, W); colour or grey, any size.
        img2: the second image, overlapping the first; the same forms and the same size.
        checkpoint: for ``eigenspace`` the Delta_avg checkpoint, for ``regression`` the
            regressor (default: the shipped ones, package data in lensdist_torch/checkpoints/).
            Refused (ValueError) with ``selfcal``, which uses none.
        checkpoint_max: for ``eigenspace``, the Delta_max checkpoint (default: shipped); refused
            with the other methods. Each eigen-space checkpoint must be fitted for its own metric
            (CheckpointError otherwise).
        method: ``selfcal`` (the default and the most accurate: (k2, k4) estimated with the
            homography, with a confidence), ``regression`` (Delta from the quality map), or
            ``eigenspace`` (the paper's classifier).
        config: settings (analysis size, registration, self-calibration, decision); for
            ``eigenspace`` the checkpoint's own config is used.
        return_map: also return the (1, 1, H/8, W/8) quality map.

    Returns:
        A dict with ``class`` ("1"-"4" or "R"; None with ``cannot_tell`` True when the pair
        cannot support an answer, the reasons in ``warnings``), ``delta_avg`` and ``delta_max``
        (analysis px; None when the registration failed or the fit diverged),
        the same in the user's pixels, ``distances`` (eigen-space, per class), ``confidence``,
        ``cannot_tell``, ``registration_ok``, ``in_domain``, ``overlap``, ``warnings`` and
        more; with ``return_map``, the tuple (dict, quality map).

    Example:
        >>> from lensdist_torch import load_scene
        >>> scene = load_scene("gravel")
        >>> res = analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424])
        >>> res["registration_ok"], res["method"]
        (True, 'selfcal')
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    # an option the method does not use is refused, not ignored; checkpoints load before the images
    if checkpoint_max is not None and method != "eigenspace":
        raise ValueError(f"checkpoint_max (--checkpoint-max) is used by method 'eigenspace' only, not {method!r}")
    if checkpoint is not None and method == "selfcal":
        raise ValueError("checkpoint (--checkpoint) is not used by method 'selfcal'; it is for 'regression' or 'eigenspace'")
    models = _eigenspace_models(checkpoint, checkpoint_max) if method == "eigenspace" else None
    reg = _load_regressor(checkpoint or default_checkpoint("regression")) if method == "regression" else None
    a, b = _as_image(img1, "img1"), _as_image(img2, "img2")
    if a.shape[-2:] != b.shape[-2:]:
        raise ValueError(f"img1 and img2 must have the same size, got {tuple(a.shape[-2:])} and {tuple(b.shape[-2:])}")
    cfg = config if config is not None else LensdistConfig()
    if method == "eigenspace":
        cfg = models[0].config
    elif method == "regression":
        check_compatible(reg.config, cfg, checkpoint or default_checkpoint("regression"))
    h, w = cfg.image.size
    orig_h, orig_w = a.shape[-2:]
    scale = min(orig_w / w, orig_h / h)  # user px per analysis px (the crop keeps the aspect)
    a, b = resize_to(a, h, w).clamp(0, 1), resize_to(b, h, w).clamp(0, 1)
    H, info = estimate_homography(a, b, config=cfg.registration)
    warped, valid = warp_to_reference(b, H)
    qmap = counts_to_map(registration_error_counts(a, warped, valid, cfg.quality), cfg.quality)
    ok, overlap = bool(info.converged[0]), float(valid.mean())
    res = {"method": method, "distances": [], "reject_threshold": None, "confidence": None, "cannot_tell": False}
    if method == "eigenspace":
        res.update(_eigenspace(qmap, models, cfg))
    elif method == "regression":
        res.update(_regression(qmap, reg, cfg))
    else:
        res.update(_selfcal(a, b, H, ok, cfg))
    far, diverged = res.pop("far_from_training", False), res.pop("diverged", False)
    if not ok or diverged:  # no alignment, no estimate: the numbers would be noise
        res.update(delta_avg=None, delta_max=None)
    res.update(
        delta_avg_user_px=None if res["delta_avg"] is None else res["delta_avg"] * scale,
        delta_max_user_px=None if res["delta_max"] is None else res["delta_max"] * scale,
        registration_ok=ok,
        registration_residual=float(info.residual[0]),
        overlap=overlap,
        in_domain=ok and overlap >= cfg.analysis.min_overlap and not far,
        error_blocks=int((qmap > 0).sum()),
        analysis_size=[h, w],
        input_size=[int(orig_h), int(orig_w)],
        user_px_per_analysis_px=scale,
        homography=H[0].tolist(),
    )
    res["warnings"] = _warnings(res, far, diverged, cfg)
    _decide(res, cfg)
    return (res, qmap) if return_map else res


def _decide(res: dict, cfg: LensdistConfig) -> None:
    """The honest answer, set in place.

    ``class`` is None and ``cannot_tell`` True whenever the registration failed, the fit diverged, the images overlap too little, the scene is unlike the training
    scenes, or the confidence is below the threshold; the reasons are in ``warnings``.
    """
    unsure = res["cannot_tell"] or not res["registration_ok"] or res["delta_avg"] is None
    unsure |= res["overlap"] < cfg.analysis.min_overlap or not res["in_domain"]
    res["cannot_tell"] = bool(unsure)
    if unsure:
        res["class"] = None
