"""models.store: save and load round trip, damaged directories refused, and a model named by
its directory or by the training run that made it."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest
import torch

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.factory import build_model
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.store import (
    config_sha256,
    load_model,
    model_identity,
    resolve_model_dir,
    save_model,
    weights_sha256,
)
from tests.models.helpers import CONFIGS, clouds, trained_like


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


def test_save_load_round_trip(tmp_path: Path) -> None:
    cfg = CONFIGS["paper-narrow"]
    model = trained_like(cfg)
    d = save_model(tmp_path / "m", model, cfg, meta={"note": "test", "format": "spoofed"})
    assert sorted(p.name for p in d.iterdir()) == ["model.json", "model.safetensors"]
    doc = json.loads((d / "model.json").read_text())
    assert doc["format"] == "pnvlad-model" and doc["version"] == 1 and doc["note"] == "test"
    assert ModelConfig.model_validate(doc["model"]) == cfg
    assert doc["config_sha256"] == config_sha256(cfg)
    sha = hashlib.sha256((d / "model.safetensors").read_bytes()).hexdigest()
    assert weights_sha256(d) == sha == doc["weights_sha256"]

    loaded, cfg2 = load_model(d)
    assert cfg2 == cfg and not loaded.training
    x = clouds(2)
    with torch.no_grad():
        assert torch.equal(loaded(x), model(x))
    enc = Encoder.from_checkpoint(d)
    assert enc.weights_sha256 == sha == Encoder(model, cfg).weights_sha256
    with pytest.raises(FileExistsError):
        save_model(d, model, cfg)
    save_model(d, build_model(cfg), cfg, overwrite=True)
    assert weights_sha256(d) != sha
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no leftovers


def test_load_refuses_damaged_or_mismatched_dirs(tmp_path: Path) -> None:
    cfg = CONFIGS["compact"]
    d = save_model(tmp_path / "m", trained_like(cfg), cfg)
    with pytest.raises(InputError, match="model directory"):
        load_model(tmp_path / "nope")

    # Flip one byte of the weights: the recorded SHA-256 no longer matches.
    w = d / "model.safetensors"
    data = bytearray(w.read_bytes())
    data[-1] ^= 0xFF
    w.write_bytes(bytes(data))
    with pytest.raises(InputError, match="SHA-256"):
        load_model(d)

    # A config that does not fit the weights: the error lists what is missing and mis-shaped.
    d2 = save_model(tmp_path / "m2", trained_like(cfg), cfg)
    doc = json.loads((d2 / "model.json").read_text())
    doc["model"]["cluster_size"] = 8
    doc["model"]["feature_transform"] = True
    (d2 / "model.json").write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        load_model(d2)
    msg = str(err.value)
    assert "missing" in msg and "feature_tnet.out.weight" in msg
    assert "shape mismatch" in msg and "pool.cluster_weights" in msg

    doc["format"] = "other"
    (d2 / "model.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="format"):
        load_model(d2)
