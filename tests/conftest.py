"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def real_scans_dir() -> Path | None:
    """The folder of real LiDAR scans: $PNVLAD_REAL_SCANS or ../shared/data/real_scans."""
    env = os.environ.get("PNVLAD_REAL_SCANS")
    candidates = [Path(env)] if env else []
    candidates.append(REPO.parent / "shared" / "data" / "real_scans")
    for c in candidates:
        if (c / "kitti00_000000.bin").is_file():
            return c
    return None


@pytest.fixture(scope="session")
def real_scans() -> Path:
    """Path of the real scans folder; skips the test where it is absent."""
    d = real_scans_dir()
    if d is None:
        pytest.skip(
            "real scans not found (set PNVLAD_REAL_SCANS or provide ../shared/data/real_scans)"
        )
    return d


@pytest.fixture(scope="session")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`pnvlad synth --preset tiny --seed 3` (two workers), generated once for every test that
    reads it (synth, verification); tests must not change it."""
    from pnvlad_service.synth.generate import generate

    root = tmp_path_factory.mktemp("synth") / "tiny"
    generate("tiny", root, seed=3, workers=2, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_maps(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Bundles of the tiny city's runs but the first, built with one random model (``ckpt``):
    ``map`` with geometry (verification), ``plain`` without, ``keys`` of the keyframe maps
    (single scans); ``query_run`` is the run left out."""
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.build import build_bundle
    from tests.index.helpers import make_checkpoint

    base = tmp_path_factory.mktemp("tiny_maps")
    tree = BenchmarkTree(tiny)
    runs = tree.runs("business")
    ckpt = make_checkpoint(base / "ckpt")
    build_bundle(base / "map.index", ckpt, tiny, runs=runs[1:], progress=False)
    build_bundle(base / "plain.index", ckpt, tiny, runs=runs[1:], progress=False, geometry="off")
    build_bundle(base / "keys.index", ckpt, tiny, runs=runs[1:], progress=False, layout="keyframe")
    return {
        "base": base,
        "tree": tree,
        "query_run": runs[0],
        "ckpt": ckpt,
        "map": base / "map.index",
        "plain": base / "plain.index",
        "keys": base / "keys.index",
    }


@pytest.fixture(scope="session")
def tiny_aligned(tiny: Path, tiny_maps: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The tiny city through ``pnvlad map align`` (``tree``) and the keyframe bundle of its runs
    but the first (``keys``, as ``tiny_maps``'s, built with its ``ckpt``)."""
    pytest.importorskip("gtsam")
    from pnvlad_service.index.build import build_bundle
    from pnvlad_service.mapping.align import align_map

    base = tmp_path_factory.mktemp("tiny_aligned")
    align_map(tiny, base / "tiny-aligned")
    runs = tiny_maps["tree"].runs("business")
    keys = base / "keys.index"
    build_bundle(keys, tiny_maps["ckpt"], base / "tiny-aligned", runs=runs[1:], progress=False,
                 layout="keyframe")  # fmt: skip
    return {"tree": base / "tiny-aligned", "keys": keys, "ckpt": tiny_maps["ckpt"]}
