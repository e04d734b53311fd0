"""The typed, frozen manifest: what it records, the exact JSON round trip of bundles on disk,
immutability, the model-compatibility check and the file checks."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.index.manifest import KEYS, MANIFEST_FILE, Manifest, ModelRecord
from pnvlad_service.models.store import model_identity
from tests.index.helpers import PER_RUN, RUNS, make_checkpoint


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def test_manifest_records_model_files_and_what_was_indexed(world: dict[str, Path]) -> None:
    m = json.loads((world["bundle"] / "manifest.json").read_text())
    assert (m["format"], m["version"], m["dim"], m["metric"]) == ("pnvlad-index", 1, 16, "l2")
    assert m["index_key"] == "Flat" and m["count"] == 2 * PER_RUN
    assert m["model"]["weights_sha256"] == _sha(world["ckpt"] / "model.safetensors")
    assert m["model"]["checkpoint"] == str(world["ckpt"].resolve())
    for name in ("index.faiss", "metadata.npz"):
        assert m["files"][name] == _sha(world["bundle"] / name)
    assert m["indexed"][0]["runs"] == list(RUNS) and m["indexed"][0]["layout"] == "test"
    assert m["recall_at_1_vs_exact"] is None  # exact index
    assert m["created"].endswith("+00:00")
    assert m["build"] == {"processes": 1, "embed_seconds": m["build"]["embed_seconds"]}


def test_typed_fields_are_the_files_values(world: dict[str, Path]) -> None:
    doc = json.loads((world["bundle"] / MANIFEST_FILE).read_text())
    man = Manifest.read(world["bundle"])
    assert (man.dim, man.count, man.index_key) == (doc["dim"], doc["count"], doc["index_key"])
    assert man.model.weights_sha256 == doc["model"]["weights_sha256"]
    assert man.model.config["output_dim"] == 16
    assert dict(man.files) == doc["files"] and man.path == world["bundle"]
    assert man.preprocess is not None and man.preprocess["target_points"] == 4096


def test_round_trip_is_exactly_the_file(world: dict[str, Path], tmp_path: Path) -> None:
    doc = json.loads((world["bundle"] / MANIFEST_FILE).read_text())
    back = Manifest.read(world["bundle"]).to_json()
    assert back == doc
    assert list(back) == list(doc)  # the file's key order too
    assert list(doc)[: len(KEYS)] == list(KEYS)
    # Keys this version does not know survive the round trip.
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    (copy / MANIFEST_FILE).write_text(json.dumps({**doc, "note": {"by": ["me"]}}))
    man = Manifest.read(copy)
    assert man.extra == {"note": {"by": ("me",)}}
    assert man.to_json() == {**doc, "note": {"by": ["me"]}}


def test_manifest_is_frozen_all_the_way_down(world: dict[str, Path]) -> None:
    man = Manifest.read(world["bundle"])
    with pytest.raises(dataclasses.FrozenInstanceError):
        man.count = 0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        man.model.weights_sha256 = "0" * 64  # type: ignore[misc]
    with pytest.raises(TypeError):
        man.files["index.faiss"] = "0"  # type: ignore[index]
    with pytest.raises(TypeError):
        man.model.config["output_dim"] = 3  # type: ignore[index]
    with pytest.raises(TypeError):
        man.indexed[0]["count"] = 3  # type: ignore[index]
    # to_json hands out plain copies: changing them leaves the manifest as it was.
    doc = man.to_json()
    doc["model"]["config"]["output_dim"] = 3
    assert man.model.config["output_dim"] == 16


def test_check_model_accepts_the_same_weights(world: dict[str, Path], tmp_path: Path) -> None:
    man = Manifest.read(world["bundle"])
    man.check_model(model_identity(world["ckpt"]))
    run = tmp_path / "run"  # a training run directory: its model/ is the model
    shutil.copytree(world["ckpt"], run / "model")
    man.check_model(model_identity(run))


def test_check_model_refuses_other_weights_naming_both_files(
    world: dict[str, Path], tmp_path: Path
) -> None:
    other = make_checkpoint(tmp_path / "other", seed=1)
    man = Manifest.read(world["bundle"])
    with pytest.raises(InputError, match="other weights") as err:
        man.check_model(model_identity(other))
    text = str(err.value)
    assert str(world["bundle"] / MANIFEST_FILE) in text
    assert str(other.resolve() / "model.safetensors") in text
    assert man.model.weights_sha256[:16] in text and _sha(other / "model.safetensors")[:16] in text
    # Another model record with the same weights file is the same model.
    same = dataclasses.replace(man, model=ModelRecord(None, man.model.weights_sha256, "", {}))
    same.check_model(model_identity(world["ckpt"]))


def test_verify_files_reports_each_file(world: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    man = Manifest.read(copy)
    assert man.verify_files(copy) == {"index.faiss": True, "metadata.npz": True}
    (copy / "index.faiss").write_bytes(b"x")
    (copy / "metadata.npz").unlink()
    assert man.verify_files(copy) == {"index.faiss": False, "metadata.npz": False}


def test_read_refuses_what_is_not_a_manifest(world: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InputError, match="directory not found"):
        Manifest.read(tmp_path / "nowhere")
    with pytest.raises(InputError, match=r"no manifest\.json"):
        Manifest.read(tmp_path)
    doc = json.loads((world["bundle"] / MANIFEST_FILE).read_text())
    cases = [
        ("{not json", "not valid JSON"),
        (json.dumps({**doc, "format": "other"}), "not a pnvlad-index manifest"),
        (json.dumps({**doc, "version": 3}), "version 3 is not supported"),
        (json.dumps({**doc, "version": True}), "version True is not supported"),
        (json.dumps({k: v for k, v in doc.items() if k != "count"}), r"lacks the keys \['count'\]"),
        (json.dumps({**doc, "dim": "16"}), r"wrong type: \['dim'\]"),
        (json.dumps({**doc, "model": {"checkpoint": None}}), "model entry lacks the keys"),
    ]
    for text, message in cases:
        (tmp_path / MANIFEST_FILE).write_text(text)
        with pytest.raises(InputError, match=message):
            Manifest.read(tmp_path)


def test_a_bundle_written_before_the_typed_manifest_loads_unchanged() -> None:
    """tests/index/bundle_v1: 8 vectors written by the dict-manifest code (commit d61b219)."""
    from pnvlad_service.index.bundle import IndexBundle

    old = Path(__file__).parent / "bundle_v1"
    doc = json.loads((old / MANIFEST_FILE).read_text())
    assert Manifest.read(old).to_json() == doc
    bundle = IndexBundle.load(old)
    assert (bundle.count, bundle.dim, bundle.key) == (8, 16, "Flat")
    assert bundle.manifest.model.weights_sha256 == doc["model"]["weights_sha256"]
    assert bundle.manifest.build == {"processes": 1, "embed_seconds": doc["build"]["embed_seconds"]}


def test_map_record_carries_how_windows_were_laid() -> None:
    from pnvlad_service.index.manifest import MapRecord

    doc = {"kind": "submap", "layout": "test", "turns": 1,
           "accumulation": {"max_points_per_scan": 8000, "min_scan_spacing_m": 0.05}}  # fmt: skip
    rec = MapRecord.from_json(doc)
    assert rec.to_json() == doc and rec.accumulation["max_points_per_scan"] == 8000
    assert "accumulation" not in MapRecord.from_json({"kind": "submap"}).to_json()
    for bad in ({"max_points_per_scan": "all"}, [8000], {"max_range_m": True}):
        with pytest.raises(InputError, match="accumulation") as err:
            MapRecord.from_json({**doc, "accumulation": bad}, "b/manifest.json")
        assert str(err.value.source) == "b/manifest.json"
