"""A camera's lens distortion from feature matches between views of a plane (or a turning camera).

Where the scene is a plane (a wall, a floor, a document, a seabed seen from high up) or the
camera only turns, two undistorted views are one homography apart, so a shared radial lens and
one homography per pair explain every correct match. This is the direct path's model
(:mod:`~lensdist_torch.calibration.direct`) fitted to COLMAP's feature matches instead of
intensities: it registers views that are far apart (the direct path's start, a translation, does
not reach them) and follows lenses beyond eq. 4's two terms. docs/method.md, section 12.

The lens: the ideal point of a pixel p is

    p_ideal = c + (p - c) (1 + a_1 r^2 + a_2 r^4 + ... + a_n r^(2n)),   r = |p - c| / R,

c the distortion centre (the frame centre, or free: step 4), R the frame's half diagonal; with
n = 2 and c the frame centre this is eq. 4 (a_1 = k2 R^2, a_2 = k4 R^4).

1. **Matches**: COLMAP's verified matches of the pairs with at least ``PLANAR_MIN_MATCHES``, each
   pair's thinned to ``PLANAR_PAIR_MATCHES`` (:mod:`~lensdist_torch.calibration.matches`).
2. **Start**: a_1 over ``PLANAR_SCAN_RANGE`` (the other terms 0); for each, the homography of
   each of the ``PLANAR_SCAN_PAIRS`` pairs with the most matches by COLMAP's LO-RANSAC
   (``pycolmap.estimate_homography_matrix``, ``PLANAR_RANSAC_PX``) on the undistorted points; the
   a_1 with the most inliers starts, with every pair's homography and inliers there. On repetitive
   texture (a chessboard) half of the epipolar-verified matches are wrong, and only the homography
   tells them apart.
3. **Fit**: Levenberg-Marquardt on the lens and every pair's homography together (the pairs'
   8 x 8 blocks eliminated by the Schur complement), on the symmetric transfer error divided by
   the lens's local scale (so, about, in the image's pixels); twice: the matches within
   ``PLANAR_INLIER_PX`` of the first fit are the inliers of the second (the centre at the frame's:
   a free centre would bend to take parallax in).
4. **The models by their evidence**: n = 1 .. ``planar_terms``, each with the centre at the
   frame's and free (a candidate while within ``PLANAR_CENTRE_MAX`` of the half diagonal from the
   frame centre), on the same inliers, each fitted again without each of ``jackknife_blocks``
   contiguous blocks of frames and scored on predicting the pairs it left out; pseudo-BMA+ weights
   (:mod:`~lensdist_torch.calibration.planar_evidence`). The model of most held-out evidence among
   those the matches determine answers. A real wide-angle lens's centre is off the frame's by a
   few % of the half diagonal: a lens of 100 px then bends the frame-centred model's lines by px.
5. **Interval**: each model's posterior (the fit's covariance), widened by the dispersion or to
   its folds' jackknife where that scatters more, mixed by the weights
   (:func:`~lensdist_torch.calibration.multiview_evidence.mixed_intervals`). No class when the
   interval spans two classes at the paper's frame (the rule every path shares,
   :func:`~lensdist_torch.calibration.sequence_class.interval_class`), when fewer than
   ``PLANAR_MIN_PAIRS`` pairs keep their inliers, or when under ``PLANAR_MIN_INLIER_SHARE`` of the
   verified matches fit: the scene is not a plane and the camera did not only turn.
6. **In the user's pixels and OpenCV's terms**: Delta over every pixel of the frame where the
   lens map is monotone; eq. 4's (k2, k4) fitted to the map (``eq4_fit_error_px``); OpenCV's
   K and dist_coeffs fitted to it, K's principal point at the distortion centre
   (:func:`~lensdist_torch.geometry.opencv_model.opencv_camera_from_map`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from lensdist_torch.calibration.lens_answer import LensAnswer
from lensdist_torch.calibration.matches import PLANAR_MIN_MATCHES, PLANAR_PAIR_MATCHES, PlanarMatches, thin_matches
from lensdist_torch.calibration.multiview_evidence import mixed_intervals, posterior_std
from lensdist_torch.calibration.planar_evidence import score_models
from lensdist_torch.calibration.planar_model import (
    bending_halfwidth,
    fit_lens_and_homographies,
    lens_deltas,
    lens_of,
    pair_homographies,
    split_lens,
    transfer_errors,
    transfer_residuals,
)
from lensdist_torch.calibration.pooling import jackknife_std
from lensdist_torch.calibration.sequence_class import interval_class
from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.config.checks import or_defaults
from lensdist_torch.geometry.distortion import distortion_center, fit_eq4, paper_frame_delta_avg
from lensdist_torch.geometry.frame import half_diagonal
from lensdist_torch.geometry.opencv_model import map_grid_step, opencv_camera_from_map
from lensdist_torch.geometry.radial_lens import lens_factor, lens_ideal_points

__all__ = ["PLANAR_CENTRE_MAX", "PLANAR_INLIER_PX", "PLANAR_ITERATIONS", "PLANAR_MIN_INLIER_SHARE", "PLANAR_MIN_PAIRS",
           "PLANAR_RANSAC_PX", "PLANAR_SCAN_PAIRS", "PLANAR_SCAN_RANGE", "PLANAR_SCAN_STEPS", "PlanarCalibration",
           "delta_avg_where", "self_calibrate_planar"]

#: Step 2: the first radial term's start values, from and to (normalised frame), ...
PLANAR_SCAN_RANGE = (-0.3, 1.5)
#: ... this many, evenly spaced, ...
PLANAR_SCAN_STEPS = 19
#: ... on this many pairs at most, those with the most matches (a video's 60 mapped frames give about 700).
PLANAR_SCAN_PAIRS = 60
#: Step 2: LO-RANSAC's threshold (px) for each pair's homography at a start value.
PLANAR_RANSAC_PX = 2.0
#: Step 3: a match within this transfer error (px) of the first fit is an inlier.
PLANAR_INLIER_PX = 3.0
#: Fewer counting pairs: the homography model has no answer.
PLANAR_MIN_PAIRS = 4
#: Levenberg-Marquardt iterations at most per fit.
PLANAR_ITERATIONS = 100
#: Step 4: a free distortion centre is a candidate within this fraction of the half diagonal from the frame's.
PLANAR_CENTRE_MAX = 0.1
#: Step 5: under this share of the verified matches on one homography per pair: not a plane (nor a turning camera).
PLANAR_MIN_INLIER_SHARE = 0.5


@dataclass(frozen=True, kw_only=True)
class PlanarCalibration(LensAnswer):
    """The result of :func:`self_calibrate_planar`: the lens answer and the homography model's diagnostics.

    The core fields are :class:`~lensdist_torch.calibration.lens_answer.LensAnswer`'s: Delta_avg
    and Delta_max over the pixels where the lens map is monotone, with ``confidence`` intervals;
    (k2, k4) eq. 4 fitted to the lens map.

    Attributes:
        coefficients: a_1 .. a_n of the chosen radial model (module docstring).
        terms: n.
        model: its name ("planar-n", "planar-n-centre" where the centre is free).
        centre: the distortion centre (x, y) in pixels (the frame centre unless free).
        eq4_fit_error_px: RMS error (px) of eq. 4's fit to the lens map.
        invertible_fraction: the share of the frame's pixels where the map is monotone.
        bending_halfwidth_px: how straight the map makes lines: the jackknife's ``confidence``
            half-width of its bending (px, RMS; no homography takes the bending away).
        matched_fraction: the share of the frame that the inliers reach.
        pairs: the pairs fitted.
        inliers: the inlier matches.
        matches: the verified matches (at most ``PLANAR_PAIR_MATCHES`` a pair).
        inlier_share: inliers over the counted pairs' matches.
        reprojection_px: the inliers' RMS transfer error (px).
        models: per model its evidence ``weight``, ``heldout_rms_px`` (held-out pairs' transfer
            error), BIC, Delta_avg and Delta_max with their posterior stds, the lens's ``covariance``,
            RMS, coefficients and centre, and its jackknife (``jackknife_std_px``;
            ``jackknife_coefficients``, ``jackknife_centres``: the folds' lenses).
        jackknife: the answer model's leave-a-block-out Delta_avg values (px).
        dispersion: how much more the folds scatter than the posteriors allow (>= 1): the scale of
            the posteriors' variances and of the log evidence.
        opencv: OpenCV's camera fitted to the map, 5 coefficients (``camera_matrix``,
            ``dist_coeffs`` and the fit's errors, as
            :func:`~lensdist_torch.geometry.opencv_model.opencv_export` gives them).
        opencv_rational: the same with 8 coefficients.
        guided: what guided matching found and the first fit's figures, where the fit is on guided
            matches (:mod:`~lensdist_torch.calibration.guided_matching`); None otherwise.
        refined: where the matches were refined (:mod:`~lensdist_torch.calibration.match_refinement`),
            what the refinement kept and the fit's figures before it; None otherwise.

    Example:
        >>> import dataclasses
        >>> [f.name for f in dataclasses.fields(PlanarCalibration)][8:12]
        ['coefficients', 'terms', 'model', 'centre']
    """

    coefficients: list
    terms: int
    model: str
    centre: list
    eq4_fit_error_px: float
    invertible_fraction: float
    bending_halfwidth_px: float
    matched_fraction: float
    pairs: int
    inliers: int
    matches: int
    inlier_share: float
    reprojection_px: float
    models: dict
    jackknife: list
    dispersion: float
    opencv: dict
    opencv_rational: dict
    guided: dict | None = None
    refined: dict | None = None


# ------------------------------------------------------------------ the start
def _ransac(matches: PlanarMatches, a: torch.Tensor, size: tuple[int, int], cfg: MultiViewConfig, pairs=None):
    """Every pair's homography (normalised frame, (P, 8)) and inliers ((N,) bool) under the lens ``a`` (step 2).

    ``pairs``: only these pairs (indices), the others keep the identity and no inlier.
    """
    h, w = size
    big_r = half_diagonal(h, w)
    c = matches.x1.new_tensor(distortion_center(h, w))
    u1, u2 = lens_ideal_points(matches.x1, a, h, w), lens_ideal_points(matches.x2, a, h, w)
    s = torch.tensor([[big_r, 0, c[0]], [0, big_r, c[1]], [0, 0, 1]], dtype=torch.float64)
    hs, inliers = torch.zeros(len(matches.first), 8, dtype=torch.float64), torch.zeros(len(u1), dtype=torch.bool)

    def threshold(idx: torch.Tensor) -> float:  # PLANAR_RANSAC_PX in the image's pixels, at the lens's mean scale
        scale = float(lens_factor(((matches.x2[idx] - c) / big_r).pow(2).sum(-1, keepdim=True), a).mean())
        return PLANAR_RANSAC_PX * max(scale, 1e-3)

    which = range(len(matches.first)) if pairs is None else pairs.tolist()
    for p, idx, hm, mask in pair_homographies(u1, u2, matches.pair, which=which, max_error=threshold, seed=cfg.seed):
        if hm is None:
            hs[p] = torch.tensor([1.0, 0, 0, 0, 1, 0, 0, 0], dtype=torch.float64)
            continue
        m = torch.linalg.solve(s, hm @ s)  # pixels -> normalised frame
        hs[p] = (m / m[2, 2]).reshape(-1)[:8]
        if int(mask.sum()) >= PLANAR_MIN_MATCHES:  # fewer: the pair does not count
            inliers[idx] = mask
    return hs, inliers


def _start(matches: PlanarMatches, size, cfg: MultiViewConfig, terms: int):
    """The scan of a_1 (step 2): the lens, the pairs' homographies and the inliers with the most inliers."""
    lo, hi = PLANAR_SCAN_RANGE
    counts = torch.zeros(len(matches.first), dtype=torch.long).index_add_(
        0, matches.pair, torch.ones_like(matches.pair)
    )
    scanned = torch.sort(-counts, stable=True).indices[:PLANAR_SCAN_PAIRS]  # the pairs with the most matches
    best = None
    for i in range(PLANAR_SCAN_STEPS):
        a = torch.zeros(terms, dtype=torch.float64)
        a[0] = lo + (hi - lo) * i / max(PLANAR_SCAN_STEPS - 1, 1)
        n = int(_ransac(matches, a, size, cfg, scanned)[1].sum())
        if best is None or n > best[1]:
            best = (a, n)
    return (best[0], *_ransac(matches, best[0], size, cfg))


