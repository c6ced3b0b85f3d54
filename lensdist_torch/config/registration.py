"""``[registration]``, ``[selfcal]``: one pair's homography registration and its self-calibration of (k2, k4) and H."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

from lensdist_torch.config.checks import choice, flag, integer, integers, real

__all__ = ["RegistrationConfig", "SelfCalConfig"]


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`estimate_homography`.

    Attributes:
        levels: pyramid levels to run, coarsest first, ending with 0 (level l is 1 / 2**l of the
            size); levels whose smaller side would be under 16 px are dropped.
        iterations: maximum IC iterations for each entry of ``levels``.
        step_tol: full resolution is done when an update moves no corner by more than this (px).
        coarse_tol: the same for the coarser levels (full-resolution px).
        phase_level: pyramid level of the phase correlation (lowered for small images).
        damping: Hessian damping, a fraction of its mean diagonal.
        min_texture: smallest admissible eigenvalue of the per-pixel Gauss-Newton Hessian
            (gradients in level px, coordinates in half-diagonals).
        min_overlap: fraction of img1 that must map inside img2.
        max_residual: largest RMS residual, relative to sqrt(2) x img1's standard deviation
            (about 1 for unrelated images; ~0.02 registered, up to ~0.25 with the strongest
            distortion of docs/method.md section 6).
        margin: level px by which the pixels used must map inside img2.
        max_step: an update moving a corner by more than this fraction of the diagonal diverged.
        fine_stride: template pixel stride at full resolution.
        presmooth: binomial smoothing (sigma 1 px) of both images first.
        match_intensity: img2's grey levels mapped affinely to img1's mean and standard deviation
            first (per pair): a change of exposure (gain, offset) is not read as misregistration.
        chunk_size: pairs registered together (cache locality); results do not depend on it.
        feature_fallback: :func:`~lensdist_torch.registration.wide_baseline.estimate_homography_robust`
            retries the pairs that did not converge from SIFT matches (docs/method.md, section 10).
        max_keypoints: SIFT keypoints kept per image by the fallback.
        match_ratio: second-nearest-neighbour ratio of the fallback's mutual matches, in ]0, 1].
        ransac_threshold: px, one-way transfer error of a RANSAC inlier in the fallback.
        min_inliers: fewest RANSAC inliers for a feature homography.

    Example:
        >>> from dataclasses import replace
        >>> RegistrationConfig().levels, replace(RegistrationConfig(), levels=(3, 1, 0), iterations=(10, 8, 6)).levels
        ((2, 0), (3, 1, 0))
        >>> RegistrationConfig(levels=(0, 2))
        Traceback (most recent call last):
        ...
        ValueError: registration.levels must be a decreasing tuple of ints ending with 0, got (0, 2)
    """

    levels: tuple[int, ...] = (2, 0)
    iterations: tuple[int, ...] = (10, 6)
    step_tol: float = 0.01
    coarse_tol: float = 0.2
    phase_level: int = 3
    damping: float = 1e-6
    min_texture: float = 1e-8
    min_overlap: float = 0.3
    max_residual: float = 0.5
    margin: float = 2.0
    max_step: float = 0.25
    fine_stride: int = 2
    presmooth: bool = True
    match_intensity: bool = True
    chunk_size: int = 8
    feature_fallback: bool = True
    max_keypoints: int = 2000
    match_ratio: float = 0.9
    ransac_threshold: float = 2.0
    min_inliers: int = 15

    def __post_init__(self) -> None:
        integers(self, "levels", lo=0)
        lv = self.levels
        if lv[-1] != 0 or not all(a > b for a, b in itertools.pairwise(lv)):
            raise ValueError(f"registration.levels must be a decreasing tuple of ints ending with 0, got {lv!r}")
        integers(self, "iterations", n=len(lv), per="level")
        for name in ("step_tol", "coarse_tol", "min_texture", "max_residual"):
            real(self, name, lo=0, lo_open=True)
        real(self, "max_step", lo=0, hi=1, lo_open=True, why="a share of the diagonal")
        integer(self, "phase_level", lo=0)
        real(self, "damping", lo=0)
        real(self, "margin", lo=0)
        real(self, "min_overlap", lo=0, hi=1)
        integer(self, "fine_stride")
        flag(self, "presmooth")
        integer(self, "chunk_size")
        flag(self, "feature_fallback")
        integer(self, "max_keypoints", lo=4)
        real(self, "match_ratio", lo=0, hi=1, lo_open=True)
        real(self, "ransac_threshold", lo=0, lo_open=True)
        integer(self, "min_inliers", lo=4)


