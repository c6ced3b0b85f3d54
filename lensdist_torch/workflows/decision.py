"""The decision of ``analyze``: the honest answer, the calibrated confidence and the domain checks.

Every threshold is in ``config.analysis`` (:class:`~lensdist_torch.config.AnalysisConfig`).

* **Confidence.** The self-calibration and the regression give a raw confidence c = s0 /
  (s0 + std) (docs/method.md, section 10). The reported confidence is its Platt map
  sigmoid(scale * logit(c) + shift), fitted on a validation split so that it estimates
  P(class right) (:func:`fit_platt`); below ``min_confidence`` the answer is "cannot tell".
* **Domain** of the learned methods (regression, eigen-space), whose checkpoints were fitted on
  a few scenes: a pair is out of domain where its gradient-magnitude histogram is farther from
  every training scene than ``texture_factor`` times the largest distance of a training view
  (:func:`texture_statistics`, stored in the checkpoint's ``extra``), or where the
  self-calibration, which learns nothing, confidently disagrees: one finds distortion and the
  other none (class R against a class), the classes are more than ``max_class_disagreement``
  apart, or Delta_avg more than ``max_delta_disagreement`` of its range apart.
* **Confirmation** of an answer without a confidence (the eigen-space's: nothing says how sure
  it is, and on rendered pairs 30 of its 75 answers were a class off): its class stands only
  where the self-calibration confidently finds a class at most ``eigenspace_max_class_disagreement``
  (0) from it; where the self-calibration cannot tell or finds another class, "cannot tell".
* **The answer** (:func:`decide`): ``class`` is None and ``cannot_tell`` True whenever the
  registration failed, there is no estimate, the overlap is too small, the pair is out of
  domain or the confidence is low; ``estimated_class`` keeps the estimator's own guess.
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.data.synthesis import draw_pairs, render_pairs
from lensdist_torch.geometry.calibration import user_coefficients
from lensdist_torch.geometry.distortion import CLASS_LABELS, delta_top, pixel_offsets
from lensdist_torch.geometry.opencv_model import opencv_export
from lensdist_torch.metric.criteria import local_criteria

__all__ = [
    "in_user_pixels",
    "TEXTURE_EDGES",
    "texture_histogram",
    "texture_statistics",
    "texture_distance",
    "platt",
    "fit_platt",
    "expected_calibration_error",
    "reliability",
    "class_distance",
    "domain_checks",
    "decide",
]

#: Bin edges of the gradient-magnitude histogram (normalised Sobel on [0, 1] intensities),
#: log-spaced; values below and above fall into two more bins.
TEXTURE_EDGES = tuple(float(v) for v in torch.logspace(math.log10(0.002), math.log10(0.5), 17, dtype=torch.float64))


def texture_histogram(img: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) grey images in [0, 1] -> (B, 18) float64 histograms of the gradient magnitude G."""
    g = local_criteria(img, img, validate=False).g1.flatten(1).double()
    idx = torch.bucketize(g, torch.tensor(TEXTURE_EDGES, dtype=torch.float64, device=g.device))
    n = len(TEXTURE_EDGES) + 1
    hist = torch.zeros(g.shape[0], n, dtype=torch.float64, device=g.device).scatter_add_(1, idx, torch.ones_like(g))
    return (hist / hist.sum(1, keepdim=True)).cpu()


def texture_statistics(config: LensdistConfig, scenes: list[torch.Tensor], names: list[str], n_views: int = 24) -> dict:
    """The training scenes' texture, for a checkpoint's ``extra``.

    Renders the first ``n_views`` training views (I1) of every scene through the protocol
    (docs/method.md, section 7), and returns {"names", "reference": the mean histogram per
    scene, "spread": the largest total-variation distance of a view from its scene's mean}.
    """
    n_scenes = len(scenes)
    params = draw_pairs(config, "train", range(min(config.protocol.n_train, 4 * n_views * n_scenes)), n_scenes)
    refs, spread = [], 0.0
    for s in range(n_scenes):
        sel = (params.scene == s).nonzero().flatten()[:n_views].tolist()
        if not sel:
            raise ValueError(f"no training view of scene {names[s]!r} among the first pairs")
        sub = draw_pairs(config, "train", params.index[sel].tolist(), n_scenes)
        img1, _ = render_pairs(scenes, sub, config)
        h = texture_histogram(img1.clamp(0, 1))
        ref = h.mean(0)
        refs.append(ref.tolist())
        spread = max(spread, float(0.5 * (h - ref).abs().sum(1).max()))
    return {"names": list(names), "edges": list(TEXTURE_EDGES), "reference": refs, "spread": spread}


