"""Lazy exports of a package (PEP 562): a name is imported from its module on first access.

The one implementation behind ``lensdist_torch`` and its subpackages (``core``, ``classify``,
``data``, ``geometry``, ``metric``, ``registration``, ``selfcal``, ``calibration``, ``workflows``): each
holds a table, module -> the names taken from it, and gets its ``__all__``, ``__getattr__`` and
``__dir__`` from :func:`lazy_exports`. Importing a package, or one of its modules, therefore
loads none of the modules its table names.
"""

from __future__ import annotations

import importlib
import sys
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, exports: Mapping[str, tuple[str, ...]]
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``__all__``, ``__getattr__`` and ``__dir__`` of ``package`` from its table of exports.

    A name is imported from the module that the table names on its first access and cached in
    the package's namespace, so later accesses are plain attribute look-ups.

    Args:
        package: The package's dotted name (its ``__name__``).
        exports: Module (dotted name) -> the names the package takes from it; a name appears once.

    Returns:
        ``(__all__, __getattr__, __dir__)``: the sorted names, the module-level ``__getattr__``
        that imports them (any other name raises ``AttributeError``) and ``__dir__``, which lists
        the package's namespace and every exported name.

    Raises:
        ValueError: If a name appears twice in ``exports``.

    Example:
        >>> import sys, types
        >>> pkg = types.ModuleType("demo_pkg")
        >>> sys.modules["demo_pkg"] = pkg
        >>> pkg.__all__, pkg.__getattr__, pkg.__dir__ = lazy_exports("demo_pkg", {"math": ("sqrt",)})
        >>> pkg.__all__, pkg.sqrt(9.0), "sqrt" in vars(pkg)
        (['sqrt'], 3.0, True)
        >>> pkg.cbrt
        Traceback (most recent call last):
        ...
        AttributeError: module 'demo_pkg' has no attribute 'cbrt'
        >>> del sys.modules["demo_pkg"]
    """
    counts = Counter(name for names in exports.values() for name in names)
    repeated = sorted(name for name, count in counts.items() if count > 1)
    if repeated:
        raise ValueError(f"{package}: names exported twice: {', '.join(repeated)}")
    home = {name: module for module, names in exports.items() for name in names}
    names = sorted(home)

    def __getattr__(name: str) -> Any:
        if name not in home:
            raise AttributeError(f"module '{package}' has no attribute {name!r}")
        value = getattr(importlib.import_module(home[name]), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return list(names), __getattr__, __dir__
