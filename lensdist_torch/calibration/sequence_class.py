"""A sequence's class, or "cannot tell" and why: the one rule every path of ``lensdist calibrate`` shares.

A sequence's answer is a Delta_avg with a 95 % interval in the user's pixels and eq. 4's fit of
its lens. Its class is the class of that lens at the paper's frame (the same normalised lens,
:func:`~lensdist_torch.geometry.distortion.paper_frame_delta_avg`), R below a sequence's own
threshold, :data:`NO_DISTORTION_PX` (0.25 px; one pair's is ``analysis.no_distortion_px``).
:func:`interval_class` gives it where every value of the interval, carried to the paper's frame,
falls in that one class, and otherwise names the classes the interval spans (docs/method.md,
section 10): no width limit besides, since a class bin is the width that matters.
"""

from __future__ import annotations

import math

import torch

from lensdist_torch.config import LensdistConfig
from lensdist_torch.geometry.distortion import CLASS_LABELS, estimated_class

__all__ = ["MIN_PAIRS", "NO_DISTORTION_PX", "interval_class"]

#: The direct path: fewer usable pairs give no class ("cannot tell"; docs/method.md, section 10).
MIN_PAIRS = 4
#: A sequence's Delta_avg (px at the paper's 320 x 424 frame) below this is class R, on every path of calibrate.
NO_DISTORTION_PX = 0.25


def _class_of(value: float, settings: LensdistConfig) -> str:
    x = torch.tensor([value], dtype=torch.float64)
    return CLASS_LABELS[int(estimated_class(x, x, metric="delta_avg", config=settings, threshold=NO_DISTORTION_PX)[0])]


def interval_class(paper_delta: float, delta: float, interval, settings: LensdistConfig) -> tuple[str | None, str]:
    """A sequence's class, or None and why, from Delta_avg ``delta`` px and its ``interval`` in the user's pixels.

    The interval is carried to the paper's frame by ``paper_delta / delta`` (``paper_delta``: the
    same lens's Delta_avg there); the class is the one both of its ends fall in. Where they fall in
    two, "cannot tell", naming them (R against 1: a distortion or none cannot be told). Without a
    finite Delta at the paper's frame (eq. 4 could not fit the camera) or an interval with two
    finite ends, no class.

    Example:
        >>> st = LensdistConfig()
        >>> interval_class(0.3, 0.6, (0.52, 0.68), st)  # a frame twice the paper's: [0.26, 0.34] px there
        ('1', '')
        >>> interval_class(0.3, 0.6, (0.4, 0.8), st)[1].startswith("the interval [0.20, 0.40] px")  # spans 0.25 px
        True
        >>> interval_class(9.0, 9.0, (6.0, 12.0), st)[1].endswith("spans classes 2, 3 and 4")
        True
    """
    lo, hi = (math.nan, math.nan) if interval is None else (
        math.nan if v is None else float(v) for v in interval)
    if not all(math.isfinite(v) for v in (paper_delta, delta, lo, hi)):
        return None, (f"no class: Delta_avg {delta:.3g} px in [{lo:.3g}, {hi:.3g}], {paper_delta:.3g} px at the "
                      "paper's frame (eq. 4's fit)")
    scale = paper_delta / max(delta, 1e-12)
    lo, hi = max(0.0, lo) * scale, hi * scale
    first, last = _class_of(lo, settings), _class_of(hi, settings)
    if first == last:
        return first, ""
    where = f"the interval [{lo:.2f}, {hi:.2f}] px at the paper's frame spans "
    if "R" in (first, last):
        return None, (where + f"the no-distortion threshold ({NO_DISTORTION_PX} px): a distortion "
                      "or none cannot be told")
    spanned = [c for c in CLASS_LABELS if c != "R" and first <= c <= last]
    return None, where + "classes " + (", ".join(spanned[:-1]) + " and " + spanned[-1])
