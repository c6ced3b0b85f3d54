"""One pair's self-calibration: its distortion and homography fitted together (layer 2).

* :mod:`~lensdist_torch.selfcal.fit`: the fit of a batch of pairs, ``estimate_distortion``.
* :mod:`~lensdist_torch.selfcal.solver`: its robust Levenberg-Marquardt steps, cost and normal equations.
* :mod:`~lensdist_torch.selfcal.model`: its model, residual and Jacobian, and the per-pair diagnostics ``SelfCalInfo``.
* :mod:`~lensdist_torch.selfcal.prior`: the Gaussian prior on the plane + parallax model's relief, set per pair by
  its evidence.
* :mod:`~lensdist_torch.selfcal.regions`: the frame's rectangles of the samples, for the cluster-robust covariance.

The names users need are exported here and imported on first use (PEP 562).

Example:
    >>> from lensdist_torch.selfcal import estimate_distortion
    >>> estimate_distortion.__module__
    'lensdist_torch.selfcal.fit'
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.selfcal.fit": ("estimate_distortion",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
