"""Optional dependencies (the package's extras), imported where a feature first needs them:
a missing one is a :class:`~pnvlad_service.errors.MissingDependencyError` naming the extra."""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

from pnvlad_service.errors import MissingDependencyError


def require(module: str, package: str, extra: str | None, feature: str) -> ModuleType:
    """``import module``; when it is not installed, MissingDependencyError: ``feature`` needs
    ``package``, from ``pip install 'pnvlad[extra]'`` (``pip install package`` for a core
    dependency, ``extra`` None)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingDependencyError(package, extra, feature) from None


def pyplot(feature: str) -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures written to files)."""
    matplotlib = require("matplotlib", "matplotlib", "plot", feature)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