def texture_distance(hist: torch.Tensor, stats: dict) -> torch.Tensor:
    """(B,) total-variation distance of histograms (B, n) from the nearest training scene."""
    ref = torch.tensor(stats["reference"], dtype=torch.float64)
    return 0.5 * (hist[:, None, :] - ref[None]).abs().sum(-1).min(1).values


# ------------------------------------------------------------------ confidence
def _logit(c: torch.Tensor) -> torch.Tensor:
    c = c.double().clamp(1e-9, 1 - 1e-9)
    return torch.log(c) - torch.log1p(-c)


def platt(confidence, scale: float, shift: float) -> torch.Tensor:
    """sigmoid(scale * logit(c) + shift) of raw confidences c in (0, 1]; (1, 0) is the identity."""
    c = torch.as_tensor(confidence, dtype=torch.float64)
    return torch.where(torch.isfinite(c), torch.sigmoid(scale * _logit(c) + shift), c)


def fit_platt(confidence: torch.Tensor, right: torch.Tensor, ridge: float = 1.0) -> tuple[float, float]:
    """(scale, shift) of the Platt map maximising the likelihood of ``right`` given ``confidence``.

    Newton's method on the logistic log-likelihood of right ~ sigmoid(scale * logit(c) + shift)
    plus ``ridge`` / 2 x the squared distance of (scale, shift) from the identity (1, 0): a unit
    Gaussian prior, which keeps a fit on a few dozen pairs near the identity and is negligible
    on hundreds. The scale stays positive (a higher raw confidence never means a lower
    calibrated one).
    """
    x, y = _logit(confidence), right.double()
    if x.numel() < 2 or bool((y == y[0]).all()):
        return 1.0, 0.0  # nothing to fit on: keep the identity
    theta = torch.tensor([1.0, 0.0], dtype=torch.float64)
    feats = torch.stack([x, torch.ones_like(x)], 1)
    for _ in range(50):
        p = torch.sigmoid(feats @ theta)
        grad = feats.T @ (p - y) + ridge * (theta - torch.tensor([1.0, 0.0], dtype=torch.float64))
        hess = feats.T @ (feats * (p * (1 - p))[:, None]) + ridge * torch.eye(2, dtype=torch.float64)
        step = torch.linalg.solve(hess, grad)
        theta = theta - step
        if float(step.abs().max()) < 1e-10:
            break
    scale, shift = float(theta[0]), float(theta[1])
    return (scale, shift) if scale > 1e-3 and math.isfinite(scale) and math.isfinite(shift) else (1.0, 0.0)


def reliability(confidence: torch.Tensor, right: torch.Tensor, n_bins: int = 10) -> dict:
    """Per equal-width confidence bin: pairs, mean confidence, share right; and the ECE.

    ECE = sum over bins of (pairs in bin / pairs) x |share right - mean confidence|.
    """
    c, y = confidence.double().reshape(-1), right.double().reshape(-1)
    ok = torch.isfinite(c)
    c, y = c[ok], y[ok]
    idx = (c * n_bins).long().clamp(0, n_bins - 1)
    n = torch.bincount(idx, minlength=n_bins).double()
    mean_c = torch.bincount(idx, c, minlength=n_bins) / n.clamp_min(1)
    acc = torch.bincount(idx, y, minlength=n_bins) / n.clamp_min(1)
    ece = float((n * (acc - mean_c).abs()).sum() / n.sum().clamp_min(1))
    nan = float("nan")
    return {
        "n": [int(v) for v in n],
        "confidence": [float(v) if k else nan for v, k in zip(mean_c, n)],
        "accuracy": [float(v) if k else nan for v, k in zip(acc, n)],
        "ece": ece if int(n.sum()) else nan,
        "pairs": int(n.sum()),
    }


def expected_calibration_error(confidence: torch.Tensor, right: torch.Tensor, n_bins: int = 10) -> float:
    """The expected calibration error of confidences against outcomes (equal-width bins)."""
    return reliability(confidence, right, n_bins)["ece"]


# ------------------------------------------------------------------ the answer
def class_distance(a: str | None, b: str | None) -> int | None:
    """How many classes apart two labels are, R counting as class 0; None if either is missing."""
    if a is None or b is None:
        return None
    rank = {lab: (0 if lab == CLASS_LABELS[-1] else int(lab)) for lab in CLASS_LABELS}
    return abs(rank[a] - rank[b])


