"""``[registration]``, ``[selfcal]``: one pair's homography registration and its self-calibration of (k2, k4) and H."""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import flag, integer, real

__all__ = ["RegistrationConfig", "SelfCalConfig"]


@dataclass(frozen=True)
class RegistrationConfig:
    """Settings of :func:`estimate_homography` (``[registration]``).

    What a user sets: the speed; the method's constants (the acceptance gates, the feature
    fallback, the pyramid, the iterations, the tolerances, the damping, the feature matching's)
    are named in the modules that use them (:mod:`~lensdist_torch.registration.direct`,
    ``wide_baseline``; docs/method.md, section 7).

    Attributes:
        chunk_size: pairs registered together (cache locality); results do not depend on it.

    Example:
        >>> from dataclasses import replace
        >>> RegistrationConfig().chunk_size, replace(RegistrationConfig(), chunk_size=4).chunk_size
        (8, 4)
        >>> RegistrationConfig(chunk_size=0)
        Traceback (most recent call last):
        ...
        ValueError: registration.chunk_size must be a positive int, got 0
    """

    chunk_size: int = 8

    def __post_init__(self) -> None:
        integer(self, "chunk_size")


@dataclass(frozen=True)
class SelfCalConfig:
    """Settings of :func:`~lensdist_torch.selfcal.fit.estimate_distortion` (``[selfcal]``).

    What a user sets; the method's constants (the pyramid, its iterations and sampling cells, the
    robust loss and the photometric model, the damping, the bounds of a plausible fit, the robust
    constants, the relief's bumps and iterations, the "cannot tell" threshold, the sampling
    kernel, the second start, the clusters of the covariance and the share an occluder may spoil,
    the small-motion floor, Hausman's test and the score test's level) are named in the modules
    that use them
    (:mod:`~lensdist_torch.selfcal.fit`, ``model``, ``prior``; docs/method.md, section 10).

    Attributes:
        chunk_size: pairs fitted together; results do not depend on it.
        parallax: plane + parallax model: a relief displacing img2's points along the
            registration's translation, a smooth field of parallax x parallax Gaussian bumps
            (fitted where (a, b) are); 0: a planar scene. On by default: whether a pair's scene is
            a plane is decided per pair: Hausman's test (``fit.PARALLAX_TEST``) keeps one answer, and both
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

    Example:
        >>> from dataclasses import replace
        >>> SelfCalConfig().parallax, replace(SelfCalConfig(), parallax=0).parallax
        (5, 0)
        >>> SelfCalConfig(parallax=-1)
        Traceback (most recent call last):
        ...
        ValueError: selfcal.parallax must be an int >= 0, got -1
    """

    chunk_size: int = 16
    parallax: int = 5
    parallax_px: float = 0.2
    parallax_evidence: bool = True

    def __post_init__(self) -> None:
        integer(self, "parallax", lo=0)
        real(self, "parallax_px", lo=0, lo_open=True)
        flag(self, "parallax_evidence")
        integer(self, "chunk_size")
