"""The index tests' shared world: a tiny tree, a small model and a Flat bundle of the tree,
built once for the package."""

from __future__ import annotations

from pathlib import Path

import pytest

from pnvlad_service.models.runtimes import load_encoder
from tests.index.helpers import make_world


@pytest.fixture(scope="package")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_world(tmp_path_factory.mktemp("index"), "flat.index")


@pytest.fixture(scope="package")
def encoder(world: dict[str, Path]):
    return load_encoder(world["ckpt"])
