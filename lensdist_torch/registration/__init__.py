"""One pair's registration by a homography (layer 2).

* :mod:`~lensdist_torch.registration.direct`: batched inverse-compositional Gauss-Newton from a phase-correlation start.
* :mod:`~lensdist_torch.registration.wide_baseline`: far-apart pairs: features and RANSAC, then the direct refinement.

The names users need are exported here and imported on first use (PEP 562).

Example:
    >>> from lensdist_torch.registration import estimate_homography
    >>> estimate_homography.__module__
    'lensdist_torch.registration.direct'
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.registration.direct": ("estimate_homography", "warp_to_reference"),
    "lensdist_torch.registration.wide_baseline": ("SiftMemo", "estimate_homography_robust", "feature_homography"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
