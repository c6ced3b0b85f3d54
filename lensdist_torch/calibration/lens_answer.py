"""The lens answer every sequence path gives, and the records that add each path's diagnostics.

A camera's distortion from a sequence is answered the same way by the direct photometric path
(:class:`~lensdist_torch.calibration.direct.SequenceCalibration`), the multi-view path on
COLMAP's tracks (:class:`~lensdist_torch.calibration.multiview.MultiViewCalibration`) and the
homography model (:class:`~lensdist_torch.calibration.planar_features.PlanarCalibration`):
Delta_avg and Delta_max over the frame with their intervals, eq. 4's (k2, k4) about the frame
centre, a class or None with the reason. :class:`LensAnswer` holds that core once; each path's
record derives from it and adds its own diagnostics. Every record is frozen and built by
keyword only (a field inserted never shifts another).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

__all__ = ["LensAnswer"]


@dataclass(frozen=True, kw_only=True)
class LensAnswer:
    """A camera's lens as a sequence path answers it, in the frames' own pixels; NaN where unknown.

    Attributes:
        k2_user: eq. 4's k2 (px^-2) about the frame centre, in the user's pixels; where another
            lens model answered, eq. 4 fitted to it.
        k4_user: eq. 4's k4 (px^-4), likewise.
        delta_avg_user_px: Delta_avg, the mean over the frame's pixels of |distorted - ideal|
            (user px); over the pixels where the lens inverts where a path says so.
        delta_avg_user_interval: (low, high), its central interval at the path's ``confidence``.
        delta_max_user_px: Delta_max, the largest such displacement (user px).
        delta_max_user_interval: (low, high), its interval.
        class_label: the distortion class "1".."4" or "R" (none visible), or None: "cannot tell".
        reason: why there is no class ("" where there is one, or a note on it).

    Example:
        >>> nan = float("nan")
        >>> a = LensAnswer(k2_user=nan, k4_user=nan, delta_avg_user_px=nan, delta_avg_user_interval=(nan, nan),
        ...                delta_max_user_px=nan, delta_max_user_interval=(nan, nan), class_label=None,
        ...                reason="no pair")
        >>> a.class_label, list(a.to_dict())[:2]
        (None, ['k2_user', 'k4_user'])
        >>> LensAnswer(1e-7, 0.0)
        Traceback (most recent call last):
        ...
        TypeError: LensAnswer.__init__() takes 1 positional argument but 3 were given
    """

    k2_user: float
    k4_user: float
    delta_avg_user_px: float
    delta_avg_user_interval: tuple[float, float]
    delta_max_user_px: float
    delta_max_user_interval: tuple[float, float]
    class_label: str | None
    reason: str

    def to_dict(self) -> dict:
        """Every field by name, the core's first, the values as they are (no copy).

        Example:
            >>> nan = float("nan")
            >>> LensAnswer(k2_user=1e-7, k4_user=0.0, delta_avg_user_px=1.0, delta_avg_user_interval=(0.9, 1.1),
            ...            delta_max_user_px=3.0, delta_max_user_interval=(2.7, 3.3), class_label="1",
            ...            reason="").to_dict()["delta_avg_user_interval"]
            (0.9, 1.1)
        """
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
