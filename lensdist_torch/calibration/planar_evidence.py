"""The homography model's lens models: each one's posterior, their evidence on held-out pairs, one answer.

The 3-D models' rule (:mod:`~lensdist_torch.calibration.multiview_evidence`, :func:`weigh_models`)
on the homography model's terms (docs/method.md, section 12):

* **Its posterior.** The covariance of the lens from the fit's normal equations, every pair's
  homography marginalised (:func:`~lensdist_torch.calibration.planar_model.lens_covariance`),
  carried to Delta_avg and Delta_max by their central-difference gradient.
* **The folds.** ``jackknife_blocks`` contiguous blocks of frames; a fold leaves out every pair
  with a frame in its block. Each lens model (n = 1 .. ``planar_terms``, the centre fixed and free)
  is fitted again on the other pairs, from its fit on all of them: its delete-a-block jackknife,
  the check of its posterior.
* **Its evidence.** Each held-out pair is registered again under the fold's lens, the lens held
  (its homography alone fitted to its inliers), and its inliers' transfer errors are what the
  model predicts: one 2-D error in pixels per match, the mean square of its two sides (the
  forward and backward errors measure one misfit, as the posterior counts it). Every model
  predicts the same observations; per held-out pair their log predictive density. A model with
  more terms that only fits the noise predicts held-out pairs no better, whatever BIC says on
  thousands of matches.
* **One answer.** Where the folds scatter more than the posteriors allow (a frame's features
  recur in many pairs, so the matches are not independent), their median ratio scales the
  posteriors' variances and the log evidence alike; pseudo-BMA+ weights; the interval is the
  models' normals mixed by their weights, so models that predict as well and disagree widen it.
  No margin decides which models count.

References:
    Y. Yao, A. Vehtari, D. Simpson, A. Gelman, "Using stacking to average Bayesian predictive
    distributions", Bayesian Analysis 13(3), 2018 (pseudo-BMA+).
    L. Pace, A. Salvan, N. Sartori, "Adjusting composite likelihood ratio statistics", Statistica
    Sinica 21(1), 2011 (scaling a misspecified likelihood by the ratio of its variances).
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.calibration.matches import PlanarMatches
from lensdist_torch.calibration.multiview_evidence import fold_ranges, heldout_rms, posterior_std, weigh_models
from lensdist_torch.calibration.planar_model import (
    fit_lens_and_homographies,
    lens_covariance,
    lens_deltas,
    transfer_residuals,
)
from lensdist_torch.calibration.pooling import jackknife_std
from lensdist_torch.geometry.frame import half_diagonal

__all__ = ["score_models"]


def score_models(fits: dict, matches: PlanarMatches, v1: torch.Tensor, v2: torch.Tensor, *, inliers: torch.Tensor,
                 blocks: int, size: tuple[int, int], step: int, iterations: int, confidence: float, stays,
                 seed: int = 0) -> tuple[dict, dict]:
    """Each lens model's posterior, jackknife and weight, and the answer's intervals (module docstring).

    Args:
        fits: per model name (theta, homographies (P, 8), Delta dict, n) of its fit on every pair.
        matches: the N matches (:class:`~lensdist_torch.calibration.matches.PlanarMatches`: their
            pairs, each pair's frames, the frames' names).
        v1: (N, 2) the matches' first ends in the normalised frame, ``(p - c) / R``.
        v2: (N, 2) their second ends.
        inliers: (N,) bool, the matches every model is fitted to and scored on.
        blocks: the folds at most.
        size: the frames' (H, W).
        step: the Delta grid's spacing (px); the posterior's gradient and the folds' take twice it.
        iterations: Levenberg-Marquardt's at most per fit.
        confidence: coverage of the intervals.
        stays: ``stays(theta, n)``, whether a lens's centre lies where the model's may (a fold's fit
            that strays beyond it takes the model out: the matches do not determine its centre).
        seed: the Bayesian bootstrap's.

    Returns:
        (per model that stays: ``weight``, ``elpd`` (its held-out log evidence over the
        dispersion), ``delta_avg_std_px`` and ``delta_max_std_px`` (the posterior's),
        ``covariance`` (of its coefficients and, where free, its centre in pixels; None where the
        matches do not determine it: then no weight), ``jackknife_std_px``, ``heldout_rms_px`` (its
        held-out transfer errors' RMS, px, per coordinate), ``jackknife_avg`` and ``jackknife_thetas`` (its
        folds' Delta_avg and lenses);
        the answer: ``intervals`` of Delta_avg and Delta_max and the ``dispersion``).
    """
    big_r = half_diagonal(*size)
    first, second, pair = matches.first, matches.second, matches.pair
    names = list(fits)
    errors = {m: [] for m in names}
    out = {m: {"jackknife_avg": [], "jackknife_thetas": []} for m in names}
    for frames in fold_ranges(len(matches.names), blocks):
        block = torch.tensor(frames)
        left = (torch.isin(first, block) | torch.isin(second, block))[pair]
        train, held = inliers & ~left, inliers & left  # each fit sees its own matches only (the rest weigh 0)
        held_pair = pair[held]
        units = held_pair.unique()
        for m in names:
            theta, hs, _, n = fits[m]
            tj, _ = fit_lens_and_homographies(theta.clone(), hs.clone(), v1[train], v2[train], pair=pair[train],
                                              w=v1.new_ones(int(train.sum())), iterations=iterations, terms=n)
            _, hh = fit_lens_and_homographies(tj, hs.clone(), v1[held], v2[held], pair=held_pair,
                                              w=v1.new_ones(len(held_pair)), iterations=iterations, terms=n,
                                              lens_held=True)
            r = transfer_residuals(tj, hh, v1[held], v2[held], terms=n, pair=held_pair) * big_r
            # (K,): one squared 2-D error per match, its two sides' mean (each side measures the same misfit);
            # a point the fold's lens cannot map is an error without bound (the cap takes it)
            e = (r.reshape(-1, 2, 2) ** 2).sum(-1).mean(-1)
            e = torch.where(torch.isfinite(e), e, torch.inf)
            errors[m].append([e[held_pair == p].numpy() for p in units])
            out[m]["jackknife_avg"].append(lens_deltas(tj, n, size, 2 * step)["delta_avg_px"])
            out[m]["jackknife_thetas"].append(tj)
    # the folds are the model too: one whose centre strays from where a lens's may lie is not determined
    names = [m for m in names if all(stays(tj, fits[m][3]) for tj in out[m]["jackknife_thetas"])]
    out = {m: out[m] for m in names}
    rows = []
    for m in names:
        theta, hs, dl, n = fits[m]
        cov = lens_covariance(theta, hs, v1, v2, pair=pair, w=inliers.double(), terms=n)

        def measure(p, n=n):
            d = lens_deltas(torch.as_tensor(p, dtype=torch.float64), n, size, 2 * step)
            return d["delta_avg_px"], d["delta_max_px"]

        std_avg, std_max = posterior_std(theta.tolist(), list(range(theta.numel())),
                                         None if cov is None else cov.numpy(), measure)
        jk_std = jackknife_std(out[m]["jackknife_avg"])
        flat = [u for fold in errors[m] for u in fold]
        to_px = torch.cat([torch.ones(n, dtype=torch.float64), torch.full((theta.numel() - n,), big_r)])
        out[m].update(delta_avg_std_px=std_avg, delta_max_std_px=std_max, jackknife_std_px=jk_std,
                      heldout_rms_px=heldout_rms(flat) / math.sqrt(2),
                      covariance=None if cov is None else (to_px[:, None] * cov * to_px).tolist())
        rows.append({"delta_avg_px": dl["delta_avg_px"], "delta_max_px": dl["delta_max_px"],
                     "delta_avg_std_px": std_avg, "delta_max_std_px": std_max, "jackknife_std_px": jk_std})
    weighed = weigh_models(rows, [errors[m] for m in names], checked=[True] * len(names), confidence=confidence,
                           seed=seed)
    for m, w, e in zip(names, weighed["weights"], weighed["lpd"].sum(axis=1)):
        out[m].update(weight=float(w), elpd=float(e))
    return out, {"intervals": weighed["intervals"], "dispersion": weighed["dispersion"]}