# ------------------------------------------------------------------ Delta and the exports
def _eq4_fit(a: torch.Tensor, centre: list[float], size: tuple[int, int], dl: dict) -> tuple[float, float, float]:
    """Eq. 4's (k2, k4) (about the frame centre) fitted to the lens map where it inverts, and the RMS error (px)."""
    p = dl["points"][dl["ok"]]
    return fit_eq4(p, lens_ideal_points(p, a, *size, centre=centre), *size)


def _stays(theta: torch.Tensor, n: int) -> bool:
    """Whether the lens ``theta``'s centre, where free, lies within :data:`PLANAR_CENTRE_MAX` of the frame centre."""
    d = split_lens(theta, n)[1]
    return d is None or float(d.norm()) <= PLANAR_CENTRE_MAX


def _fit_models(theta0: torch.Tensor, hs, v1, v2, pair, inl, size, cfg: MultiViewConfig, step: int):
    """Step 4: the models n = 1 .. terms, the centre fixed and free, from ``theta0`` (terms,) on the inliers ``inl``.

    Returns:
        (table, fits).
    """
    h, w = size
    big_r = half_diagonal(h, w)
    table, fits = {}, {}
    n_obs = 4 * int(inl.sum())
    n_info = 2 * int(inl.sum())  # BIC's count: a match's two transfer errors measure one misfit (4 residuals, 2 obs.)
    for n in range(1, cfg.planar_terms + 1):
        for free in (False, True) if PLANAR_CENTRE_MAX > 0 else (False,):
            start = torch.cat([theta0[:n], theta0.new_zeros(2)]) if free else theta0[:n].clone()
            tn, hn = fit_lens_and_homographies(start, hs.clone(), v1, v2, pair=pair, w=inl.double(),
                                               iterations=PLANAR_ITERATIONS, terms=n)
            if not _stays(tn, n):
                continue  # a centre that far off is no lens's: not a candidate
            r = transfer_residuals(tn, hn, v1, v2, terms=n, pair=pair)[inl] * big_r
            rss = float((r * r).sum())
            dl = lens_deltas(tn, n, size, step)
            name = f"planar-{n}" + ("-centre" if free else "")
            table[name] = {
                "bic": n_info * math.log(max(rss, 1e-300) / max(n_obs, 1)) + (n + 2 * free) * math.log(max(n_info, 1)),
                "delta_avg_px": dl["delta_avg_px"],
                "delta_max_px": dl["delta_max_px"],
                "reprojection_px": math.sqrt(rss / max(n_obs, 1)),
                **dict(zip(("coefficients", "centre"), lens_of(tn, n, size))),
            }
            fits[name] = (tn, hn, dl, n)
    return table, fits


