"""A sequence's class, or "cannot tell" and why: the rules every path of ``lensdist calibrate`` shares.

A sequence's answer is a Delta_avg with a 95 % interval in the user's pixels and eq. 4's fit of
its lens. Its class is the class of that lens at the paper's frame (the same normalised lens,
:func:`~lensdist_torch.geometry.distortion.paper_frame_delta_avg`), R below a sequence's own
threshold, ``calibration.no_distortion_px`` (0.25 px; one pair's is ``analysis.no_distortion_px``).
No class where the interval is too wide (:func:`interval_too_wide`, the multi-view and
homography-model paths in the user's pixels) or spans that threshold at the paper's frame
(:func:`class_or_open`; :func:`sequence_class` scales a user-pixel interval there first).
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.config import LensdistConfig, MultiViewConfig
from lensdist_torch.geometry.distortion import CLASS_LABELS, estimated_class

__all__ = ["MAX_CLASS_HALFWIDTH_PX", "MAX_HALFWIDTH_PX", "MAX_HALFWIDTH_REL", "MIN_PAIRS", "class_or_open",
           "sequence_class", "interval_too_wide"]

#: The direct path: fewer usable pairs give no class ("cannot tell"; docs/method.md, section 10).
MIN_PAIRS = 4
#: The direct path: a half-width of Delta_avg over this many px at the paper's 320 x 424 frame gives no class
#: (a class bin is 3.6 px wide there).
MAX_CLASS_HALFWIDTH_PX = 1.0
#: The multi-view and homography-model paths: a half-width over this share of Delta_avg, and over
#: :data:`MAX_HALFWIDTH_PX`, gives no class (docs/method.md, sections 11-12).
MAX_HALFWIDTH_REL = 0.25
#: See :data:`MAX_HALFWIDTH_REL`, in the user's pixels.
MAX_HALFWIDTH_PX = 1.0


def class_or_open(dc: float, half: float, settings: LensdistConfig) -> tuple[str | None, str]:
    """A sequence's class from Delta_avg ``dc`` +- ``half`` (px) at the paper's frame, or None and why.

    R is below a sequence's threshold, ``calibration.no_distortion_px``; where the interval spans
    it, a distortion or none cannot be told.

    Example:
        >>> class_or_open(3.0, 0.5, LensdistConfig())[0], class_or_open(0.3, 0.2, LensdistConfig())[0]
        ('1', None)
    """
    t = settings.calibration.no_distortion_px
    if dc - half < t <= dc + half:
        return None, (f"the interval [{max(0.0, dc - half):.2f}, {dc + half:.2f}] px at the paper's frame spans the "
                      f"no-distortion threshold ({t} px): a distortion or none cannot be told")
    label = estimated_class(torch.tensor([dc]), torch.tensor([dc]), metric="delta_avg", config=settings, threshold=t)
    return CLASS_LABELS[int(label[0])], ""


def sequence_class(paper_delta: float, delta: float, half: float, settings: LensdistConfig) -> tuple[str | None, str]:
    """A sequence's class, or None and why, from Delta_avg ``delta`` +- ``half`` in the user's pixels.

    The class is of ``paper_delta``, the same lens's Delta_avg at the paper's frame, its interval
    scaled there by ``paper_delta / delta`` (:func:`class_or_open`). The multi-view and the
    homography-model paths of ``lensdist calibrate`` both decide this way; without a finite Delta
    at the paper's frame (eq. 4 could not fit the camera), no class.

    Example:
        >>> sequence_class(0.3, 0.6, 0.08, LensdistConfig())  # a frame twice the paper's: [0.26, 0.34] px there
        ('1', '')
        >>> sequence_class(0.3, 0.6, 0.2, LensdistConfig())[0] is None  # [0.2, 0.4] px spans 0.25 px
        True
    """
    if not (math.isfinite(paper_delta) and math.isfinite(delta) and math.isfinite(half)):
        return (
            None,
            f"no Delta_avg at the paper's frame (eq. 4's fit gave {paper_delta:.3g} px for {delta:.3g} "
            f"+- {half:.3g} px)",
        )
    return class_or_open(paper_delta, half * paper_delta / max(delta, 1e-12), settings)


def interval_too_wide(half: float, value: float, cfg: MultiViewConfig) -> bool:
    """Whether a Delta_avg of ``value`` px with 95 % half-width ``half`` is too uncertain for a class.

    Too wide beyond :data:`MAX_HALFWIDTH_PX` and :data:`MAX_HALFWIDTH_REL` of the value, both; a
    half-width that is not finite always.

    Example:
        >>> interval_too_wide(0.9, 0.5, MultiViewConfig()), interval_too_wide(20.0, 100.0, MultiViewConfig())
        (False, False)
        >>> interval_too_wide(30.0, 100.0, MultiViewConfig())  # beyond 1 px and 25 %
        True
    """
    return not math.isfinite(half) or half > max(MAX_HALFWIDTH_PX, MAX_HALFWIDTH_REL * value)
