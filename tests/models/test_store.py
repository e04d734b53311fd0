"""models.store: a model is named by its directory or by the training run that made it."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.pointnetvlad import build_model
from pnvlad_service.models.store import model_identity, resolve_model_dir, save_model


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cfg = ModelConfig.compact().model_copy(update={"num_points": 64})
    out = tmp_path_factory.mktemp("run") / "model"
    save_model(out, build_model(cfg), cfg)
    return out


def test_model_dir_and_run_dir_name_the_same_model(model_dir: Path) -> None:
    assert resolve_model_dir(model_dir) == model_dir
    assert resolve_model_dir(model_dir.parent) == model_dir  # the run's OUT/model
    a, b = model_identity(model_dir), model_identity(model_dir.parent)
    assert a == b
    want = hashlib.sha256((model_dir / "model.safetensors").read_bytes()).hexdigest()
    assert a.weights_sha256 == want
    assert a.checkpoint == str(model_dir.resolve())
    assert a.to_json()["config"]["num_points"] == 64


def test_model_files_get_the_umask_permissions(model_dir: Path) -> None:
    """safetensors writes 0600; a model must be readable as any other output is (umask 022:
    0644), e.g. by the container image's uid 10001 (scripts/image_test.sh)."""
    umask = os.umask(0)
    os.umask(umask)
    for f in ("model.safetensors", "model.json"):
        assert (model_dir / f).stat().st_mode & 0o777 == 0o666 & ~umask, f


def test_unfinished_run_and_other_folders_are_refused(tmp_path: Path) -> None:
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    with pytest.raises(InputError, match="has not finished") as exc:
        resolve_model_dir(tmp_path / "run")
    assert exc.value.source == str(tmp_path / "run")
    with pytest.raises(InputError, match="not a model directory"):
        resolve_model_dir(tmp_path)
    with pytest.raises(InputError, match="not found"):
        resolve_model_dir(tmp_path / "missing")
