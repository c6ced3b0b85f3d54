"""What the commands do: evaluation, reports, reproduction, analysis of a pair, undistortion, figures.

A camera's calibration from a sequence runs in :mod:`lensdist_torch.calibration.controllers`.

Modules:

* :mod:`~lensdist_torch.workflows.prepare`: a user's pairs at the analysis size, registered, with their quality maps.
* :mod:`~lensdist_torch.workflows.analyze`: the methods on a prepared batch (``lensdist analyze``).
* :mod:`~lensdist_torch.workflows.pair_analysis`: a pair's analysis as one record, with the CLI's JSON and text.
* :mod:`~lensdist_torch.workflows.decision`: the honest answer, the calibrated confidence, the domain checks.
* :mod:`~lensdist_torch.workflows.confidence`: the confidence's Platt map and its reliability.
* :mod:`~lensdist_torch.workflows.decision_fit`: the decision fitted on a validation split (R threshold, std scales,
  Platt map).
* :mod:`~lensdist_torch.workflows.texture`: the scenes' gradient histograms of the learned methods' domain check.
* :mod:`~lensdist_torch.workflows.evaluate`: every method on a generated test set, through the analysis path.
* :mod:`~lensdist_torch.workflows.reports`: an evaluation's figures, Markdown and JSON.
* :mod:`~lensdist_torch.workflows.reproduce`: the paper's Tables 1 and 2 beside ours (``lensdist reproduce``).
* :mod:`~lensdist_torch.workflows.demo`: ``lensdist demo``.
* :mod:`~lensdist_torch.workflows.undistort`: corrected frames of a folder or a video (``lensdist undistort``).
* :mod:`~lensdist_torch.workflows.figures`: figures, the only module that imports matplotlib.

The names users need are exported here and imported on first use (PEP 562). ``reproduce`` is
not among them, because it is also the name of its module (which, once imported, would shadow
the function here): import it from the top level, ``from lensdist_torch import reproduce``.

Example:
    >>> import lensdist_torch.workflows as wf
    >>> wf.undistort_path is wf.undistort.undistort_path  # its module is imported on first use
    True
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.workflows.prepare": ("PreparedPairs", "prepare_batch"),
    "lensdist_torch.workflows.analyze": ("analyze_batch", "analyze_pair"),
    "lensdist_torch.workflows.pair_analysis": ("PairAnalysis",),
    "lensdist_torch.workflows.undistort": ("undistort_path",),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
