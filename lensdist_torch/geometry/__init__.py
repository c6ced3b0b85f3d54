"""Geometry: one home per primitive (layer 1): the lens models, homographies, grids and pyramids.

* :mod:`~lensdist_torch.geometry.frame`: pixel grids, grid_sample coordinates, the centred normalised frame.
* :mod:`~lensdist_torch.geometry.phase`: phase correlation, the translation between two images.
* :mod:`~lensdist_torch.geometry.pyramid`: central differences, 2 x 2 mean pyramids, binomial smoothing.
* :mod:`~lensdist_torch.geometry.distortion`: eq. 4: its factor, Newton inverse, Delta metrics and classes.
* :mod:`~lensdist_torch.geometry.homography`: homographies on points, the class-R perturbation, corner error, motion.
* :mod:`~lensdist_torch.geometry.opencv_model`: eq. 4 as OpenCV camera parameters, in pure torch.
* :mod:`~lensdist_torch.geometry.undistort`: undistorted images, batched and differentiable.
* :mod:`~lensdist_torch.geometry.radial_lens`: a radial lens about a distortion centre (eq. 4 its special case) and its
  inverse.

Built on them: one pair's registration (:mod:`lensdist_torch.registration`) and self-calibration
(:mod:`lensdist_torch.selfcal`), a whole sequence's calibration (:mod:`lensdist_torch.calibration`).

The names users need are exported here and imported on first use (PEP 562): importing
:mod:`~lensdist_torch.geometry.distortion` loads neither OpenCV, pycolmap nor the estimators.

Example:
    >>> from lensdist_torch.geometry import delta_avg
    >>> round(float(delta_avg([1e-6], [0.0], 320, 424)[0]), 2)  # px, at the paper's frame
    4.19
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.geometry.distortion": (
        "CLASS_LABELS",
        "delta_avg",
        "delta_max",
        "delta_top",
        "distort_points",
        "distortion_class",
        "distortion_grid",
        "estimated_class",
        "pixel_offsets",
        "radial_factor",
        "radial_inverse",
        "render_distorted",
        "undistort_points",
    ),
    "lensdist_torch.geometry.homography": (
        "apply_homography",
        "corner_error",
        "mean_displacement",
        "perturb_homography",
    ),
    "lensdist_torch.geometry.phase": ("phase_correlation",),
    "lensdist_torch.geometry.opencv_model": ("OpenCVCamera", "opencv_camera"),
    "lensdist_torch.geometry.undistort": ("Undistort", "undistort_image"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
