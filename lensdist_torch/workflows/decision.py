"""The decision of ``analyze``: the honest answer, the calibrated confidence and the domain checks.

What a user sets is in ``config.analysis`` (:class:`~lensdist_torch.config.AnalysisConfig`); the
decision's constants are named below.

* **Confidence.** The self-calibration and the regression give a raw confidence c = s0 /
  (s0 + std) (docs/method.md, section 10). The reported confidence is its Platt map
  sigmoid(scale * logit(c) + shift), fitted on a validation split so that it estimates
  P(class right) (:mod:`~lensdist_torch.workflows.confidence`; the self-calibration's is the
  identity, :data:`SELFCAL_CONFIDENCE_SCALE` and :data:`SELFCAL_CONFIDENCE_SHIFT`); below
  ``min_confidence`` the answer is "cannot tell".
* **Domain** of the learned methods (regression, eigen-space), whose checkpoints were fitted on
  a few scenes: a pair is out of domain where its gradient-magnitude histogram is farther from
  every training scene than :data:`TEXTURE_FACTOR` times the largest distance of a training view
  (:mod:`~lensdist_torch.workflows.texture`, stored in the checkpoint's ``extra``), or where the
  self-calibration, which learns nothing, confidently disagrees: one finds distortion and the
  other none (class R against a class), the classes are more than :data:`MAX_CLASS_DISAGREEMENT`
  apart, or Delta_avg more than :data:`MAX_DELTA_DISAGREEMENT` of its range apart.
* **Confirmation** of an answer without a confidence (the eigen-space's: nothing says how sure
  it is, and on rendered pairs 30 of its 75 answers were a class off): its class stands only
  where the self-calibration confidently finds a class at most
  :data:`EIGENSPACE_MAX_CLASS_DISAGREEMENT` (0) from it; where the self-calibration cannot tell
  or finds another class, "cannot tell".
* **The answer** (:func:`decide`): ``class`` is None and ``cannot_tell`` True whenever the
  registration failed, there is no estimate, the overlap is below :data:`MIN_OVERLAP`, the pair
  is out of domain or the confidence is low; ``estimated_class`` keeps the estimator's own guess.
"""

from __future__ import annotations

import torch

from lensdist_torch.calibration.direct import user_coefficients
from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import CLASS_LABELS, delta_top, pixel_offsets
from lensdist_torch.geometry.opencv_model import opencv_export
from lensdist_torch.workflows.confidence import platt
from lensdist_torch.workflows.texture import texture_distance

__all__ = ["REASONS", "in_user_pixels", "class_distance", "domain_checks", "decide"]

#: The codes of ``cannot_tell_reasons``, in the order they are listed: the registration failed,
#: the views overlap too little, no estimate, too little motion, relief found (the planar and
#: the plane + parallax models put the pair in different classes), a low confidence, out of the learned methods'
#: domain, an answer without a confidence that the self-calibration does not confirm.
REASONS = (
    "registration",
    "overlap",
    "no_estimate",
    "motion",
    "relief",
    "low_confidence",
    "out_of_domain",
    "unconfirmed",
)
#: Share of the analysis frame's pixels valid after the registration's warp below which the map is too small to judge.
MIN_OVERLAP = 0.5
#: Scale of the self-calibration's Platt map, sigmoid(scale * logit(c) + shift): 1 with a shift of 0 is the identity.
SELFCAL_CONFIDENCE_SCALE = 1.0
#: Shift of the self-calibration's Platt map (see :data:`SELFCAL_CONFIDENCE_SCALE`).
SELFCAL_CONFIDENCE_SHIFT = 0.0
#: The eigen-space's class (no confidence) stands where the confident self-calibration's is at most this far.
EIGENSPACE_MAX_CLASS_DISAGREEMENT = 0
#: Out of domain where a learned method's class and the confident self-calibration's are more than this many apart.
MAX_CLASS_DISAGREEMENT = 1
#: Out of domain where their Delta_avg estimates differ by more than this share of the Delta_avg range.
MAX_DELTA_DISAGREEMENT = 0.25
#: Out of domain beyond this multiple of the largest texture distance of a training view (the checkpoint's).
TEXTURE_FACTOR = 2.0