def domain_checks(res: dict, selfcal: dict | None, texture: torch.Tensor | None, extra: dict, cfg: LensdistConfig) -> None:
    """The learned methods' domain checks on one result, in place (read by :func:`decide`).

    Args:
        res: the method's result (``estimated_class``, ``delta_avg``).
        selfcal: the self-calibration of the same pair (its raw confidence, class and Delta),
            or None to skip the cross-check.
        texture: (1, n) gradient-magnitude histogram of the pair, or None without statistics.
        extra: the checkpoint's ``extra`` ({"scenes": [...], "texture": ...}).
        cfg: the analysis settings.
    """
    a = cfg.analysis
    res["fitted_on"] = list(extra.get("scenes", [])) or None
    stats = extra.get("texture")
    if stats and texture is not None:
        d = float(texture_distance(texture, stats)[0])
        res["texture_distance"], res["texture_limit"] = d, a.texture_factor * float(stats["spread"])
        res["_texture_far"] = d > res["texture_limit"]
    if selfcal is None:
        return
    conf = float(platt(selfcal["raw_confidence"], a.selfcal_confidence_scale, a.selfcal_confidence_shift))
    usable = selfcal["delta_avg"] is not None and conf >= a.min_confidence and res["delta_avg"] is not None
    check = {"class": selfcal["estimated_class"], "delta_avg": selfcal["delta_avg"], "usable": usable, "agrees": True}
    if usable:
        gap = class_distance(res["estimated_class"], selfcal["estimated_class"])
        # whether there is distortion at all is asked first: R against a class disagrees
        is_r = [c == CLASS_LABELS[-1] for c in (res["estimated_class"], selfcal["estimated_class"])]
        # a class-R answer's Delta is the eigen-space's guess of its nearest class: the classes decide
        far = not any(is_r) and abs(res["delta_avg"] - selfcal["delta_avg"]) > a.max_delta_disagreement * delta_top("delta_avg", cfg)
        check["agrees"] = not ((gap is not None and gap > a.max_class_disagreement) or far or is_r[0] != is_r[1])
    if res.get("confidence") is None:  # the eigen-space: its class needs the self-calibration's confirmation
        gap = class_distance(res["estimated_class"], selfcal["estimated_class"]) if usable else None
        check["confirms"] = bool(check["agrees"] and gap is not None and gap <= a.eigenspace_max_class_disagreement)
    res["selfcal_check"] = check


def _warnings(res: dict, cfg: LensdistConfig) -> list[str]:
    out = []
    fitted = ", ".join(res.get("fitted_on") or []) or "unknown scenes"
    if res.pop("_diverged", False):
        out.append("self-calibration diverged: no estimate from this pair")
    if res.pop("_far", False) and res["registration_ok"]:
        out.append("the quality map is unlike every training map (out of domain): treat the class with caution")
    if res.pop("_texture_far", False):
        out.append(
            f"the images' texture is unlike the scenes the checkpoint was fitted on ({fitted}): out of domain "
            f"(texture distance {res['texture_distance']:.3f} > {res['texture_limit']:.3f})"
        )
    check = res.get("selfcal_check")
    if check and not check["agrees"]:
        out.append(
            f"the self-calibration disagrees (class {check['class']}, Delta_avg {check['delta_avg']:.2f} px): "
            "the scene is probably unlike the training scenes (out of domain)"
        )
    if check and check["agrees"] and check.get("confirms") is False and res["registration_ok"]:
        found = (f"finds class {check['class']} (Delta_avg {check['delta_avg']:.2f} px), not {res['estimated_class']}"
                 if check["usable"] else "cannot tell from this pair")
        out.append(f"cannot tell: the eigen-space gives no confidence, and the self-calibration {found}; its class "
                   "stands only where the self-calibration confirms it")
    if not res["registration_ok"]:
        out.append("registration failed: the pair could not be aligned by a homography; the result is not meaningful")
    if res["overlap"] < cfg.analysis.min_overlap:
        out.append(
            f"the images overlap on {100 * res['overlap']:.0f} % only (< {100 * cfg.analysis.min_overlap:.0f} %): too little to judge"
        )
    aligned = res["registration_ok"] and res["overlap"] >= cfg.analysis.min_overlap  # else that is the reason given
    if aligned and res["confidence"] is not None and res["confidence"] < cfg.analysis.min_confidence:
        out.append("cannot tell from this pair: too little motion or texture to see the distortion (low confidence)")
    return out


