"""Camera calibration from a sequence: a folder of frames or a video, one camera.

Estimators (layer 2: tensors and COLMAP reconstructions in, typed records out; they never
print or read files):

* :mod:`~lensdist_torch.calibration.lens_answer`: the lens answer every path gives; each path's record derives from it.
* :mod:`~lensdist_torch.calibration.direct`: the direct photometric path, the pairs' self-calibrations pooled.
* :mod:`~lensdist_torch.calibration.direct_fits`: its pairs fitted one by one, the failures refitted from their
  registration.
* :mod:`~lensdist_torch.calibration.pooling`: how its pairs pool: which count (the good-and-bad mixture), mean,
  interval.
* :mod:`~lensdist_torch.calibration.sequence_class`: a sequence's class or "cannot tell", shared by every path.
* :mod:`~lensdist_torch.calibration.multiview`: bundle adjustment on COLMAP's tracks, one shared camera.
* :mod:`~lensdist_torch.calibration.multiview_fits`: a camera fitted on a reconstruction's tracks, free or held.
* :mod:`~lensdist_torch.calibration.multiview_evidence`: the lens models' posteriors, held-out evidence, the weighted
  answer.
* :mod:`~lensdist_torch.calibration.multiview_runs`: several mappings' run-to-run spread.
* :mod:`~lensdist_torch.calibration.planar_features`: a plane or a turning camera: one lens, one homography per pair.
* :mod:`~lensdist_torch.calibration.planar_model`: its residual, Jacobian and Levenberg-Marquardt.
* :mod:`~lensdist_torch.calibration.matches`: the verified matches read from COLMAP's database, and their thinning.
* :mod:`~lensdist_torch.calibration.guided_matching`: its matches found again where its first fit predicts them.
* :mod:`~lensdist_torch.calibration.match_refinement`: its matches moved to where the views' patches align.

Controllers (layer 4: a run over files, :mod:`~lensdist_torch.calibration.controllers`):
reading the frames and running the paths (``lensdist calibrate``), their answers combined, the
answer's lens, its file, its verification by the paper's metric.

The names users need are exported here and imported on first use (PEP 562).

Example:
    >>> import lensdist_torch.calibration as cal
    >>> cal.calibrate_path.__module__
    'lensdist_torch.calibration.controllers.calibrate'
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.calibration.lens_answer": ("LensAnswer",),
    "lensdist_torch.calibration.direct": ("SequenceCalibration", "calibrate_sequence"),
    "lensdist_torch.calibration.pooling": ("GoodBadFit", "good_and_bad"),
    "lensdist_torch.calibration.matches": ("PlanarMatches",),
    "lensdist_torch.calibration.planar_features": ("PlanarCalibration", "self_calibrate_planar"),
    "lensdist_torch.calibration.controllers.calibrate": ("calibrate_path", "synthetic_sequence"),
    "lensdist_torch.calibration.controllers.verify": ("verify_undistortion",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