# ------------------------------------------------------------------ the answer
def class_distance(a: str | None, b: str | None) -> int | None:
    """How many classes apart two labels are, R counting as class 0; None if either is missing."""
    if a is None or b is None:
        return None
    rank = {lab: (0 if lab == CLASS_LABELS[-1] else int(lab)) for lab in CLASS_LABELS}
    return abs(rank[a] - rank[b])


def domain_checks(
    res: dict, selfcal: dict | None, texture: torch.Tensor | None, extra: dict, *, cfg: LensdistConfig
) -> None:
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
        res["texture_distance"], res["texture_limit"] = d, TEXTURE_FACTOR * float(stats["spread"])
        res["_texture_far"] = d > res["texture_limit"]
    if selfcal is None:
        return
    conf = float(platt(selfcal["raw_confidence"], SELFCAL_CONFIDENCE_SCALE, SELFCAL_CONFIDENCE_SHIFT))
    usable = selfcal["delta_avg"] is not None and conf >= a.min_confidence and res["delta_avg"] is not None
    check = {"class": selfcal["estimated_class"], "delta_avg": selfcal["delta_avg"], "usable": usable, "agrees": True}
    if usable:
        gap = class_distance(res["estimated_class"], selfcal["estimated_class"])
        # whether there is distortion at all is asked first: R against a class disagrees
        is_r = [c == CLASS_LABELS[-1] for c in (res["estimated_class"], selfcal["estimated_class"])]
        # a class-R answer's Delta is the eigen-space's guess of its nearest class: the classes decide
        far = not any(is_r) and abs(res["delta_avg"] - selfcal["delta_avg"]) > MAX_DELTA_DISAGREEMENT * delta_top(
            "delta_avg", cfg
        )
        check["agrees"] = not ((gap is not None and gap > MAX_CLASS_DISAGREEMENT) or far or is_r[0] != is_r[1])
    if res.get("confidence") is None:  # the eigen-space: its class needs the self-calibration's confirmation
        gap = class_distance(res["estimated_class"], selfcal["estimated_class"]) if usable else None
        check["confirms"] = bool(check["agrees"] and gap is not None and gap <= EIGENSPACE_MAX_CLASS_DISAGREEMENT)
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
    if res["overlap"] < MIN_OVERLAP:
        out.append(
            f"the images overlap on {100 * res['overlap']:.0f} % only (< {100 * MIN_OVERLAP:.0f} %): "
            "too little to judge"
        )
    aligned = res["registration_ok"] and res["overlap"] >= MIN_OVERLAP  # else that is the reason given
    low = _low_confidence(res, cfg)
    if aligned and _relief(res, low):
        lo, hi = res["relief_delta_avg_interval"] or (float("nan"), float("nan"))
        out.append(
            f"cannot tell: relief: a plane + parallax model puts Delta_avg at {res['relief_delta_avg']:.2f} px "
            f"[{lo:.2f}, {hi:.2f}], the planar model at {res['planar_delta_avg']:.2f} px, in another class: the class "
            "depends on whether the scene is flat, which one pair cannot tell"
        )
    elif aligned and low:
        out.append("cannot tell from this pair: too little motion or texture to see the distortion (low confidence)")
    return out


def _reasons(res: dict, cfg: LensdistConfig, still: bool, low: bool, no_number: bool, unconfirmed: bool) -> list[str]:
    """The machine-readable reasons of a "cannot tell", one code each (:data:`REASONS`), the text in ``warnings``."""
    aligned = res["registration_ok"] and res["overlap"] >= MIN_OVERLAP
    found = {
        "registration": not res["registration_ok"],
        "overlap": res["registration_ok"] and res["overlap"] < MIN_OVERLAP,
        "no_estimate": aligned and no_number,
        "motion": still,
        "relief": aligned and _relief(res, low),
        "low_confidence": aligned and low and not _relief(res, low),
        "out_of_domain": aligned and not res["in_domain"],
        "unconfirmed": aligned and unconfirmed,
    }
    return [code for code in REASONS if found[code]]


def _low_confidence(res: dict, cfg: LensdistConfig) -> bool:
    """A confidence below ``analysis.min_confidence`` (none, for the eigen-space, is not low)."""
    return res["confidence"] is not None and res["confidence"] < cfg.analysis.min_confidence


