"""One small world for the localisation tests: a benchmark tree, a model and its bundle."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.index.helpers import make_world


@pytest.fixture(scope="package")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``tree``, ``ckpt`` (a model directory) and ``bundle`` (built from both)."""
    return make_world(tmp_path_factory.mktemp("localization"))