def delta_avg_where(res, points: torch.Tensor, height: int, width: int, *, settings: LensdistConfig | None = None):
    """The answer's Delta_avg (px) over other ``points`` (M, 2), with its interval.

    ``points``: say, where a reference calibration inverts. The same rule as the answer's own: each
    model's figure, its posterior (its ``covariance``) and its jackknife lenses measured on those
    pixels, mixed by the models' weights
    (:func:`~lensdist_torch.calibration.multiview_evidence.mixed_intervals`). ``res``: a
    :class:`PlanarCalibration` or its dict (the JSON's ``planar`` block).

    Returns:
        (value, (low, high)).

    Example:
        >>> one = {"coefficients": [0.1], "centre": [4.5, 3.5], "weight": 1.0, "covariance": [[0.0]],
        ...        "jackknife_coefficients": [[0.1], [0.1]], "jackknife_centres": [[4.5, 3.5], [4.5, 3.5]]}
        >>> r = {"coefficients": [0.1], "centre": [4.5, 3.5], "models": {"planar-1": one}, "dispersion": 1.0}
        >>> value, (lo, hi) = delta_avg_where(r, torch.tensor([[0.0, 0.0]], dtype=torch.float64), 8, 10)
        >>> round(value, 4), round(hi - lo, 9)  # a corner at r = 1: 10 % of 5.7 px; no posterior, replicates alike
        (0.5701, 0.0)
    """
    st = or_defaults(settings, LensdistConfig, "settings")
    r = res.to_dict() if isinstance(res, PlanarCalibration) else res

    def there(a, centre) -> float:
        return float((lens_ideal_points(points, a, height, width, centre=centre) - points).norm(dim=-1).mean())

    rows = []
    for v in r["models"].values():
        coef, centre, free = v["coefficients"], v["centre"], len(v.get("covariance") or []) > len(v["coefficients"])
        n = len(coef)

        def measure(p, n=n, free=free, centre=centre):
            return (there(list(p[:n]), list(p[n:]) if free else centre),)

        jk = [there(a, c) for a, c in zip(v["jackknife_coefficients"], v["jackknife_centres"])]
        cov = v.get("covariance")
        params = list(coef) + (list(centre) if free else [])
        std = posterior_std(params, list(range(len(params))), None if cov is None else np.asarray(cov), measure)[0]
        rows.append({"delta_avg_px": there(coef, centre), "delta_avg_std_px": std, "delta_max_px": 0.0,
                     "delta_max_std_px": 0.0, "jackknife_std_px": jackknife_std(jk)})
    interval = mixed_intervals(rows, [v["weight"] for v in r["models"].values()], dispersion=r["dispersion"],
                               checked=[True] * len(rows), confidence=st.calibration.confidence)[0]
    return there(r["coefficients"], r["centre"]), interval


