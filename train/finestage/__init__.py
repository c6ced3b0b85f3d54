"""The fine stage: the registration-quality loss where it is meant to help.

The package behind ``train/fine_stage.py`` (see ``docs/results/fine_stage.md``). Pairs arrive
after a coarse alignment, 0.5-3 px from registered, with strong illumination changes between
the two patches; a refinement network (or, at test time, the eight corner offsets themselves)
is optimised with a photometric L1, a local normalised cross-correlation (NCC) or normalised
gradient fields (NGF), each alone and each + lambda * ``RegistrationQualityLoss``.

* :mod:`.config`  defaults <- TOML <- ``--set`` overrides, key checks, the arms;
* :mod:`.data`    fine-stage pairs (0.5-3 px residuals, illumination, lens distortion), splits;
* :mod:`.losses`  L1, windowed NCC, NGF and the quality loss, batch or per-pair reductions;
* :mod:`.models`  the refinement network (a 1/4-resolution cost volume);
* :mod:`.loop`    one training run (arm, seed) with versioned checkpoints and resume, evaluation;
* :mod:`.refine`  test-time refinement of the corner offsets with Adam;
* :mod:`.report`  seed statistics, lambda selection on validation, the verdict, merging seeds,
  results.json / .md, figures;
* :mod:`.experiment` the plan of runs (groups of arms per seed, processes), the selections on
  validation, the refinement study.

It reuses ``train/learnreg`` (photometric changes, lens distortion, the warp, the corner
error, the lambda schedule, the network's building blocks) by import.
"""