@dataclass(frozen=True)
class SelfCalConfig:
    """Settings of :func:`~lensdist_torch.selfcal.fit.estimate_distortion` (``[selfcal]``).

    What a user sets; the method's constants (the damping, the bounds of a plausible fit, the
    robust constants, the relief's bumps and iterations) are named in the modules that use them
    (:mod:`~lensdist_torch.selfcal.fit`, ``model``, ``prior``; docs/method.md, section 10).

    Attributes:
        levels: pyramid levels (2 x 2 means), coarsest first in ``iterations``.
        iterations: Levenberg-Marquardt iterations per level, coarsest first.
        sample_block: per level (coarsest first), the residual uses the strongest-gradient
            pixel of every block x block cell (1: every pixel).
        chunk_size: pairs fitted together; results do not depend on it.
        confidence_threshold: pairs below this confidence are "cannot tell from this pair" (the
            confidence is 0.5 at a std of Delta_avg of ``selfcal.fit.CANNOT_TELL_STD_PX``).
        robust: the M-estimator of the photometric residual: "tukey" (biweight), "huber" or
            "none" (least squares); IRLS with sigma = 1.4826 MAD re-estimated every iteration.
        photometric: "gain_bias" (img2 times a fitted gain plus a bias), "normalized"
            (zero-mean, unit-variance samples per pair) or "none".
        both_starts: with an ``init`` homography, also fit from phase correlation in the same
            batch and keep, per pair, the start with the lower final robust cost.
        clusters: the full-size samples are grouped in clusters x clusters rectangles of the
            frame for the cluster-robust (sandwich) covariance of the fit; 0: the Gauss-Newton
            covariance alone (docs/method.md, section 10).
        occluded_share: the share of those rectangles that an occluder or a moving object may
            spoil: ``aligned_residual``, the RMS that ``analyze`` puts to the registration's test,
            leaves out the worst of them (0, or ``clusters`` < 2: the RMS of every sample).
        parallax: plane + parallax model: a relief displacing img2's points along the
            registration's translation, a smooth field of parallax x parallax Gaussian bumps
            (fitted where (a, b) are); 0: a planar scene. On by default: whether a pair's scene is
            a plane is decided per pair: Hausman's test (``parallax_test``) keeps one answer, and both
            weigh in the confidence (``analysis.flat_prior``).
        parallax_px: the std (px) of the Gaussian prior on each bump's height: how far a
            relief may move points (MAP; larger: freer relief), chosen on validation pairs: on the
            realistic protocol the model's freedom mostly fits noise and JPEG (docs/method.md,
            section 10); the sequence path keeps its own (``calibration.direct_fits.PARALLAX_PX``). With
            ``parallax_evidence`` the std each pair starts from.
        parallax_evidence: re-estimate that std per pair from the evidence (MacKay's type-II
            maximum likelihood, after every LM step of the relief): a flat pair drives it down,
            a relief the data pin drives it up, so a flat scene's answer stays by the planar one
            while a relief is not shrunk (docs/method.md, section 10). The
            sequence path keeps its fixed prior.
        small_motion_error: a floor e R^2 / m px on the std of Delta_avg that the covariance
            leaves out, m the fitted H's mean displacement (px), R the half diagonal: fitted on
            rendered validation pairs to cover the truth in every motion bin (docs/method.md, 10).
        parallax_score_level: with ``parallax_evidence``, the plane + parallax stage runs on a pair
            where the planar answer's score test (Rao's, of the relief at zero, on the planar
            fit's finest samples) rejects a flat scene at this level; elsewhere the evidence holds
            the relief at the floor of ``selfcal.prior.PARALLAX_PX_RANGE`` and the pair keeps the planar answer
            alone (no relief answer). 1 (the default): on every pair, as the decision was fitted;
            0.01 trades confident answers at small motion for speed; a fixed prior always runs it
            (docs/method.md, section 10).
        parallax_test: the plane + parallax answer replaces the planar one where their
            Delta_avg differ by more than this many standard deviations of the difference
            (Hausman's test: under a planar scene both are right and the planar one is the
            more precise).
        interpolation: img2's sampling kernel: "bilinear", "bicubic" or "blend" (their mean).

    Example:
        >>> from dataclasses import replace
        >>> SelfCalConfig().robust, replace(SelfCalConfig(), robust="huber").robust
        ('tukey', 'huber')
        >>> SelfCalConfig(robust="l1")
        Traceback (most recent call last):
        ...
        ValueError: selfcal.robust must be 'none' or 'huber' or 'tukey', got 'l1' (str)
    """

    levels: int = 3
    iterations: tuple[int, ...] = (8, 4, 6)
    sample_block: tuple[int, ...] = (2, 4, 4)
    chunk_size: int = 16
    confidence_threshold: float = 0.5
    robust: str = "tukey"
    photometric: str = "gain_bias"
    both_starts: bool = True
    clusters: int = 6
    occluded_share: float = 0.15
    parallax: int = 5
    parallax_px: float = 0.2
    parallax_evidence: bool = True
    parallax_test: float = 2.0
    parallax_score_level: float = 1.0
    small_motion_error: float = 1.5e-5
    interpolation: str = "blend"

    def __post_init__(self) -> None:
        real(self, "small_motion_error", lo=0)
        integer(self, "clusters", lo=0)
        real(self, "occluded_share", lo=0, hi=1, hi_open=True)
        integer(self, "parallax", lo=0)
        real(self, "parallax_test", lo=0)
        real(self, "parallax_score_level", lo=0, hi=1)
        real(self, "parallax_px", lo=0, lo_open=True)
        flag(self, "parallax_evidence")
        choice(self, "robust", ("none", "huber", "tukey"))
        choice(self, "photometric", ("none", "gain_bias", "normalized"))
        choice(self, "interpolation", ("bilinear", "bicubic", "blend"))
        flag(self, "both_starts")
        for name in ("levels", "chunk_size"):
            integer(self, name)
        for name in ("iterations", "sample_block"):
            integers(self, name, n=self.levels, per="level")
        real(self, "confidence_threshold", lo=0, hi=1)
