"""Analyse a user's own image pairs: registration, quality map, distortion class and Delta.

:func:`analyze_batch` is the one analysis path: ``lensdist analyze``, :func:`analyze_pair`
(a batch of one) and the evaluation behind every reported figure
(:mod:`~lensdist_torch.workflows.evaluate`) all call it. Per pair it brings both images to the
analysis size (centre crop to the aspect ratio, then area resampling), registers them with an
estimated homography (:func:`~lensdist_torch.registration.wide_baseline.estimate_homography_robust`:
the direct registration, with a feature fallback for far-apart pairs; :mod:`.prepare`),
computes the quality map and asks one estimator for the distortion: the
self-calibration (default; started from the registration's H), the Delta regression, or the
paper's eigen-space classifiers; then the decision of :mod:`~lensdist_torch.workflows.decision`
(class or "cannot tell", calibrated confidence, domain checks). Each pair's answer is a
:class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis`, offsets in analysis pixels and in
the user's pixels. What a user sets is in ``config.analysis``; the decision's constants are named
in the modules that use them (:data:`OUT_OF_DOMAIN_FACTOR` here).

On the CPU the estimators (registration, self-calibration, classifiers) run pair by pair: their
batched float32 kernels round differently with the batch's size, and a pair's answer must not
depend on the pairs it was analysed with. On a GPU, whose kernels round differently from the
CPU's anyway, the registration and the self-calibration take the batch in one call (about 10 x
faster; the answers agree with the CPU's to ~1e-3 px). Resampling, warps and quality maps are
batched.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from importlib import resources
from pathlib import Path

import torch

from lensdist_torch.classify.eigenspace import EigenSpaceClassifier
from lensdist_torch.classify.regression import DeltaRegressor
from lensdist_torch.config import LensdistConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.core.images import centre_crop_box
from lensdist_torch.core.storage import CheckpointError, check_compatible
from lensdist_torch.geometry.distortion import CLASS_LABELS, METRICS, estimated_class
from lensdist_torch.geometry.homography import check_homography
from lensdist_torch.workflows.confidence import platt
from lensdist_torch.workflows.decision import (
    SELFCAL_CONFIDENCE_SCALE,
    SELFCAL_CONFIDENCE_SHIFT,
    decide,
    domain_checks,
    in_user_pixels,
)
from lensdist_torch.workflows.pair_analysis import JSON_KEYS, PairAnalysis
from lensdist_torch.workflows.prepare import PreparedPairs, one_thread, prepare_batch, resolve_device

__all__ = ["analyze_batch", "analyze_pair", "analysis_config", "prepare_batch", "PreparedPairs", "default_checkpoint",
           "resolve_device", "METHODS"]

METHODS = ("selfcal", "regression", "eigenspace")
_CKPT_DIR = Path(str(resources.files("lensdist_torch") / "checkpoints"))  # package data: in the wheel too
_ATTRIBUTES = {key: name for name, key in JSON_KEYS.items()}  # the working dict's keys -> PairAnalysis's names
_SHIPPED = {
    "delta_avg": "eigenspace_delta_avg_10ev.pt",
    "delta_max": "eigenspace_delta_max_10ev.pt",
    "regression": "regression.pt",
}
#: An eigen-space map farther from every class than this multiple of its reject threshold is unlike every training map.
OUT_OF_DOMAIN_FACTOR = 2.0


def default_checkpoint(name: str = "delta_avg") -> Path:
    """The shipped checkpoint ``name``.

    ``delta_avg`` / ``delta_max`` (eigen-space, 10 eigenvectors) or ``regression``.
    """
    if name not in _SHIPPED:
        raise ValueError(f"name must be one of {sorted(_SHIPPED)}, got {name!r}")
    path = _CKPT_DIR / _SHIPPED[name]
    if not path.is_file():
        raise FileNotFoundError(
            f"shipped checkpoint {path} not found; pass checkpoint=PATH, e.g. one written by `lensdist reproduce`"
        )
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
    return path if isinstance(path, EigenSpaceClassifier) else _cached_eigenspace(*_file_key(path))


def _load_regressor(path) -> DeltaRegressor:
    if isinstance(path, DeltaRegressor):
        return path
    if isinstance(path, EigenSpaceClassifier):
        raise CheckpointError(
            "`checkpoint` is an eigen-space classifier, but method 'regression' needs a Delta regressor"
        )
    return _cached_regressor(*_file_key(path))


def _eigenspace_models(checkpoint, checkpoint_max) -> tuple:
    """The Delta_avg and Delta_max classifiers, each checked against its metric.

    None is the shipped one; False leaves that metric out (a lone classifier under evaluation).
    Both must be fitted under the same image size, block size and thresholds.
    """
    wanted = [(c, metric, option) for c, metric, option in zip(
        (checkpoint, checkpoint_max), METRICS, ("`checkpoint`", "`checkpoint_max`"))]
    models = []
    for c, metric, option in wanted:
        if c is False:
            models.append(None)
            continue
        path = default_checkpoint(metric) if c is None else c
        model = _load_eigenspace(path)
        if model.config.classifier.metric != metric:
            raise CheckpointError(
                f"{path} is a {model.config.classifier.metric} classifier, but {option} needs a {metric} one"
            )
        models.append(model)
    if models[0] is None and models[1] is None:
        raise ValueError("method 'eigenspace' needs at least one of checkpoint and checkpoint_max")
    if models[0] is not None and models[1] is not None:
        check_compatible(models[1].config, models[0].config, checkpoint_max or default_checkpoint("delta_max"))
    return tuple(models)


def _model_on(model, device: torch.device):
    """The model with its buffers on ``device`` (a copy if it lives elsewhere: the caller's and cached ones stay)."""
    if model is None or next(iter(model.buffers())).device == device:
        return model
    moved = copy.deepcopy(model).to(device)
    moved.extra = getattr(model, "extra", {})
    return moved


# ------------------------------------------------------------------ the methods, one pair each
def _selfcal(p: PreparedPairs, i: int, _models) -> dict:
    res = dict(p.selfcal()[i])
    res["confidence"] = float(platt(res["raw_confidence"], SELFCAL_CONFIDENCE_SCALE, SELFCAL_CONFIDENCE_SHIFT))
    return res


def _regression(p: PreparedPairs, i: int, reg: DeltaRegressor) -> dict:
    """The Delta regressor on pair i's quality map: both Deltas with a confidence."""
    cfg, a = p.config, p.config.analysis
    with torch.no_grad():
        r = reg(p.qmap[i : i + 1].flatten(1))
    d_avg, d_max = r.delta_avg.double().cpu(), r.delta_max.double().cpu()
    raw = float(r.confidence[0])
    return {
        "estimated_class": CLASS_LABELS[int(estimated_class(d_avg, d_avg, metric="delta_avg", config=cfg)[0])],
        "estimated_class_max": CLASS_LABELS[int(estimated_class(d_max, d_avg, metric="delta_max", config=cfg)[0])],
        "delta_avg": float(d_avg[0]),
        "delta_max": float(d_max[0]),
        "raw_confidence": raw,
        "confidence": float(platt(raw, a.regression_confidence_scale, a.regression_confidence_shift)),
    }


def _eigenspace(p: PreparedPairs, i: int, models) -> dict:
    """The paper's classifiers on pair i's quality map: classes, both Deltas, distances, domain check."""
    out = {
        "estimated_class": None,
        "estimated_class_max": None,
        "delta_avg": None,
        "delta_max": None,
        "confidence": None,
    }
    far = False
    x = p.qmap[i : i + 1].flatten(1)
    for model, metric in zip(models, METRICS):
        if model is None:
            continue
        with torch.no_grad():
            r = model(x)
        suffix = "" if metric == "delta_avg" else "_max"
        out[f"estimated_class{suffix}"] = CLASS_LABELS[int(r.label[0])]
        out[metric] = float(r.delta[0])
        if metric == "delta_avg" or models[0] is None:
            out["distances"] = [float(v) for v in r.distances[0]]
            out["reject_threshold"] = float(model.reject_threshold)
            far = min(out["distances"]) > OUT_OF_DOMAIN_FACTOR * out["reject_threshold"]
    out["_far"] = far
    return out


_RUN = {"selfcal": _selfcal, "regression": _regression, "eigenspace": _eigenspace}


def _models_and_config(method, checkpoint, checkpoint_max, config):
    """The method's models and the config of the analysis.

    Without a config, a checkpoint's measurement settings (image size, quality, distortion
    ranges) are adopted and everything else is the default; with one, they must match.
    """
    if method not in METHODS:
        raise ValueError(f"`method` must be one of {METHODS}, got {method!r}")
    # an option the method does not use is refused, not ignored; checkpoints load before the images
    if checkpoint_max is not None and checkpoint_max is not False and method != "eigenspace":
        raise ValueError(f"`checkpoint_max` is used by method 'eigenspace' only, not {method!r}")
    if checkpoint is not None and method == "selfcal":
        raise ValueError(
            "`checkpoint` is not used by method 'selfcal'; it is for 'regression' or 'eigenspace'"
        )
    if method == "selfcal":
        return None, or_defaults(config, LensdistConfig)
    if method == "eigenspace":
        models = _eigenspace_models(checkpoint, checkpoint_max)
    else:
        models = _load_regressor(checkpoint if checkpoint is not None else default_checkpoint("regression"))
    first = models if isinstance(models, DeltaRegressor) else next(m for m in models if m is not None)
    if config is None:
        d = LensdistConfig()
        mc = first.config
        return models, dataclasses.replace(d, image=mc.image, quality=mc.quality, distortion=mc.distortion)
    where = checkpoint if checkpoint not in (None, False) else checkpoint_max
    check_compatible(first.config, config, where if isinstance(where, (str, Path)) else "(the given model)")
    return models, config


def analysis_config(*, method: str = "selfcal", checkpoint=None, checkpoint_max=None,
                    config: LensdistConfig | None = None) -> LensdistConfig:
    """The settings an analysis runs under, its options checked before any image is read.

    The checks of :func:`analyze_batch`: an option the method does not use is refused, the
    checkpoints load (a missing or corrupt one is a one-line error), and a checkpoint's image
    size and quality thresholds are adopted without a ``config``.

    Example:
        >>> analysis_config().image.size
        (320, 424)
        >>> analysis_config(checkpoint="m.pt")
        Traceback (most recent call last):
        ...
        ValueError: `checkpoint` is not used by method 'selfcal'; it is for 'regression' or 'eigenspace'
    """
    return _models_and_config(method, checkpoint, checkpoint_max, config)[1]


def analyze_batch(
    img1,
    img2,
    *,
    method: str = "selfcal",
    config: LensdistConfig | None = None,
    checkpoint=None,
    checkpoint_max=None,
    device=None,
    homography=None,
    prepared: PreparedPairs | None = None,
    return_maps: bool = False,
) -> list[PairAnalysis] | tuple[list[PairAnalysis], torch.Tensor]:
    """Analyse a batch of overlapping pairs of photographs of roughly planar scenes.

    Args:
        img1: file paths, a list of tensors, or a tensor (B, C, H, W); one image (a path or an
            (H, W), (C, H, W) tensor) is a batch of one. Colour or grey, any size.
        img2: the second images, each overlapping its img1 and of its size.
        method: ``selfcal`` (the default and the most accurate: (k2, k4) estimated with the
            homography, started from the registration's), ``regression`` (Delta from the
            quality map) or ``eigenspace`` (the paper's classifiers).
        config: settings (analysis size, registration, self-calibration, decision); without
            one, a checkpoint's image size and quality thresholds are used.
        checkpoint: for ``eigenspace`` the Delta_avg classifier, for ``regression`` the
            regressor: a path or a loaded model (default: the shipped ones). Refused with
            ``selfcal``.
        checkpoint_max: for ``eigenspace``, the Delta_max classifier (default: shipped; False:
            none). Each eigen-space checkpoint must be fitted for its own metric.
        device: where the tensors go ("cpu" by default, "cuda", ...).
        homography: optional (B, 3, 3) registrations img1 -> img2 at the analysis size, used
            instead of estimating them.
        prepared: a :class:`PreparedPairs` batch from :func:`prepare_batch` (then img1, img2,
            homography and device are ignored): several methods on one registration.
        return_maps: also return the (B, 1, H/8, W/8) quality maps of the registered pairs.

    Returns:
        One :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis` per pair (every field
        documented there): ``class_label`` and ``class_max_label`` ("1"-"4" or "R"; None with
        ``cannot_tell`` True when the pair cannot support an answer, the reasons in
        ``warnings``), ``estimated_class`` (the estimator's own answer, even when unsure),
        ``delta_avg``, ``delta_max`` (analysis px; None without an estimate), the same in the
        user's pixels, ``confidence`` (calibrated P(class right); None for eigenspace),
        ``registration_ok`` (and ``registered_by``: "homography", or with ``selfcal``
        "self-calibration" where only its fit, which models the lens and the photometry, passed
        the registration's residual test), ``in_domain``, ``overlap``, ``fitted_on``,
        ``warnings`` and more; ``to_json()`` is ``lensdist analyze --json``'s object and
        ``summary()`` its text. With ``return_maps``, (that list, the quality maps).

    Example:
        >>> from lensdist_torch.calibration.controllers.calibrate import synthetic_sequence
        >>> frames, ideal = synthetic_sequence(2, 1e-6, 0.0)  # a pan through a lens of Delta_avg 4.19 px, and without
        >>> res = analyze_batch(torch.stack([frames[0], ideal[0]]), torch.stack([frames[1], ideal[1]]))
        >>> [r.class_label for r in res], abs(res[0].delta_avg - 4.19) < 0.25  # px at 320 x 424
        (['2', 'R'], True)
    """
    dev = resolve_device(device) if prepared is None else prepared.img1.device
    with one_thread(dev):  # one pair's small tensors on the CPU: one thread (prepare.one_thread)
        return _analyze_batch(img1, img2, method=method, config=config, checkpoint=checkpoint,
                              checkpoint_max=checkpoint_max, device=device, homography=homography, prepared=prepared,
                              return_maps=return_maps)


def _analyze_batch(img1, img2, *, method, config, checkpoint, checkpoint_max, device, homography, prepared,
                   return_maps):
    """:func:`analyze_batch`'s work, on the threads it was given."""
    models, cfg = _models_and_config(method, checkpoint, checkpoint_max, config)
    p = (
        prepared
        if prepared is not None
        else prepare_batch(img1, img2, config=cfg, homography=homography, device=device)
    )
    if prepared is not None and (p.config.image != cfg.image or p.config.quality != cfg.quality):
        raise CheckpointError(
            "the prepared batch was made under another image size or quality thresholds than the checkpoint's"
        )
    cfg = p.config
    dev = p.img1.device
    models = tuple(_model_on(m, dev) for m in models) if isinstance(models, tuple) else _model_on(models, dev)
    extra = {}
    if models is not None:
        first = models if isinstance(models, DeltaRegressor) else next(m for m in models if m is not None)
        extra = getattr(first, "extra", {}) or {}
    h, w = cfg.image.size
    out = []
    for i in range(p.img1.shape[0]):
        res = {"method": method, "distances": [], "reject_threshold": None, "confidence": None}
        res.update(_RUN[method](p, i, models))
        motion, by = float(p.motion[i]), "homography" if bool(p.registration_ok[i]) else None
        aligned, aligned_motion = res.pop("_aligned", False), res.pop("_aligned_motion_px", math.nan)
        if by is None and aligned:  # the registration's residual test, passed with the lens and photometry modelled
            motion, by = aligned_motion, "self-calibration"
        res.update(registration_ok=by is not None, registered_by=by, overlap=float(p.overlap[i]),
                   motion_px=motion if math.isfinite(motion) else None)
        if method != "selfcal":
            domain_checks(res, p.selfcal()[i] if cfg.analysis.cross_check else None,
                          p.texture()[i : i + 1] if extra.get("texture") else None, extra, cfg=cfg)
        decide(res, cfg)
        s, (ih, iw) = p.scale[i], p.input_size[i]
        box = centre_crop_box(ih, iw, h, w)
        whole = box == (0, 0, ih, iw)
        region = {m: None if res[m] is None else res[m] * s for m in METRICS}
        res.update(
            analysed_region_user_px=list(box),
            delta_avg_region_user_px=region["delta_avg"],
            delta_max_region_user_px=region["delta_max"],
            # over the user's whole frame: the region's when it is the frame (the self-calibration
            # extends its coefficients to the whole frame below)
            delta_avg_user_px=region["delta_avg"] if whole else None,
            delta_max_user_px=region["delta_max"] if whole else None,
            registration_residual=float(p.residual[i]),
            error_blocks=int((p.qmap[i] > 0).sum()),
            analysis_size=[h, w],
            input_size=p.input_size[i],
            user_px_per_analysis_px=s,
            homography=p.H[i].cpu().tolist(),
        )
        if method == "selfcal":
            res.update(in_user_pixels(res, s, p.input_size[i]))
        # by keyword: a key that is no field, or a field without its key, is a TypeError here
        out.append(PairAnalysis(**{_ATTRIBUTES.get(key, key): value for key, value in res.items()}))
    return (out, p.qmap) if return_maps else out


def analyze_pair(img1, img2, *, checkpoint=None, checkpoint_max=None, method: str = "selfcal",
                 config: LensdistConfig | None = None, return_map: bool = False, device=None,
                 homography=None) -> PairAnalysis | tuple[PairAnalysis, torch.Tensor]:
    """Analyse one overlapping pair: :func:`analyze_batch` of a batch of one.

    Args:
        img1: a file path, or a tensor (H, W), (C, H, W) or (1, C, H, W); colour or grey, any size.
        img2: the second image, overlapping the first; the same forms and the same size.
        checkpoint: as for :func:`analyze_batch`.
        checkpoint_max: as for :func:`analyze_batch`.
        method: as for :func:`analyze_batch`.
        config: as for :func:`analyze_batch`.
        device: as for :func:`analyze_batch`.
        return_map: also return the (1, 1, H/8, W/8) quality map.
        homography: optional (3, 3) or (1, 3, 3) registration img1 -> img2 at the analysis size.

    Returns:
        The pair's :class:`~lensdist_torch.workflows.pair_analysis.PairAnalysis` (see
        :func:`analyze_batch`); with ``return_map``, (that record, the quality map).

    Example:
        >>> from lensdist_torch import load_scene
        >>> scene = load_scene("gravel")
        >>> res = analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424])
        >>> res.registration_ok, res.method, res.class_label
        (True, 'selfcal', 'R')
    """
    for img, name in ((img1, "img1"), (img2, "img2")):
        if isinstance(img, (list, tuple)) or (isinstance(img, torch.Tensor) and img.dim() == 4 and img.shape[0] != 1):
            raise ValueError(
                f"{name} must be one image (a path or an (H, W), (C, H, W), (1, C, H, W) tensor); "
                "use analyze_batch for more"
            )
    hom = None
    if homography is not None:
        try:
            hom = torch.as_tensor(homography, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(
                f"homography must be a (3, 3) or (1, 3, 3) array of numbers, got {type(homography).__name__}"
            ) from None
        if hom.device.type == "meta":
            raise ValueError("homography is on the meta device (a shape, no values): give a (3, 3) matrix")
        if hom.shape not in ((3, 3), (1, 3, 3)):
            raise ValueError(f"homography must have shape (3, 3) or (1, 3, 3), got {tuple(hom.shape)}")
        hom = check_homography(hom.reshape(1, 3, 3), "homography")
    out, qmap = analyze_batch(img1, img2, method=method, config=config, checkpoint=checkpoint,
                              checkpoint_max=checkpoint_max, device=device, homography=hom, return_maps=True)
    return (out[0], qmap) if return_map else out[0]
