"""The wheel holds every package of the source tree (pyproject.toml lists them by hand)."""

from __future__ import annotations

from pathlib import Path

import pytest

tomllib = pytest.importorskip("tomllib")

REPO = Path(__file__).resolve().parents[1]


def test_every_library_package_is_listed_in_pyproject() -> None:
    listed = set(
        tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    src = REPO / "pnvlad_service"
    on_disk = {
        ".".join(("pnvlad_service", *d.relative_to(src).parts)).rstrip(".")
        for d in [src, *(p for p in src.rglob("*") if p.is_dir())]
        if (d / "__init__.py").is_file() or any(d.glob("*.yaml"))
    }
    assert on_disk - listed == set(), "packages missing from pyproject.toml"
    assert {p for p in listed if p.startswith("pnvlad_service")} - on_disk == set()
