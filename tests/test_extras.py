"""extras: an optional dependency that is missing names its package and extra."""

from __future__ import annotations

import sys

import pytest

from pnvlad_service.errors import MissingDependencyError
from pnvlad_service.extras import pyplot, require


def test_require_returns_the_module() -> None:
    import json

    assert require("json", "json", "io", "a feature") is json


def test_a_missing_module_is_a_missing_dependency(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "some_extra_pkg", None)  # makes the import fail
    with pytest.raises(MissingDependencyError) as exc:
        require("some_extra_pkg", "some-extra-pkg", "io", "Reading things")
    assert str(exc.value) == (
        "Reading things needs the 'some-extra-pkg' package, which is not installed. "
        "Install it with: pip install 'pnvlad[io]'"
    )
    assert isinstance(exc.value, ImportError)


def test_pyplot_without_matplotlib_names_the_plot_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(MissingDependencyError, match=r"figures needs the 'matplotlib' .*\[plot\]"):
        pyplot("figures")


def test_pyplot_is_on_the_agg_backend() -> None:
    pytest.importorskip("matplotlib")
    plt = pyplot("figures")
    assert plt.get_backend().lower() == "agg"
