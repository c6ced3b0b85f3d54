"""The lens models of one reconstruction: each one's posterior, their evidence on held-out frames, one answer.

Every camera model of ``multiview.models`` is fitted by bundle adjustment on the same tracks
(:mod:`~lensdist_torch.calibration.multiview`). What the data say about each, and which to believe:

* **Its posterior.** The covariance of the camera's intrinsics from the adjustment's normal
  equations, the 3-D points and the poses marginalised (COLMAP's Schur complement,
  ``pycolmap.estimate_ba_covariance``; the gauge fixed by two poses), scaled by the residual
  variance RSS / (2 n - 3 points - 6 frames - k): :func:`camera_covariance`. It reaches Delta_avg and
  Delta_max over the frame through their central-difference gradient in the intrinsics
  (:func:`posterior_std`). A direction the data do not constrain (relief under translation
  alone trades with the distortion) is a large variance here, measured, not a rule on the motion.
* **Its evidence.** Frames are held out in contiguous blocks (the folds); the model is adjusted
  without them, each held-out frame is posed again on the remaining 3-D points with that camera
  held (``pycolmap.refine_absolute_pose``) and its observations are predicted
  (:func:`heldout_squared_errors`). Each held-out frame's log predictive density under a normal
  noise whose variance the fold's models share, each squared error capped at ``CAP`` times the
  fold's median over all models (a mismatched track speaks for no model):
  :func:`unit_log_evidence`. A richer model that only fits the noise predicts held-out frames no
  better, whatever BIC says on thousands of tracks.
* **Their weights.** Pseudo-BMA+ (Yao et al. 2018): the held-out frames' log densities resampled
  by a Bayesian bootstrap (Dirichlet(1, ..., 1) weights over the frames), the models' softmax
  averaged over the draws (:func:`evidence_weights`). A model that predicts every frame better
  takes the weight; where the lead changes from frame to frame the weight is shared.
* **Their dispersion.** The delete-a-block fits of the folds are each model's jackknife. Where
  they scatter more than the posterior allows (the reprojection errors are not independent: a
  pure pan trades the scene's curvature with the distortion, and its tracks hold the wrong
  balance together), the median ratio of the two variances, at least 1, scales both the
  posteriors' variances and the log evidence (:func:`dispersion`).
* **One answer.** The model of most weight is the answer (its camera is what ``undistort``
  applies); the interval is the central ``confidence`` interval of the models' posteriors mixed by
  their weights (:func:`mixture_interval`), so models that fit as well and disagree widen it.

The jackknife is the posterior's check, not the interval: it sets the dispersion and is reported
beside the posterior.

References:
    Y. Yao, A. Vehtari, D. Simpson, A. Gelman, "Using stacking to average Bayesian predictive
    distributions", Bayesian Analysis 13(3), 2018 (pseudo-BMA+).
    L. Pace, A. Salvan, N. Sartori, "Adjusting composite likelihood ratio statistics", Statistica
    Sinica 21(1), 2011 (scaling a misspecified likelihood by the ratio of its variances).
    B. Triggs, P. McLauchlan, R. Hartley, A. Fitzgibbon, "Bundle adjustment: a modern synthesis",
    Vision Algorithms: Theory and Practice, 2000 (the covariance of the adjusted parameters).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from statistics import NormalDist, median

import numpy as np

__all__ = [
    "fold_ranges",
    "checked_scale",
    "CAP",
    "NO_GRADIENT",
    "camera_covariance",
    "posterior_std",
    "dispersion",
    "heldout_squared_errors",
    "heldout_rms",
    "unit_log_evidence",
    "evidence_weights",
    "mixture_interval",
    "weigh_models",
    "mixed_intervals",
]

#: A held-out squared error counts at most this many times its fold's median (over every model).
CAP = 16.0
#: A central difference smaller than this (px of Delta per unit of a parameter) is no dependence: a camera without
#: distortion has Delta 0 whatever its focal length, known even where the adjustment does not determine the camera.
NO_GRADIENT = 1e-9


def fold_ranges(n: int, blocks: int) -> list[range]:
    """The folds of ``n`` frames in recording order: ``min(blocks, n)`` contiguous blocks of their indices.

    Example:
        >>> [list(r) for r in fold_ranges(5, 2)]
        [[0, 1], [2, 3, 4]]
    """
    b = min(blocks, n)
    return [range(g * n // b, (g + 1) * n // b) for g in range(b)]


def camera_covariance(rec, camera_id: int, rss: float, observations: int) -> np.ndarray | None:
    """The covariance (k, k) of a reconstruction's variable intrinsics, in their units squared, or None.

    ``rec`` is the adjusted reconstruction with one camera ``camera_id`` whose principal point is
    held; ``rss`` (px^2) and ``observations`` its reprojection errors' sum of squares and count.
    The normal equations' inverse (unit residual variance) times RSS over the residual degrees of
    freedom. None where COLMAP finds the camera not determined (a rank-deficient Schur complement;
    COLMAP logs why, which the caller may silence).
    """
    import pycolmap as pc

    options = pc.BundleAdjustmentOptions()
    options.refine_principal_point = False
    config = pc.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(pc.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pc.create_default_ceres_bundle_adjuster(options, config, rec)
    cov_options = pc.BACovarianceOptions()
    cov_options.params = pc.BACovarianceOptionsParams.ALL
    cov = pc.estimate_ba_covariance(cov_options, rec, adjuster)
    if cov is None:
        return None
    c = cov.get_other_params_cov(rec.cameras[camera_id].params)
    k = c.shape[0]
    dof = 2 * observations - 3 * rec.num_points3D() - 6 * rec.num_reg_images() - k
    if dof <= 0 or not np.isfinite(c).all():
        return None
    return np.asarray(c) * rss / dof


def posterior_std(params: Sequence[float], variable: Sequence[int], cov: np.ndarray | None,
                  measure: Callable[[np.ndarray], tuple[float, ...]]) -> list[float]:
    """The posterior std of each figure ``measure(params)`` returns, by its central-difference gradient.

    ``variable``: the indices of ``params`` that ``cov`` (k, k) covers, in its order; None as
    ``cov`` (the camera is not determined): infinite, except for a figure no variable moves
    (:data:`NO_GRADIENT`), whose std is 0.

    Example:
        >>> import numpy as np
        >>> posterior_std([2.0, 5.0], [0], np.array([[0.01]]), lambda p: (3 * p[0], p[0] ** 2 + p[1]))
        [0.3, 0.4]
        >>> posterior_std([2.0, 5.0], [0], None, lambda p: (3 * p[0], 0.0 * p[0]))
        [inf, 0.0]
    """
    p0 = np.asarray(params, dtype=float)
    grads = []
    for i in variable:
        h = 1e-4 * max(abs(p0[i]), 1e-3)
        up, down = p0.copy(), p0.copy()
        up[i], down[i] = p0[i] + h, p0[i] - h
        grads.append((np.asarray(measure(up)) - np.asarray(measure(down))) / (2 * h))
    g = np.stack(grads)  # (k, figures)
    if cov is None:  # a figure that no variable moves (a camera without distortion: Delta 0) is still known
        return [0.0 if np.all(np.abs(col) < NO_GRADIENT) else math.inf for col in g.T]
    var = np.einsum("if,ij,jf->f", g, cov, g)
    return [round(float(math.sqrt(max(v, 0.0))), 12) for v in var]


def dispersion(posterior_stds: Sequence[float], jackknife_stds: Sequence[float]) -> float:
    """How much more the frames scatter than the posterior allows: the median of (jackknife / posterior)^2, at least 1.

    Over the models whose posterior std is finite and positive; 1 where there is none. The
    likelihood of reprojection errors assumes them independent; where blocks of frames move the
    estimate more than that allows (errors correlated along tracks, a valley that trades relief
    with distortion), both the posteriors' variances and the log evidence are scaled by it (the
    magnitude adjustment of a composite likelihood).

    Example:
        >>> round(dispersion([0.26, 0.12, 0.27, 1.26], [1.11, 0.14, 1.05, 1.50]), 2)  # a pan: 1.36, 1.42, 15.12, 18.23
        8.27
        >>> dispersion([0.04, float("inf")], [0.03, 0.3])  # a scene the posterior describes: no adjustment
        1.0
    """
    r = [
        (j / p) ** 2 for p, j in zip(posterior_stds, jackknife_stds) if math.isfinite(p) and p > 0 and math.isfinite(j)
    ]
    return round(max(1.0, median(r)), 12) if r else 1.0


def checked_scale(dispersion: float, posterior_std: float, jackknife_std: float) -> float:
    """The factor on one model's posterior variance: ``dispersion``, or more where its own jackknife scatters more.

    The jackknife is the check of the posterior, not the interval; where the check fails for a
    model (its folds' fits scatter beyond the dispersion-scaled posterior: a camera whose Delta the
    tracks leave to extrapolation), that model's variance becomes the jackknife's. A posterior
    that is not finite or not positive stays as it is.

    Example:
        >>> round(checked_scale(2.0, 1.0, 1.2), 2), round(checked_scale(2.0, 1.0, 3.0), 2)
        (2.0, 9.0)
    """
    if not (math.isfinite(posterior_std) and posterior_std > 0 and math.isfinite(jackknife_std)):
        return dispersion
    return max(dispersion, (jackknife_std / posterior_std) ** 2)


def heldout_squared_errors(train, camera, full, frame_ids: Sequence[int]) -> list[np.ndarray]:
    """Squared reprojection errors (px^2) of the held-out frames ``frame_ids`` under ``camera``, ``train``'s.

    ``full`` holds every frame (their observations and starting poses), ``train`` the adjustment
    without them, ``camera`` its one camera. Each held-out frame is posed again on its observations
    of ``train``'s 3-D points (at least 6), the camera held; per frame one squared error per
    observation (a frame with too few such observations is left out).
    """
    import pycolmap as pc

    out = []
    for frame_id in frame_ids:
        image = full.image(frame_id)
        obs = [(p.xy, train.point3D(p.point3D_id).xyz) for p in image.points2D
               if p.has_point3D() and train.exists_point3D(p.point3D_id)]
        if len(obs) < 6:
            continue
        xy, xyz = np.array([o[0] for o in obs]), np.array([o[1] for o in obs])
        refined = pc.refine_absolute_pose(image.cam_from_world(), xy, xyz, np.ones(len(xy), dtype=bool), camera)
        pose = refined["cam_from_world"] if refined else image.cam_from_world()
        err = np.sum((camera.img_from_cam(pose * xyz) - xy) ** 2, axis=1)
        out.append(np.where(np.isfinite(err), err, np.inf))
    return out


def heldout_rms(errors: Sequence[np.ndarray]) -> float:
    """RMS (px) of the finite squared errors of held-out frames (a point behind a frame's camera has none); NaN if none.

    Example:
        >>> import numpy as np
        >>> heldout_rms([np.array([1.0, 3.0]), np.array([np.inf])]), heldout_rms([])
        (1.4142135623730951, nan)
    """
    e = np.concatenate(errors) if len(errors) else np.zeros(0)
    e = e[np.isfinite(e)]
    return math.sqrt(float(e.mean())) if e.size else math.nan


def unit_log_evidence(errors: Sequence[Sequence[Sequence[np.ndarray]]]) -> np.ndarray:
    """Per model and held-out frame the log predictive density of its observations (M, frames).

    ``errors[m][k][f]``: model m's squared errors (px^2) on frame f of fold k (the same
    observations for every model). Each fold has one noise variance for all models, half the
    mean squared error over them all (two coordinates); each squared error is capped at ``CAP``
    times the fold's median over all models, and a frame's density is the sum over its
    observations of the 2-D normal's: -log(2 pi s^2) - e^2 / (2 s^2). The models differ by
    their errors alone; frames are the units the weights resample.

    Example:
        >>> import numpy as np
        >>> e = unit_log_evidence([[[np.full(4, 1.0)]], [[np.full(4, 3.0)]]])  # s^2 = 1: -4 log(2 pi) - 2 and - 6
        >>> [round(float(v + 4 * np.log(2 * np.pi)), 6) for v in e[:, 0]]
        [-2.0, -6.0]
    """
    m = len(errors)
    units = []
    for k in range(len(errors[0])):
        frames = [[np.asarray(f, dtype=float) for f in errors[i][k]] for i in range(m)]
        if [[len(f) for f in fr] for fr in frames] != [[len(f) for f in frames[0]]] * m:
            raise ValueError(f"errors must hold the same observations for every model in fold {k}, got "
                             f"{[[len(f) for f in fr] for fr in frames]}")
        if not frames[0]:
            continue
        every = np.concatenate([np.concatenate(fr) for fr in frames])
        cap = CAP * float(np.median(every))
        s2 = max(float(np.mean(np.minimum(every, cap))) / 2, 1e-300)
        for j in range(len(frames[0])):
            units.append(
                [float(np.sum(-math.log(2 * math.pi * s2) - np.minimum(fr[j], cap) / (2 * s2))) for fr in frames]
            )
    return np.array(units).T if units else np.zeros((m, 0))


def evidence_weights(log_evidence: np.ndarray, draws: int = 1000, seed: int = 0) -> np.ndarray:
    """Pseudo-BMA+ weights (M,) from per-unit log evidence (M, K): the softmax averaged over a Bayesian bootstrap.

    Each draw weighs the K units (held-out frames) by Dirichlet(1, ..., 1) and scales by K; a
    model that wins every unit by far takes all the weight, models whose lead changes from unit
    to unit share it. No unit: equal weights.

    Example:
        >>> import numpy as np
        >>> evidence_weights(np.array([[0.0, 0.0, 0.0], [-50.0, -60.0, -40.0]])).round(3).tolist()
        [1.0, 0.0]
        >>> w = evidence_weights(np.array([[10.0, -10.0, 5.0, -5.0], [-10.0, 10.0, -5.0, 5.0]]))
        >>> bool(0.3 < w[0] < 0.7)
        True
    """
    e = np.asarray(log_evidence, dtype=float)
    k = e.shape[1]
    if k == 0:
        return np.full(e.shape[0], 1.0 / e.shape[0])
    rng = np.random.default_rng(seed)
    z = k * e @ rng.dirichlet(np.ones(k), size=draws).T  # (M, draws)
    z -= z.max(axis=0, keepdims=True)
    w = np.exp(z)
    return (w / w.sum(axis=0, keepdims=True)).mean(axis=1)


def mixture_interval(means: Sequence[float], stds: Sequence[float], weights: Sequence[float],
                     confidence: float = 0.95) -> tuple[float, float]:
    """The central ``confidence`` interval of a mixture of normals (an infinite std: that weight anywhere).

    Example:
        >>> lo, hi = mixture_interval([5.0], [1.0], [1.0])
        >>> round(lo, 3), round(hi, 3)
        (3.04, 6.96)
        >>> [round(v, 2) for v in mixture_interval([0.0, 10.0], [0.1, 0.1], [0.5, 0.5])]  # each one's 5 % tail
        [-0.16, 10.16]
        >>> mixture_interval([1.0, 2.0], [0.1, float("inf")], [0.9, 0.1])[1]
        inf
    """
    mu, sd, w = (np.asarray(v, dtype=float) for v in (means, stds, weights))
    w = w / w.sum()
    tail = (1 - confidence) / 2
    lost = float(w[~np.isfinite(sd)].sum())  # mass spread over the whole line: half below any x, half above
    if lost / 2 >= tail:
        return (-math.inf, math.inf)
    ok = np.isfinite(sd)
    mu, sd, w = mu[ok], np.maximum(sd[ok], 1e-12), w[ok]
    normal = NormalDist()

    def cdf(x: float) -> float:
        return lost / 2 + float(sum(wi * normal.cdf((x - m) / s) for m, s, wi in zip(mu, sd, w)))

    def quantile(q: float) -> float:
        lo, hi = float((mu - 10 * sd).min()), float((mu + 10 * sd).max())
        for _ in range(200):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if cdf(mid) < q else (lo, mid)
        return (lo + hi) / 2

    return quantile(tail), quantile(1 - tail)


def weigh_models(rows: Sequence[dict], errors: Sequence, *, checked: Sequence[bool], confidence: float,
                 draws: int = 1000, seed: int = 0) -> dict:
    """The models' weights and the answer's intervals: dispersion, checked posteriors, pseudo-BMA+, their mixture.

    ``rows``: per model ``delta_avg_px``, ``delta_max_px`` and their posterior stds
    (``delta_avg_std_px``, ``delta_max_std_px``) and ``jackknife_std_px`` (of Delta_avg);
    ``errors``: per model what :func:`unit_log_evidence` takes. ``checked``: the models whose
    jackknife sets the :func:`dispersion` and checks their posterior (:func:`checked_scale`; the
    others' posteriors stay as they are). A model without a finite posterior (the data do not
    determine it) or whose adjustment did not converge (a row's ``converged`` False) takes no
    weight, unless no model is left.

    Returns:
        ``weights`` (M,), ``lpd`` (M, units; the log evidence over the dispersion), ``dispersion``,
        ``carried`` (M,) bool and ``intervals``: the central ``confidence`` intervals of Delta_avg and
        Delta_max (each >= 0) of the models' normals mixed by their weights.

    Example:
        >>> import numpy as np
        >>> rows = [{"delta_avg_px": 10.0, "delta_avg_std_px": 1.0, "delta_max_px": 20.0, "delta_max_std_px": 2.0,
        ...          "jackknife_std_px": 2.0}]
        >>> out = weigh_models(rows, [[[np.ones(4)]]], checked=[True], confidence=0.95)
        >>> out["dispersion"], [round(v, 2) for v in out["intervals"][0]]  # the jackknife doubles the std
        (4.0, [6.08, 13.92])
    """
    spread = dispersion([r["delta_avg_std_px"] for r, c in zip(rows, checked) if c],
                        [r["jackknife_std_px"] for r, c in zip(rows, checked) if c])
    lpd = unit_log_evidence(errors) / spread
    finite = np.array([math.isfinite(r["delta_avg_std_px"]) and r.get("converged", True) for r in rows])
    carried = finite if finite.any() else np.ones(len(rows), dtype=bool)
    weights = np.zeros(len(rows))
    weights[carried] = evidence_weights(lpd[carried], draws, seed)
    intervals = mixed_intervals(rows, weights, dispersion=spread, checked=checked, confidence=confidence)
    return {"weights": weights, "lpd": lpd, "dispersion": spread, "carried": carried, "intervals": intervals}


def mixed_intervals(rows: Sequence[dict], weights: Sequence[float], *, dispersion: float, checked: Sequence[bool],
                    confidence: float) -> list[tuple[float, float]]:
    """The central ``confidence`` intervals (each >= 0) of Delta_avg and Delta_max: the models' normals, mixed.

    ``rows`` as :func:`weigh_models` takes them; each checked model's posterior variance times
    :func:`checked_scale` of ``dispersion``, the others' as they are.

    Example:
        >>> row = {"delta_avg_px": 10.0, "delta_avg_std_px": 1.0, "delta_max_px": 20.0, "delta_max_std_px": 2.0,
        ...        "jackknife_std_px": 0.5}
        >>> [[round(v, 2) for v in iv] for iv in mixed_intervals([row], [1.0], dispersion=1.0, checked=[True],
        ...                                                      confidence=0.95)]
        [[8.04, 11.96], [16.08, 23.92]]
    """
    widen = [checked_scale(dispersion, r["delta_avg_std_px"], r["jackknife_std_px"]) if c else 1.0
             for r, c in zip(rows, checked)]
    return [
        tuple(max(0.0, v) for v in mixture_interval(
            [r[f"{fig}_px"] for r in rows], [r[f"{fig}_std_px"] * math.sqrt(w) for r, w in zip(rows, widen)],
            weights, confidence))
        for fig in ("delta_avg", "delta_max")
    ]
