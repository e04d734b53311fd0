"""The index tests' shared world: a tiny tree, a small model and a Flat bundle of the tree,
built once for the package."""

from __future__ import annotations

from pathlib import Path

import pytest

from pnvlad_service.index.build import build_bundle, load_encoder
from tests.index.helpers import make_checkpoint, make_tree


@pytest.fixture(scope="package")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("index")
    tree = make_tree(base / "tree")
    ckpt = make_checkpoint(base / "ckpt")
    bundle = base / "flat.index"
    build_bundle(bundle, ckpt, tree, progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "bundle": bundle}


@pytest.fixture(scope="package")
def encoder(world: dict[str, Path]):
    return load_encoder(world["ckpt"])
