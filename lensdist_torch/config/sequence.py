"""The sequence estimators' settings: ``[calibration]`` (the direct path) and ``[multiview]`` (COLMAP).

Sections of :class:`~lensdist_torch.config.LensdistConfig`;
import them from ``lensdist_torch.config``.
"""

from __future__ import annotations

from dataclasses import dataclass

from lensdist_torch.config.checks import integer, names, real

__all__ = ["CalibrationConfig", "MULTIVIEW_MODELS", "MultiViewConfig"]


@dataclass(frozen=True)
class CalibrationConfig:
    """Settings of ``lensdist calibrate`` (``[calibration]``): the answer's coverage, the direct path's size.

    Those of :func:`~lensdist_torch.calibration.direct.calibrate_sequence` a user sets (the relief
    model's bumps are ``selfcal.parallax``, for a pair and a sequence); the method's constants (the
    misfit gate, the refit from a pair's own registration, the relief's test and share of the
    interval, a sequence's R threshold, the verification's pairs, the pairs fitted together among
    them) are named in the modules that use them
    (:mod:`~lensdist_torch.calibration.direct`, ``pooling``, ``direct_fits``, ``sequence_class``,
    ``controllers.calibrate``; docs/method.md, section 10).

    Attributes:
        analysis_side: longest side (px) of the analysis frames; larger frames are downscaled.
        max_pairs: at most this many pairs, evenly spread over those chosen.
        confidence: coverage of the intervals, of every path (the direct one, the multi-view one and
            the homography model).

    Example:
        >>> import dataclasses
        >>> cfg = CalibrationConfig()
        >>> cfg.analysis_side, dataclasses.replace(cfg, confidence=0.9).confidence
        (512, 0.9)
        >>> CalibrationConfig(confidence=1.5)
        Traceback (most recent call last):
        ...
        ValueError: calibration.confidence must be a number in ]0, 1[, got 1.5
    """

    analysis_side: int = 512
    max_pairs: int = 64
    confidence: float = 0.95

    def __post_init__(self) -> None:
        for name in ("analysis_side", "max_pairs"):
            integer(self, name, lo={"analysis_side": 64}.get(name, 1))
        real(self, "confidence", lo=0, hi=1, lo_open=True, hi_open=True)


#: The camera models :class:`MultiViewConfig` may choose from: COLMAP's names, all OpenCV-compatible.
MULTIVIEW_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


@dataclass(frozen=True)
class MultiViewConfig:
    """Settings of :mod:`~lensdist_torch.calibration.multiview` (``[multiview]``): bundle adjustment on COLMAP.

    What a user sets (the intervals' coverage is ``calibration.confidence``, one for every path); the
    method's constants are named in the modules that use them
    (:mod:`~lensdist_torch.calibration.multiview`, ``features``, ``matches``, ``planar_features``,
    ``guided_matching``, ``match_refinement``, ``sequence_class``, ``controllers.multiview_path``;
    docs/method.md, 11-12).

    Attributes:
        models: the camera models fitted on the reconstruction's tracks, each weighed by how well it
            predicts held-out frames (COLMAP names, all with an exact OpenCV equivalent;
            :mod:`~lensdist_torch.calibration.multiview_evidence`). SIMPLE_PINHOLE, a camera without
            distortion, may join them: where the tracks cannot tell a relief from a lens, it predicts
            held-out frames as well and the answer's interval reaches 0 (docs/method.md, section 11).
            SIMPLE_RADIAL (RADIAL with k2 = 0) may join them too; it is not among the defaults:
            RADIAL holds it, and its adjustment crawled without converging on long videos.
        max_image_side: frames are read by COLMAP's SIFT at most this long (px).
        max_features: SIFT features per frame at most (and ``features.FEATURES_PER_MEGAPIXEL`` per
            megapixel of the frame as SIFT reads it); matching and mapping scale with the features.
        mapped_frames: at most this many frames go to COLMAP, evenly spaced over the sequence (a
            video's neighbouring frames add tracks but little baseline, while matching and
            mapping grow with the frames): of 300 frames every 5th.
        jackknife_blocks: the folds: contiguous blocks of frames held out in turn; each model is
            adjusted without a block and scored on predicting it (its evidence), and the spread of
            those fits is the jackknife that checks each model's posterior.
        reconstructions: mappings on the same matches (seeds ``seed``, ``seed`` + 1, ...); one
            answers, its posterior checked by its own jackknife; more: their spread of Delta_avg
            joins the interval (:mod:`~lensdist_torch.calibration.multiview_runs`) and a class needs
            this many mappings that registered enough frames.
        num_threads: shards of COLMAP's feature extraction and geometric verification (one
            thread each), and the worker processes that fit the camera models on tracks of many
            observations (:mod:`~lensdist_torch.calibration.multiview_workers`); the matching
            and the mapping run on one. The features and matches repeat bit for bit whatever
            this is (docs/method.md, 11).
        seed: COLMAP's random seed (the verification's RANSAC and the first mapping) and the
            Bayesian bootstrap's of the models' weights.
        planar_terms: the homography model's radial terms at most (1 .. this many fitted, each
            weighed by how well it predicts held-out pairs:
            :mod:`~lensdist_torch.calibration.planar_evidence`); 0: no homography model. Its
            other numbers are constants of the method (``matches.PLANAR_MIN_MATCHES``,
            ``planar_features.PLANAR_CENTRE_MAX``, ``guided_matching.PLANAR_GUIDED_PX``, ...).

    Example:
        >>> MultiViewConfig().models
        ('RADIAL', 'OPENCV', 'FULL_OPENCV')
        >>> MultiViewConfig(models=("RADIAL", "FISHEYE"))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: multiview.models must hold names from SIMPLE_PINHOLE, SIMPLE_RADIAL, ..., got 'FISHEYE'
    """

    models: tuple[str, ...] = ("RADIAL", "OPENCV", "FULL_OPENCV")
    max_image_side: int = 1600
    max_features: int = 8192
    mapped_frames: int = 60
    jackknife_blocks: int = 6
    reconstructions: int = 1
    num_threads: int = 2
    seed: int = 0
    planar_terms: int = 3

    def __post_init__(self) -> None:
        names(self, "models")
        for m in self.models:
            if m not in MULTIVIEW_MODELS:
                raise ValueError(f"multiview.models must hold names from {', '.join(MULTIVIEW_MODELS)}, got {m!r}")
        for name, lo in (
            ("max_image_side", 64),
            ("max_features", 64),
            ("mapped_frames", 3),
            ("jackknife_blocks", 2),
            ("reconstructions", 1),
            ("num_threads", 1),
            ("seed", 0),
            ("planar_terms", 0),
        ):
            integer(self, name, lo=lo)

