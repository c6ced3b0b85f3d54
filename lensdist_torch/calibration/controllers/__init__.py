"""A sequence's calibration run over files (layer 4, beside :mod:`lensdist_torch.workflows`).

* :mod:`~lensdist_torch.calibration.controllers.calibrate`: a camera from a folder of frames or a video
  (``lensdist calibrate``).
* :mod:`~lensdist_torch.calibration.controllers.multiview_path`: the multi-view path, and how its answer and the direct
  one combine.
* :mod:`~lensdist_torch.calibration.controllers.answer_lens`: the lens an answer stands for, scaled to other frames.
* :mod:`~lensdist_torch.calibration.controllers.answer_file`: the checks of a saved answer read by ``undistort --from``.
* :mod:`~lensdist_torch.calibration.controllers.verify`: the paper's metric as the verifier of an answer.

Its public names are exported by :mod:`lensdist_torch.calibration`.
"""