def _relief(res: dict, low: bool) -> bool:
    """Whether relief is the reason of a "cannot tell".

    Relief found (``relief_found``), or a low confidence (``low``) where the planar and the plane
    + parallax answers fall in different classes (``relief_parted``: the confidence weighs both,
    and their disagreement is what lowered it).
    """
    return bool(res.get("relief_found")) or (low and bool(res.get("relief_parted")))


def decide(res: dict, cfg: LensdistConfig) -> None:
    """Set ``warnings``, ``in_domain``, ``cannot_tell``, ``class`` and ``class_max`` of one result, in place.

    "Cannot tell" where the confidence is low, there is no estimate, the pair is out of domain, an
    answer without a confidence is not confirmed by the self-calibration (:func:`domain_checks`),
    the self-calibration found relief (``relief_found``: its planar and plane + parallax answers
    fall in different classes; both stay in the result, as ``planar_delta_avg`` and
    ``relief_delta_avg`` with their intervals), or
    the views moved by less than ``analysis.min_motion_px`` (``motion_px``: the registration's
    mean displacement; every method, since none can see a distortion that cancels). Then
    ``class``, ``class_max``, ``delta_avg``, ``delta_max`` and ``distortion_type`` are None: no
    number that reads as an answer. ``estimated_class``, ``estimated_class_max``,
    ``estimated_delta_avg`` and ``estimated_delta_max`` keep the estimator's own output, for
    evaluation. A Delta_avg beyond the classes' range is class 4 with a warning saying so and
    ``beyond_class_range`` True. A failed registration or too small an overlap is the one reason
    given for a low confidence (not also "too little motion or texture"), and found relief is the
    one given for it. ``cannot_tell_reasons`` lists the reasons as codes of :data:`REASONS`
    (empty with an answer).
    """
    a = cfg.analysis
    check = res.get("selfcal_check")
    res["in_domain"] = bool(
        res["registration_ok"] and res["overlap"] >= MIN_OVERLAP and not res.get("_far", False)
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
    low = _low_confidence(res, cfg)
    no_number = res["delta_avg"] is None and res["delta_max"] is None
    unconfirmed = bool(check) and check.get("confirms") is False  # an answer without confidence (domain_checks)
    unsure = low or no_number or still or not res["in_domain"] or unconfirmed or bool(res.get("relief_found"))
    res["cannot_tell"] = bool(unsure)
    res["cannot_tell_reasons"] = _reasons(res, cfg, still, low, no_number, unconfirmed) if unsure else []
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
        # the interval was validated within the range only: beyond it, on real wide-angle pairs, eq. 4
        # cannot follow the lens and the intervals missed the truth (docs/method.md, section 10)
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
    resolution: s times Delta of (k2, k4) on a round(H / s) x round(W / s) frame.
    ``delta_avg_user_interval`` is ``delta_avg_interval`` carried to the user's whole frame along
    the lens's own scale: Delta over either frame is proportional to t for coefficients t (k2, k4),
    so the interval's ends are multiplied by the ratio of the two Deltas (docs/method.md,
    section 10). All None without an answer (``delta_avg`` None: no estimate, or "cannot tell").
    """
    none = ("k2_user", "k4_user", "opencv", "delta_avg_user_px", "delta_max_user_px", "delta_avg_user_interval")
    if res.get("k2") is None or res["delta_avg"] is None:
        return dict.fromkeys(none)
    k2_user, k4_user = user_coefficients(res["k2"], res["k4"], s)
    fh, fw = max(1, round(int(size[0]) / s)), max(1, round(int(size[1]) / s))
    off = pixel_offsets(res["k2"], res["k4"], fh, fw)  # one map for both Deltas
    d_user, iv = float(off.mean()) * s, res.get("delta_avg_interval")
    ratio = d_user / res["delta_avg"] if res["delta_avg"] > 0 else s  # no lens: the crop's scale alone
    return {
        "k2_user": k2_user,
        "k4_user": k4_user,
        "opencv": opencv_export(k2_user, k4_user, int(size[0]), int(size[1])),
        "delta_avg_user_px": d_user,
        "delta_max_user_px": float(off.max()) * s,
        "delta_avg_user_interval": None if iv is None else [iv[0] * ratio, iv[1] * ratio],
    }