# ------------------------------------------------------------------ the estimator
def self_calibrate_planar(
    matches: PlanarMatches,
    image_size: tuple[int, int],
    *,
    config: MultiViewConfig | None = None,
    settings: LensdistConfig | None = None,
    start=None,
    plane_share: float | None = None,
) -> PlanarCalibration:
    """The camera's distortion from matches between views of a plane (module docstring, steps 2-6).

    Args:
        matches: :class:`PlanarMatches` (:func:`read_verified_matches`), in the user's pixels.
        image_size: the frames' (H, W).
        config: :class:`~lensdist_torch.config.MultiViewConfig` (the folds' ``jackknife_blocks``, ``seed``).
        settings: the library's config (the coverage ``calibration.confidence``, the class rule, the frame).
        start: a lens's a_1 .. a_n to start from instead of the scan (step 2), or None.
        plane_share: the share of verified matches on one homography per pair, where ``matches``
            cannot tell it (guided matches: :mod:`~lensdist_torch.calibration.guided_matching`);
            the "not a plane" rule and ``inlier_share`` take it. None: measured on ``matches``.

    Returns:
        :class:`PlanarCalibration`.

    Example:
        >>> none = torch.zeros(0, 2, dtype=torch.float64)
        >>> m = PlanarMatches(none, none, torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long),
        ...                   torch.zeros(0, dtype=torch.long), ("a.png", "b.png"))
        >>> self_calibrate_planar(m, (240, 320)).reason  # fitted figures: tests/calibration/test_planar_features.py
        'too few matched pairs: 0 of at least 4'
    """
    cfg, st = or_defaults(config, MultiViewConfig), or_defaults(settings, LensdistConfig, "settings")
    matches = thin_matches(matches, PLANAR_PAIR_MATCHES)
    h, w = (int(v) for v in image_size)
    big_r = half_diagonal(h, w)
    step = map_grid_step(h, w)
    c = matches.x1.new_tensor(distortion_center(h, w))
    v1, v2 = (matches.x1 - c) / big_r, (matches.x2 - c) / big_r

    def fail(reason: str, a=None, inl: int = 0, models=None) -> PlanarCalibration:
        nan = math.nan
        return PlanarCalibration(
            coefficients=[] if a is None else list(a), terms=0 if a is None else len(a), model="",
            centre=list(distortion_center(h, w)), k2_user=nan, k4_user=nan, eq4_fit_error_px=nan,
            delta_avg_user_px=nan, delta_avg_user_interval=(nan, nan), delta_max_user_px=nan,
            delta_max_user_interval=(nan, nan), invertible_fraction=0.0, bending_halfwidth_px=nan,
            matched_fraction=0.0, class_label=None, reason=reason, pairs=len(matches.first), inliers=inl,
            matches=len(matches.pair), inlier_share=nan, reprojection_px=nan, models=models or {}, jackknife=[],
            dispersion=nan, opencv={}, opencv_rational={})

    if len(matches.first) < PLANAR_MIN_PAIRS:
        return fail(f"too few matched pairs: {len(matches.first)} of at least {PLANAR_MIN_PAIRS}")
    terms = cfg.planar_terms
    if start is None:
        theta, hs, inl = _start(matches, (h, w), cfg, terms)
    else:
        theta = torch.zeros(terms, dtype=torch.float64)
        theta[: min(terms, len(start))] = torch.as_tensor(list(start)[:terms], dtype=torch.float64)
        hs, inl = _ransac(matches, theta, (h, w), cfg)
    for _ in range(2):  # fit on the inliers, then again on the matches the fit explains (the centre fixed: a free one
        # would bend to take parallax in, and "not a plane" would go unseen)
        theta, hs = fit_lens_and_homographies(theta, hs, v1, v2, pair=matches.pair, w=inl.double(),
                                              iterations=PLANAR_ITERATIONS, terms=terms)
        inl = transfer_errors(theta, hs, v1, v2, pair=matches.pair, big_r=big_r, terms=terms) < PLANAR_INLIER_PX
        per_pair = torch.zeros(len(matches.first), dtype=torch.long).index_add_(0, matches.pair, inl.long())
        inl &= (per_pair >= PLANAR_MIN_MATCHES)[matches.pair]
    kept = torch.zeros(len(matches.first), dtype=torch.long).index_add_(0, matches.pair, inl.long())
    good_pairs = int((kept >= PLANAR_MIN_MATCHES).sum())
    counted = (kept >= PLANAR_MIN_MATCHES)[matches.pair]  # the matches of the pairs that count
    share = float(inl[counted].double().mean()) if bool(counted.any()) else 0.0
    share = share if plane_share is None else plane_share
    table, fits = _fit_models(theta, hs, v1, v2, matches.pair, inl, (h, w), cfg, step)
    if good_pairs < PLANAR_MIN_PAIRS:
        return fail(f"too few pairs fit one homography: {good_pairs} of at least {PLANAR_MIN_PAIRS}",
                    lens_of(theta, terms, (h, w))[0], int(inl.sum()), table)
    coverage = st.calibration.confidence
    scores, answer = score_models(fits, matches, v1, v2, inliers=inl, blocks=cfg.jackknife_blocks, size=(h, w),
                                  step=step, iterations=PLANAR_ITERATIONS, confidence=coverage, seed=cfg.seed,
                                  stays=_stays)
    table = {m: table[m] for m in scores}
    for m, sc in scores.items():
        lenses = [lens_of(tj, fits[m][3], (h, w)) for tj in sc["jackknife_thetas"]]
        table[m].update({k: sc[k] for k in ("weight", "elpd", "delta_avg_std_px", "delta_max_std_px",
                                            "jackknife_std_px", "heldout_rms_px", "covariance")},
                        jackknife_coefficients=[v[0] for v in lenses], jackknife_centres=[v[1] for v in lenses])
    # the most held-out evidence among the models the matches determine (near-twins split weight, not elpd)
    best = max((m for m in table if table[m]["weight"] > 0), key=lambda m: table[m]["elpd"])
    theta, hs, dl, n = fits[best]
    a, centre = lens_of(theta, n, (h, w))
    jk_t = scores[best]["jackknife_thetas"]
    intervals = answer["intervals"]
    seen = torch.cat([matches.x1[inl], matches.x2[inl]]).unique(dim=0)
    bending, reach = bending_halfwidth(theta, jk_t, n=n, size=(h, w), dl=dl, confidence=coverage, seen=seen)
    k2u, k4u, fit_err = _eq4_fit(a, centre, (h, w), dl)
    label, reason = None, ""
    if share < PLANAR_MIN_INLIER_SHARE:
        reason = (
            f"not a plane: one homography per pair explains {100 * share:.0f} % of its pair's verified matches "
            f"(at least {100 * PLANAR_MIN_INLIER_SHARE:.0f} % needed)"
        )
    else:
        paper = paper_frame_delta_avg(k2u, k4u, (h, w), st) if math.isfinite(k2u) else math.nan
        label, reason = interval_class(paper, dl["delta_avg_px"], intervals[0], st)
    cams = [
        opencv_camera_from_map(
            lambda p: lens_ideal_points(p, a, h, w, centre=centre), h, w, model=m, step=step, centre=centre
        )
        for m in ("standard", "rational")
    ]
    standard, rational = (
        {k: (v.tolist() if isinstance(v, torch.Tensor) else v) for k, v in c._asdict().items() if k != "model"}
        for c in cams
    )
    return PlanarCalibration(
        coefficients=a,
        terms=n,
        model=best,
        centre=centre,
        k2_user=k2u,
        k4_user=k4u,
        eq4_fit_error_px=fit_err,
        delta_avg_user_px=dl["delta_avg_px"],
        delta_avg_user_interval=intervals[0],
        delta_max_user_px=dl["delta_max_px"],
        delta_max_user_interval=intervals[1],
        invertible_fraction=dl["invertible_fraction"],
        bending_halfwidth_px=bending,
        matched_fraction=reach,
        class_label=label,
        reason=reason,
        pairs=good_pairs,
        inliers=int(inl.sum()),
        matches=len(matches.pair),
        inlier_share=share,
        reprojection_px=table[best]["reprojection_px"],
        models=table,
        jackknife=scores[best]["jackknife_avg"],
        dispersion=answer["dispersion"],
        opencv=standard,
        opencv_rational=rational,
    )