def decide(res: dict, cfg: LensdistConfig) -> None:
    """Set ``warnings``, ``in_domain``, ``cannot_tell``, ``class`` and ``class_max`` of one result, in place.

    "Cannot tell" where the confidence is low, there is no estimate, the pair is out of domain, an
    answer without a confidence is not confirmed by the self-calibration (:func:`domain_checks`), or
    the views moved by less than ``analysis.min_motion_px`` (``motion_px``: the registration's
    mean displacement; every method, since none can see a distortion that cancels). Then
    ``class``, ``class_max``, ``delta_avg``, ``delta_max`` and ``distortion_type`` are None: no
    number that reads as an answer. ``estimated_class``, ``estimated_class_max``,
    ``estimated_delta_avg`` and ``estimated_delta_max`` keep the estimator's own output, for
    evaluation. A Delta_avg beyond the classes' range is class 4 with a warning saying so and
    ``beyond_class_range`` True. A failed registration or too small an overlap is the one reason
    given for a low confidence (not also "too little motion or texture").
    """
    a = cfg.analysis
    check = res.get("selfcal_check")
    res["in_domain"] = bool(
        res["registration_ok"] and res["overlap"] >= a.min_overlap and not res.get("_far", False)
        and not res.get("_texture_far", False) and not (check and not check["agrees"])
    )
    if not res["registration_ok"] or res.get("_diverged", False):  # no alignment, no estimate
        res.update(delta_avg=None, delta_max=None)
    res["warnings"] = _warnings(res, cfg)
    motion = res.get("motion_px")
    still = res["registration_ok"] and motion is not None and not motion >= a.min_motion_px
    if still:
        res["warnings"].append(
            f"cannot tell from this pair: the views moved by {motion:.2f} px only (< {a.min_motion_px:g}); both carry "
            "the same distortion, which cancels where the scene did not move"
        )
    low = res["confidence"] is not None and res["confidence"] < a.min_confidence
    no_number = res["delta_avg"] is None and res["delta_max"] is None
    unconfirmed = bool(check) and check.get("confirms") is False  # an answer without confidence (domain_checks)
    unsure = low or no_number or still or not res["in_domain"] or unconfirmed
    res["cannot_tell"] = bool(unsure)
    res["class"] = None if unsure else res["estimated_class"]
    res["class_max"] = None if unsure else res["estimated_class_max"]
    # the estimator's own numbers stay, named as such; the answer's numbers only where there is one
    res["estimated_delta_avg"], res["estimated_delta_max"] = res["delta_avg"], res["delta_max"]
    if unsure:
        res.update(delta_avg=None, delta_max=None, delta_avg_interval=None)
    # barrel, pincushion or mustache: from the sign of eq. 4's offsets (the self-calibration only)
    res["distortion_type"] = None if unsure or res["class"] == CLASS_LABELS[-1] else res.get("distortion_type")
    res["beyond_class_range"] = bool(not unsure and res["delta_avg"] is not None
                                     and res["delta_avg"] > delta_top("delta_avg", cfg))
    if res["beyond_class_range"]:
        # the interval was validated within the range only: on real wide-angle pairs (a GoPro,
        # 103 px) 5 of 6 intervals beyond it missed the truth (eq. 4 cannot follow such a lens)
        res["delta_avg_interval"] = None
        res["warnings"].append(
            f"Delta_avg {res['delta_avg']:.1f} px is beyond the classes' range (class 4 ends at "
            f"{delta_top('delta_avg', cfg):.1f} px at this size): class 4 here means 'at least class 4', and the "
            "figure is an extrapolation with no interval"
        )


def in_user_pixels(res: dict, s: float, size) -> dict:
    """Eq. 4's coefficients in the user's pixels, Delta over the user's whole frame, and the OpenCV camera.

    The analysis frame is a centred crop scaled by s: p_user - c_user = s (p - c), so
    k2_user = k2 / s^2 and k4_user = k4 / s^4. ``delta_avg_user_px`` / ``delta_max_user_px``
    are over the user's whole H x W frame (not only the analysed crop), sampled at the analysis
    resolution: s times Delta of (k2, k4) on a round(H / s) x round(W / s) frame. All None
    without an answer (``delta_avg`` None: no estimate, or "cannot tell").
    """
    if res.get("k2") is None or res["delta_avg"] is None:
        return {"k2_user": None, "k4_user": None, "opencv": None, "delta_avg_user_px": None, "delta_max_user_px": None}
    k2_user, k4_user = user_coefficients(res["k2"], res["k4"], s)
    fh, fw = max(1, round(int(size[0]) / s)), max(1, round(int(size[1]) / s))
    off = pixel_offsets(res["k2"], res["k4"], fh, fw)  # one map for both Deltas
    return {"k2_user": k2_user, "k4_user": k4_user, "opencv": opencv_export(k2_user, k4_user, int(size[0]), int(size[1])),
            "delta_avg_user_px": float(off.mean()) * s, "delta_max_user_px": float(off.max()) * s}
