"""Learned registration with the registration-quality metric as an auxiliary loss.

The package behind ``train/learned_registration.py`` (see ``train/README.md``):

* :mod:`.config`  the training config (defaults <- TOML <- ``--set`` overrides);
* :mod:`.data`    pair generation (crops, corner offsets, lens distortion, photometric changes), seeds;
* :mod:`.models`  the networks (correlation and stacked HomographyNet);
* :mod:`.losses`  the warp, the photometric L1, the quality loss, the corner error;
* :mod:`.loop`    the schedule, one training step, checkpoints, an arm end to end, resume;
* :mod:`.report`  evaluation on held-out pairs, results.json / results.md, training curves.
"""
