"""A pair's analysis as one record: :class:`PairAnalysis`, with the CLI's JSON and text defined once.

:func:`~lensdist_torch.workflows.analyze.analyze_batch` (and ``analyze_pair``) return one
:class:`PairAnalysis` per pair. ``lensdist analyze --json`` prints its :meth:`PairAnalysis.to_json`
and ``lensdist analyze`` its :meth:`PairAnalysis.summary`, so the record, the JSON and the text
answer cannot drift apart. Offsets are in analysis pixels (the analysis frame, 320 x 424 by
default) unless the field's name ends in ``_user_px``: the user's own pixels.
"""

from __future__ import annotations

import dataclasses

from lensdist_torch.workflows.reports import json_safe

__all__ = ["PairAnalysis", "JSON_KEYS"]

#: The fields whose JSON key differs from the attribute's name (a Python keyword): attribute -> key.
JSON_KEYS = {"class_label": "class", "class_max_label": "class_max"}

#: The plane + parallax model's fields, given together where that model converged (the self-calibration).
_RELIEF = ("relief_agreement", "relief_parted", "planar_delta_avg", "planar_delta_avg_std", "planar_delta_avg_interval",
           "relief_delta_avg", "relief_delta_avg_std", "relief_delta_avg_interval")
#: In the user's pixels and the registration's, after the decision (every method).
_TAIL = ("analysed_region_user_px", "delta_avg_region_user_px", "delta_max_region_user_px", "delta_avg_user_px",
         "delta_avg_user_interval", "delta_max_user_px", "registration_residual", "error_blocks", "analysis_size",
         "input_size", "user_px_per_analysis_px", "homography")


def _fmt(value, spec: str = ".1f", unit: str = " px") -> str:
    """A number, or "n/a" where there is no (finite) estimate (the CLI's rule)."""
    return (
        f"{value:{spec}}{unit}"
        if isinstance(value, (int, float)) and value == value and abs(value) != float("inf")
        else "n/a"
    )


