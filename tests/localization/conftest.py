"""One small world for the localisation tests: a benchmark tree, a model and its bundle."""

from __future__ import annotations

from pathlib import Path

import pytest

from pnvlad_service.index import build as ix
from tests.index.helpers import make_checkpoint, make_tree


@pytest.fixture(scope="package")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``tree``, ``ckpt`` (a model directory) and ``bundle`` (built from both)."""
    base = tmp_path_factory.mktemp("localization")
    tree = make_tree(base / "tree")
    ckpt = make_checkpoint(base / "ckpt")
    ix.build_bundle(base / "map.index", ckpt, tree, progress=False)
    return {"tree": tree, "ckpt": ckpt, "bundle": base / "map.index"}
