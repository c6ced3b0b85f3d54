"""The ``lensdist`` command line (layer 5): argument parsing, printing, exit codes.

* :mod:`~lensdist_torch.cli.commands`: ``main``, the parser, and the protocol's commands (demo, generate, train,
  evaluate, reproduce).
* :mod:`~lensdist_torch.cli.analyze`: a user's pair, ``lensdist analyze``.
* :mod:`~lensdist_torch.cli.calibrate`: a user's camera, ``lensdist calibrate`` and ``lensdist undistort``.
* :mod:`~lensdist_torch.cli.support`: the parser class, argument types, shared help texts, the stdout guard.

``main`` and ``build_parser`` are imported on first use (PEP 562), so the package's import is cheap.

Example:
    >>> from lensdist_torch.cli import build_parser
    >>> build_parser().prog
    'lensdist'
"""

from lensdist_torch._lazy import lazy_exports

#: The public names of the package: module -> the names taken from it.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "lensdist_torch.cli.commands": ("build_parser", "main"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
