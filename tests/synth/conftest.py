"""The tiny synthetic tree, generated once for every synth test that reads it."""

from __future__ import annotations

from pathlib import Path

import pytest

from pnvlad_service.synth.generate import generate


@pytest.fixture(scope="session")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`pnvlad synth --preset tiny --seed 3` (two workers); tests must not change it."""
    root = tmp_path_factory.mktemp("synth") / "tiny"
    generate("tiny", root, seed=3, workers=2, progress=False)
    return root
