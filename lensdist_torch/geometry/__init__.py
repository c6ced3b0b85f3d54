"""Geometry: one home per primitive, and the estimators built on them.

Primitives (layer 1): :mod:`.frame` (pixel grids, grid_sample coordinates, the centred
normalised frame), :mod:`.phase` (phase correlation), :mod:`.pyramid` (central differences,
2 x 2 mean pyramids, binomial smoothing), :mod:`.distortion` (eq. 4: its factor, Newton
inverse, Delta metrics and classes), :mod:`.homography`.
Estimators (layer 2): :mod:`.registration` (homography), :mod:`.selfcal` (distortion and
homography together).
"""