@dataclasses.dataclass(frozen=True, kw_only=True)
class PairAnalysis:
    """One pair's analysis: the answer (a class or "cannot tell"), the estimator's own output, the registration.

    Offsets are in analysis pixels (px at the analysis size ``analysis_size``) unless the name
    ends in ``_user_px`` (the user's pixels, ``user_px_per_analysis_px`` times as many). The
    fields of one method only are None for the others. :meth:`to_json` is what
    ``lensdist analyze --json`` prints (the JSON's ``class`` and ``class_max`` are
    ``class_label`` and ``class_max_label`` here), :meth:`summary` what ``lensdist analyze``
    prints.

    Attributes:
        method: the estimator: "selfcal", "regression" or "eigenspace".
        distances: the eigen-space's distances of the quality map to each class's subspace
            (its Delta_avg classifier's, or its Delta_max one's alone); empty for the others.
        reject_threshold: the eigen-space's distance above which a map is rejected; None for the others.
        confidence: calibrated P(class right) of the estimator's class (0 to 1); None for the
            eigen-space, which gives none.
        estimated_class: the estimator's own class of Delta_avg ("1"-"4" or "R"), also where the
            answer is "cannot tell"; None without an estimate.
        estimated_class_max: its class of Delta_max, likewise.
        delta_avg: Delta_avg, the mean offset of the frame's pixels (analysis px); None without
            an answer ("cannot tell" or no estimate).
        delta_max: Delta_max, the largest offset (analysis px); None likewise.
        registration_ok: the pair was registered (by the homography, or by the self-calibration's fit).
        registered_by: "homography", "self-calibration" (only its fit, which models the lens and
            the photometry, passed the registration's residual test), or None: not registered.
        overlap: the share of the first view that the registered second view covers (0 to 1).
        motion_px: how far the views moved: the registration's mean displacement (analysis px;
            the self-calibration's fit's where it registered the pair); None without one.
        in_domain: the pair is registered, overlaps enough and lies in the learned methods'
            domain (the self-calibration: always, once registered and overlapping).
        warnings: the reasons and caveats in words, one per line of the text answer.
        cannot_tell: no class: the pair cannot support an answer.
        cannot_tell_reasons: the reasons as codes (``decision.REASONS``); empty with an answer.
        class_label: the answer, "1"-"4" (least to most distortion) or "R" (none visible); None:
            "cannot tell". The JSON's ``class``.
        class_max_label: the answer's class of Delta_max; None likewise. The JSON's ``class_max``.
        estimated_delta_avg: the estimator's own Delta_avg (analysis px), also where the answer
            is "cannot tell"; None without an estimate.
        estimated_delta_max: its own Delta_max (analysis px), likewise.
        distortion_type: "barrel", "pincushion" or "mustache" (the self-calibration, from the
            sign of eq. 4's offsets); None for the others, for class R and without an answer.
        beyond_class_range: Delta_avg lies past class 4's range: "4 or beyond", no interval.
        analysed_region_user_px: [top, left, height, width] of the centred crop analysed (user px).
        delta_avg_region_user_px: Delta_avg over that crop (user px); None without an answer.
        delta_max_region_user_px: Delta_max over that crop (user px); None without an answer.
        delta_avg_user_px: Delta_avg over the user's whole frame (user px): the
            self-calibration's (k2, k4) extended to it, the learned methods' only where the crop
            is the frame; None otherwise and without an answer.
        delta_avg_user_interval: [low, high], ``delta_avg_interval`` carried to the user's whole
            frame (user px); None likewise and for the learned methods.
        delta_max_user_px: Delta_max over the whole frame (user px), likewise.
        registration_residual: the registration's RMS residual (grey levels 0 to 1); NaN where
            the homography was given.
        error_blocks: blocks of the quality map with a registration error.
        analysis_size: [height, width] of the analysis frame (analysis px).
        input_size: [height, width] of the user's images (user px).
        user_px_per_analysis_px: the scale s from the analysis frame to the user's.
        homography: the 3 x 3 registration from the first view to the second (analysis px).
        raw_confidence: the estimator's confidence before its Platt map (self-calibration and
            regression; 0 where the self-calibration diverged); None for the eigen-space.
        k2: eq. 4's k2 (analysis px^-2), the self-calibration's; None for the others and where it diverged.
        k4: eq. 4's k4 (analysis px^-4), likewise.
        delta_avg_std: the self-calibration fit's own std of Delta_avg (analysis px); None likewise.
        delta_avg_interval: [low, high], the 95 % interval of Delta_avg (analysis px); None
            without an answer, beyond the classes' range, for the learned methods, and where the
            std is not finite.
        relief: the self-calibration kept its plane + parallax model's answer (Hausman's test); None for the others.
        relief_z: that test's statistic; NaN without that model; None for the others.
        relief_found: the planar and the plane + parallax answers fall in different classes and
            the latter gives the former's class less mass than ``analysis.relief_mass``: "cannot
            tell"; None for the others and where the self-calibration diverged.
        relief_agreement: the probability the plane + parallax answer gives the planar answer's
            class; None without that model's answer (not fitted, or not converged).
        relief_parted: the two answers fall in different classes; None likewise.
        planar_delta_avg: the planar model's Delta_avg (analysis px); None likewise.
        planar_delta_avg_std: its std (analysis px); None likewise.
        planar_delta_avg_interval: its 95 % interval (analysis px); None likewise.
        relief_delta_avg: the plane + parallax model's Delta_avg (analysis px); None likewise.
        relief_delta_avg_std: its std (analysis px); None likewise.
        relief_delta_avg_interval: its 95 % interval (analysis px); None likewise.
        fitted_on: the scenes the learned method's checkpoint was fitted on; None for the
            self-calibration and where the checkpoint does not say.
        texture_distance: the learned methods' domain check: how far the images' gradient
            histogram lies from the training scenes'; None without the checkpoint's statistics.
        texture_limit: the distance above which the pair is out of domain; None likewise.
        selfcal_check: the learned methods' cross-check by the self-calibration: {"class",
            "delta_avg" (analysis px), "usable", "agrees"} and, for the eigen-space, "confirms";
            None for the self-calibration and where ``analysis.cross_check`` is off.
        k2_user: eq. 4's k2 in the user's pixels (px^-2), the self-calibration's; None for the
            others and without an answer.
        k4_user: eq. 4's k4 in the user's pixels (px^-4), likewise.
        opencv: OpenCV's camera for the user's frame ({"camera_matrix", "dist_coeffs", and the
            fit's errors in user px}); None likewise.

    Example:
        >>> from lensdist_torch import analyze_pair, load_scene
        >>> scene = load_scene("gravel")
        >>> res = analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424])  # moved by 8 px, no lens
        >>> res.class_label, res.to_json()["class"], res.registered_by
        ('R', 'R', 'homography')
        >>> print(res.summary().splitlines()[2])
        distortion class: R  (1 = small ... 4 = very strong, R = none visible)
        >>> res.class_label = "1"
        Traceback (most recent call last):
        ...
        dataclasses.FrozenInstanceError: cannot assign to field 'class_label'
    """

    method: str
    distances: list[float]
    reject_threshold: float | None
    confidence: float | None
    estimated_class: str | None
    estimated_class_max: str | None
    delta_avg: float | None
    delta_max: float | None
    registration_ok: bool
    registered_by: str | None
    overlap: float
    motion_px: float | None
    in_domain: bool
    warnings: list[str]
    cannot_tell: bool
    cannot_tell_reasons: list[str]
    class_label: str | None
    class_max_label: str | None
    estimated_delta_avg: float | None
    estimated_delta_max: float | None
    distortion_type: str | None
    beyond_class_range: bool
    analysed_region_user_px: list[int]
    delta_avg_region_user_px: float | None
    delta_max_region_user_px: float | None
    delta_avg_user_px: float | None
    delta_avg_user_interval: list[float] | None = None
    delta_max_user_px: float | None
    registration_residual: float
    error_blocks: int
    analysis_size: list[int]
    input_size: list[int]
    user_px_per_analysis_px: float
    homography: list[list[float]]
    # selfcal and regression
    raw_confidence: float | None = None
    # selfcal
    k2: float | None = None
    k4: float | None = None
    delta_avg_std: float | None = None
    delta_avg_interval: list[float] | None = None
    relief: bool | None = None
    relief_z: float | None = None
    relief_found: bool | None = None
    relief_agreement: float | None = None
    relief_parted: bool | None = None
    planar_delta_avg: float | None = None
    planar_delta_avg_std: float | None = None
    planar_delta_avg_interval: list[float] | None = None
    relief_delta_avg: float | None = None
    relief_delta_avg_std: float | None = None
    relief_delta_avg_interval: list[float] | None = None
    # regression and eigenspace
    fitted_on: list[str] | None = None
    texture_distance: float | None = None
    texture_limit: float | None = None
    selfcal_check: dict | None = None
    # selfcal, in the user's pixels
    k2_user: float | None = None
    k4_user: float | None = None
    opencv: dict | None = None

    def _json_fields(self) -> list[str]:
        """The attributes the JSON gives, in its order: each method's keys, as the analysis adds them."""
        fitted = self.k2 is not None  # the self-calibration converged: its fit's fields, in its order
        names = ["method", "distances", "reject_threshold", "confidence", "estimated_class", "estimated_class_max",
                 "delta_avg", "delta_max"]
        if fitted:
            names += ["k2", "k4", "delta_avg_std", "delta_avg_interval", "relief", "relief_z", "distortion_type"]
        if self.raw_confidence is not None:
            names.append("raw_confidence")
        if fitted:
            names += ["relief_found", *(_RELIEF if self.relief_delta_avg is not None else ())]
        names += ["registration_ok", "registered_by", "overlap", "motion_px"]
        if self.method != "selfcal":  # the learned methods' domain checks
            names += [
                "fitted_on",
                *(n for n in ("texture_distance", "texture_limit", "selfcal_check") if getattr(self, n) is not None),
            ]
        names += ["in_domain", "warnings", "cannot_tell", "cannot_tell_reasons", "class_label", "class_max_label",
                  "estimated_delta_avg", "estimated_delta_max"]
        if not fitted:  # the interval only where the decision withheld it, for every method
            names += [*(["delta_avg_interval"] if self.cannot_tell else []), "distortion_type", "beyond_class_range",
                      *(["delta_avg_interval"] if self.beyond_class_range and not self.cannot_tell else [])]
        else:
            names.append("beyond_class_range")
        names += _TAIL
        if self.method == "selfcal":
            names += ["k2_user", "k4_user", "opencv"]
        return names

    def to_json(self) -> dict:
        """What ``lensdist analyze --json`` prints: a strict-JSON-ready dict (NaN and infinities None).

        The keys are the attributes' (``class`` and ``class_max`` for ``class_label`` and
        ``class_max_label``, :data:`JSON_KEYS`); a method's own keys only for that method, in
        the order the analysis adds them. The values are copies.

        Example:
            >>> import json
            >>> from lensdist_torch import analyze_pair, load_scene
            >>> scene = load_scene("gravel")
            >>> d = analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424], method="regression").to_json()
            >>> list(d)[:3], "k2" in d, json.loads(json.dumps(d, allow_nan=False)) == d
            (['method', 'distances', 'reject_threshold'], False, True)
        """
        return json_safe({JSON_KEYS.get(n, n): getattr(self, n) for n in self._json_fields()})

    def summary(self) -> str:
        """What ``lensdist analyze`` prints: the answer in a few lines of text, the warnings last.

        The registration and overlap, the method and its confidence, the class (or "cannot tell"),
        Delta_avg with its interval and Delta_max at the analysis size and in the user's pixels
        (none where the answer is "cannot tell": the reasons instead), the eigen-space's
        distances, then one line per warning.

        Example:
            >>> from lensdist_torch import analyze_pair, load_scene
            >>> scene = load_scene("gravel")
            >>> print(analyze_pair(scene[..., :320, :424], scene[..., 8:328, :424]).summary().splitlines()[0])
            registration: ok (overlap 98 %)
        """
        lines = [f"registration: {'ok' if self.registration_ok else 'FAILED'} (overlap {100 * self.overlap:.0f} %)"]
        conf = "" if self.confidence is None or self.class_label is None else f", confidence {self.confidence:.2f}"
        lines.append(
            f"method: {self.method}{conf}" + (f"; fitted on: {', '.join(self.fitted_on)}" if self.fitted_on else "")
        )
        if self.class_label is None:
            lines.append("distortion class: cannot tell (see the warnings)")
        else:
            kind = f", {self.distortion_type}" if self.distortion_type else ""
            beyond = " or beyond (Delta_avg lies past the classes' range)" if self.beyond_class_range else ""
            lines.append(
                f"distortion class: {self.class_label}{beyond}{kind}  (1 = small ... 4 = very strong, R = none visible)"
            )
        (h, w), (ih, iw) = self.analysis_size, self.input_size
        if self.class_label is None:  # no number that reads as an answer (the JSON keeps estimated_*)
            why = f"the views moved by {_fmt(self.motion_px, '.2f')}" if self.registration_ok else "registration failed"
            reasons = ", ".join(self.cannot_tell_reasons or []) if self.registration_ok else ""
            lines.append(f"Delta: none given ({'reason: ' + reasons + '; ' if reasons else ''}{why})")
        else:
            iv = self.delta_avg_interval
            lines.append(
                f"Delta_avg ~ {_fmt(self.delta_avg, '.2f')}"
                + (f" [{iv[0]:.2f}, {iv[1]:.2f}] (95 %)" if iv else "")
                + f", Delta_max ~ {_fmt(self.delta_max)} at {w} x {h}"
            )
            uv = self.delta_avg_user_interval
            lines.append(
                f"in your {iw} x {ih} pixels: Delta_avg {_fmt(self.delta_avg_user_px)}"
                + (f" [{uv[0]:.1f}, {uv[1]:.1f}] (95 %)" if uv else "")
                + ", Delta_max "
                f"{_fmt(self.delta_max_user_px)} over the whole frame; {_fmt(self.delta_avg_region_user_px)} and "
                f"{_fmt(self.delta_max_region_user_px)} over the analysed centre crop"
            )
        if self.distances:
            lines.append("eigen-space distances: " + ", ".join(f"{d:.3f}" for d in self.distances)
                         + f" (reject above {self.reject_threshold:.3f})")
        lines += [f"warning: {text}" for text in self.warnings]
        return "\n".join(lines)
