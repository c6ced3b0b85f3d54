"""``[analysis]``: the decision of ``analyze`` (R threshold, confidence, motion) and the fit of that decision."""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import flag, real

__all__ = ["AnalysisConfig"]


@dataclass(frozen=True)
class AnalysisConfig:
    """The decision of ``analyze`` and of the evaluation of the estimators (``[analysis]``).

    What a user sets and what ``fit_confidence`` writes (the R threshold, the confidence, the
    intervals' scale, fitted on a validation split); the decision's constants (the overlap, the
    domain checks, the self-calibration's Platt map, the intervals' coverage, the validation
    split's seed offset, the fit's target precision and its most "cannot tell", the eigen-space's
    confirmation) are named in the modules that use them
    (:mod:`~lensdist_torch.workflows.decision`, ``analyze``, ``class_mass``, ``decision_fit``;
    docs/method.md, section 10).

    Attributes:
        no_distortion_px: one pair's estimated Delta_avg (px at 320 x 424) below this is class
            R, "no visible distortion" (class 1 spans ]0, 3.6] px there). One pair's estimate
            is noisier than a sequence's (``calibration.sequence_class.NO_DISTORTION_PX``, 0.25 px): 0.75 px
            is the threshold whose largest reliability error over the three rendered conditions
            is least, and on real views with no lens it called 2 of 6 answers class 1 where
            0.25 px called 6 of 7 (docs/method.md, section 10).
        min_confidence: below this calibrated confidence (an estimate of P(class right)) the
            answer is "cannot tell" (self-calibration and regression). Fitted on a validation
            split (``fit_confidence``): the value that answers most while the answers' share
            right reaches ``decision_fit.TARGET_PRECISION`` (at the lower end of its 95 %
            interval), within ``decision_fit.MAX_CANNOT_TELL``.
        regression_confidence_scale, regression_confidence_shift: the Platt map of the
            regression's confidence c: sigmoid(scale * logit(c) + shift); 1 and 0 leave it as it
            is. Fitted on a validation split by ``fit_confidence``.
        selfcal_std_scale: the factor on a pair's Delta_avg stds (the fit's covariance) in the
            self-calibration's confidence, its class's mass under each model of the scene; 1
            leaves them. Fitted on a validation split by ``fit_confidence`` (least log-loss):
            0.5 on the rendered planar conditions (the grid's end), 1.54 where the scene has relief.
        interval_std_scale: the factor on a pair's Delta_avg std in its intervals (the kept
            answer's, the planar and the plane + parallax ones); 1 leaves them. Fitted on a
            validation split by ``fit_confidence``: the least whose intervals cover the true
            Delta_avg on ``class_mass.INTERVAL_CONFIDENCE`` of its pairs. The shipped default is 1
            for both: real pairs are not the rendered protocol (docs/method.md, section 10).
        cross_check: the learned methods (regression, eigen-space) also run the
            self-calibration and are out of domain where the two disagree; the eigen-space's
            class, which has no confidence, stands only where the self-calibration confirms it
            (``decision.EIGENSPACE_MAX_CLASS_DISAGREEMENT``).
        min_motion_px: below this mean displacement (analysis px) of the registration, every
            method says "cannot tell": both views carry the same distortion, which cancels
            where the scene did not move. Positive, and applied with or without ``cross_check``.
        flat_prior: with the plane + parallax model (``selfcal.parallax`` > 0), the weight of the
            planar model in a pair's confidence: the class's mass under the planar answer times
            this, plus its mass under the plane + parallax answer times 1 - this (a prior
            probability that the scene is flat; chosen on validation pairs of three conditions,
            docs/method.md, section 10: the least largest ECE with each pair's relief prior
            from its evidence). Fitted on a validation split with
            ``selfcal_std_scale`` (least log-loss).
        relief_mass: "cannot tell" for relief where the planar and the plane + parallax
            answers fall in different classes and the plane + parallax answer gives the planar
            answer's class less probability than this (its class mass, the std times
            ``selfcal_std_scale``): the class then depends on whether the scene is flat, which one
            pair cannot tell; both answers are given beside it. 0: never; 1 (the default):
            wherever the classes differ. Not fitted: on rendered flat pairs 0 answers more
            and as well, but on real frames the rule withheld a pair both models got wrong
            (docs/method.md, section 10); 0 is for scenes known to be flat.

    Example:
        >>> from dataclasses import replace
        >>> AnalysisConfig().no_distortion_px, replace(AnalysisConfig(), no_distortion_px=0.5).no_distortion_px
        (0.75, 0.5)
        >>> AnalysisConfig(relief_mass=1.5)
        Traceback (most recent call last):
        ...
        ValueError: analysis.relief_mass must be a number in [0, 1], got 1.5
    """

    no_distortion_px: float = 0.75
    min_confidence: float = 0.5
    # fitted by `lensdist reproduce` (configs/paper.toml) on its validation split, the run that
    # fitted the shipped checkpoints (docs/results/reproduce.md, "Calibration")
    regression_confidence_scale: float = 0.5684
    regression_confidence_shift: float = 1.0797
    selfcal_std_scale: float = 1.0
    interval_std_scale: float = 1.0
    cross_check: bool = True
    min_motion_px: float = 1.0
    flat_prior: float = 0.5
    relief_mass: float = 1.0

    def __post_init__(self) -> None:
        real(self, "no_distortion_px", lo=0, lo_open=True)
        real(self, "min_motion_px", lo=0, lo_open=True, why="at 0 every method answers on the same image twice")
        real(self, "flat_prior", lo=0, hi=1)
        real(self, "relief_mass", lo=0, hi=1)
        real(self, "min_confidence", lo=0, hi=1)
        for name in ("regression_confidence_scale", "selfcal_std_scale", "interval_std_scale"):
            real(self, name, lo=0, lo_open=True)
        real(self, "regression_confidence_shift")
        flag(self, "cross_check")
