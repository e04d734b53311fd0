"""models.onnx_graph and models.onnx_export: the encoder as an ONNX graph on ONNX Runtime
against torch (the folded ``Encoder`` and the module itself), for every architecture and
switch, with and without canonical heading, on synthetic and real clouds, batched and one
cloud at a time; what an export writes and refuses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from pnvlad_service.errors import InputError, PnvladError
from pnvlad_service.models import onnx_export
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.heading import GRID
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.onnx_encoder import (
    ONNX_FILE,
    OnnxEncoder,
    OnnxRecord,
    check_clouds,
    cosines,
    encode_array,
)
from pnvlad_service.models.onnx_graph import HEADING_GRID, build_graph
from pnvlad_service.models.store import save_model
from tests.models.helpers import BEV_SMALL, CONFIGS, clouds, trained_like

#: The issue's bar: every descriptor within this cosine of torch's.
MIN_COS = 0.9999

ALL = {**CONFIGS, "bev-small": BEV_SMALL}


def trained_bev_like(cfg: ModelConfig, seed: int = 0) -> torch.nn.Module:
    """``trained_like`` with its 2-D batch norms moved off the identity too."""
    model = trained_like(cfg, seed)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                c = m.num_features
                m.weight.copy_(torch.rand(c, generator=g) + 0.5)
                m.bias.copy_(torch.rand(c, generator=g) * 0.6 - 0.3)
                m.running_mean.copy_(torch.rand(c, generator=g) * 0.4 - 0.2)
                m.running_var.copy_(torch.rand(c, generator=g) * 1.5 + 0.5)
    return model.eval()


def onnx_of(model: torch.nn.Module, cfg: ModelConfig, tile: int = 64) -> OnnxEncoder:
    """ONNX Runtime on the graph of ``model`` (no file, no self-check)."""
    desc = np.zeros((1, cfg.output_dim), dtype=np.float32)
    meta = OnnxRecord("w", "c", 0, cfg.num_points, desc, tile, "").metadata()
    proto = build_graph(cfg, onnx_export.folded_params(model), point_tile=tile, metadata=meta)
    return OnnxEncoder(
        "model.onnx", cfg, "w", threads=2, check=False, data=proto.SerializeToString()
    )


def test_heading_grid_is_the_models() -> None:
    assert HEADING_GRID == GRID


@pytest.mark.parametrize("heading", [False, True], ids=["aligned", "canonical-heading"])
@pytest.mark.parametrize(("name", "tile"), [(n, 64) for n in sorted(ALL)] + [("compact", 0)])
def test_graph_matches_torch(name: str, tile: int, heading: bool) -> None:
    """Descriptors of 5 clouds (batched, and one at a time) within cosine 0.9999 of the folded
    encoder's and of the module's own forward pass; in practice within 1e-5."""
    cfg = ALL[name].model_copy(update={"canonical_heading": heading})
    model = trained_bev_like(cfg) if cfg.arch == "bev-netvlad" else trained_like(cfg)
    x = np.concatenate([check_clouds(3, 3, 300), clouds(2, n=300, seed=4).numpy()])
    want = Encoder(model, cfg).embed(x)
    with torch.no_grad():
        module = model(torch.from_numpy(x)).numpy()
    ort = onnx_of(model, cfg, tile)
    got = ort.embed(x)
    one = np.concatenate([ort.embed(c) for c in x])
    ort.close()
    assert got.shape == (5, cfg.output_dim) and got.dtype == np.float32
    for other in (want, module):
        assert cosines(got, other).min() >= MIN_COS
        assert cosines(one, other).min() >= MIN_COS
        assert np.abs(got - other).max() < 1e-4
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


def test_graph_refuses_local_shape_features() -> None:
    cfg = ModelConfig.compact(local_k=8)
    with pytest.raises(ValueError, match="local_k"):
        build_graph(cfg, onnx_export.folded_params(trained_like(cfg)))


@pytest.fixture(scope="module")
def real_clouds(real_scans: Path) -> np.ndarray:
    """Five real scans (KITTI, nuScenes, NCLT) through the filter G: float32 [5, 4096, 3]."""
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.preprocess.filter_g import GConfig, apply_g

    files = [
        ("kitti00_000000.bin", "kitti"),
        ("kitti00_000052.bin", "kitti"),
        ("kitti00_004501.bin", "kitti"),
        ("nuscenes_lidar_top.bin", "nuscenes"),
        ("nclt_1326652795280148.bin", "nclt"),
    ]
    out = [apply_g(read_points(real_scans / f, r), GConfig(), seed=0).points for f, r in files]
    return np.stack(out).astype(np.float32)


@pytest.mark.real_scans
@pytest.mark.parametrize("heading", [False, True], ids=["aligned", "canonical-heading"])
@pytest.mark.parametrize("preset", ["paper", "compact", "bev"])
def test_real_scans_match_torch(real_clouds: np.ndarray, preset: str, heading: bool) -> None:
    """The shipped configurations at full size on real scans through G."""
    torch.manual_seed(1)
    cfg = getattr(ModelConfig, preset)(canonical_heading=heading)
    model = trained_bev_like(cfg) if cfg.arch == "bev-netvlad" else trained_like(cfg)
    want = Encoder(model, cfg).embed(real_clouds)
    ort = onnx_of(model, cfg, tile=512)
    got = ort.embed(real_clouds)
    ort.close()
    assert cosines(got, want).min() >= MIN_COS


# --------------------------------------------------------------------------------------------
# pnvlad model export
# --------------------------------------------------------------------------------------------


def _model_dir(path: Path, cfg: ModelConfig, seed: int = 0) -> Path:
    model = trained_bev_like(cfg, seed) if cfg.arch == "bev-netvlad" else trained_like(cfg, seed)
    save_model(path, model, cfg)
    return path


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = _model_dir(tmp_path_factory.mktemp("export") / "m", CONFIGS["paper-narrow"])
    onnx_export.export_onnx(d, point_tile=100)
    return d


def test_export_writes_a_checked_file_with_its_identity(exported: Path) -> None:
    import onnx

    from pnvlad_service.models.store import model_identity

    proto = onnx.load(str(exported / ONNX_FILE))
    meta = {p.key: p.value for p in proto.metadata_props}
    ident = model_identity(exported)
    assert meta["pnvlad.weights_sha256"] == ident.weights_sha256
    assert meta["pnvlad.config_sha256"] == ident.config_sha256
    check = json.loads(meta["pnvlad.check"])
    assert check["seed"] == onnx_export.CHECK_SEED and check["points"] == 256
    # Dynamic batch and point count; one input and one output, named.
    (inp,) = proto.graph.input
    dims = [d.dim_param or d.dim_value for d in inp.type.tensor_type.shape.dim]
    assert inp.name == "points" and dims == ["batch", "points", 3]
    assert [o.name for o in proto.graph.output] == ["descriptor"]
    # The recorded descriptors are the torch encoder's of the seeded clouds.
    rec = OnnxRecord.from_metadata(meta, exported / ONNX_FILE)
    enc = Encoder.from_checkpoint(exported)
    assert np.abs(enc.embed(rec.clouds()) - rec.check_descriptors).max() < 1e-6
    # And the encoder loads it, self-check included, for any batch size.
    ort = OnnxEncoder.from_checkpoint(exported, threads=2)
    x = clouds(7, seed=9).numpy()
    assert cosines(ort.embed(x), enc.embed(x)).min() >= MIN_COS
    assert ort.weights_sha256 == ident.weights_sha256
    ort.close()


def test_export_checks_given_clouds_and_writes_nothing_when_they_differ(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = _model_dir(tmp_path / "m", CONFIGS["compact"])
    report = onnx_export.export_onnx(d, points=clouds(3, seed=5).numpy())
    assert report.clouds == onnx_export.CHECK_CLOUDS + 3 and report.min_cosine >= MIN_COS
    (d / ONNX_FILE).unlink()
    monkeypatch.setattr(onnx_export, "MIN_COSINE", 1.5)  # no descriptor can pass
    with pytest.raises(PnvladError, match=r"check cloud \d is at cosine .* nothing written"):
        onnx_export.export_onnx(d)
    assert sorted(p.name for p in d.iterdir()) == ["model.json", "model.safetensors"]


def test_onnx_beside_other_weights_is_refused_naming_both(exported: Path, tmp_path: Path) -> None:
    import shutil

    d = tmp_path / "m"
    shutil.copytree(exported, d)
    _model_dir(tmp_path / "other", CONFIGS["paper-narrow"], seed=1)
    shutil.copy(tmp_path / "other" / "model.safetensors", d / "model.safetensors")
    shutil.copy(tmp_path / "other" / "model.json", d / "model.json")
    with pytest.raises(InputError, match="exported from other weights") as exc:
        OnnxEncoder.from_checkpoint(d)
    assert str(d / ONNX_FILE) in str(exc.value) and str(d / "model.safetensors") in str(exc.value)


def test_onnx_of_another_configuration_is_refused(exported: Path, tmp_path: Path) -> None:
    import shutil

    d = tmp_path / "m"
    shutil.copytree(exported, d)
    doc = json.loads((d / "model.json").read_text())
    doc["model"]["canonical_heading"] = True
    (d / "model.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="another configuration") as exc:
        OnnxEncoder.from_checkpoint(d)
    assert str(d / "model.json") in str(exc.value)


def test_wrong_recorded_descriptors_fail_the_self_check(exported: Path, tmp_path: Path) -> None:
    import shutil

    import onnx

    d = tmp_path / "m"
    shutil.copytree(exported, d)
    proto = onnx.load(str(d / ONNX_FILE))
    meta = {p.key: p.value for p in proto.metadata_props}
    rec = OnnxRecord.from_metadata(meta, d / ONNX_FILE)
    check = json.loads(meta["pnvlad.check"])
    check["descriptors"] = encode_array(-rec.check_descriptors)
    onnx.helper.set_model_props(proto, {**meta, "pnvlad.check": json.dumps(check)})
    onnx.save(proto, str(d / ONNX_FILE))
    with pytest.raises(InputError, match="descriptors of the check clouds differ"):
        OnnxEncoder.from_checkpoint(d)


def test_a_foreign_onnx_file_is_refused(exported: Path, tmp_path: Path) -> None:
    import shutil

    import onnx

    d = tmp_path / "m"
    shutil.copytree(exported, d)
    proto = onnx.load(str(d / ONNX_FILE))
    del proto.metadata_props[:]
    onnx.save(proto, str(d / ONNX_FILE))
    with pytest.raises(InputError, match="not an ONNX file that pnvlad exported"):
        OnnxEncoder.from_checkpoint(d)


def test_the_same_top1_on_the_tiny_citys_submaps(tiny: Path, tmp_path: Path) -> None:
    """Every submap of the tiny city (the test and the training layouts, leave-one-out nearest
    neighbour among them) has the same top-1 under both runtimes, for PN_VLAD and bev-netvlad
    with canonical heading. (The 1,000-submap check with trained weights:
    benchmarks/bench_runtime.py --root.)"""
    from pnvlad_service.index.build import list_database_submaps
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.models.inference import other_distances

    records = [*list_database_submaps(tiny), *list_database_submaps(tiny, layout="train")]
    x = np.stack([read_points(tiny / r.path, "benchmark") for r in records]).astype(np.float32)
    for name, cfg in [
        ("compact", ModelConfig.compact()),
        ("bev", ModelConfig.bev(canonical_heading=True)),
    ]:
        d = _model_dir(tmp_path / name, cfg)
        onnx_export.export_onnx(d)
        want = Encoder.from_checkpoint(d).embed(x)
        ort = OnnxEncoder.from_checkpoint(d, threads=2)
        got = ort.embed(x)
        ort.close()
        assert len(x) >= 100
        assert cosines(got, want).min() >= MIN_COS
        assert (other_distances(got).argmin(1) == other_distances(want).argmin(1)).all(), name


def test_onnx_runtime_averages_over_the_embed_scales_as_torch_does() -> None:
    """``embed_scales`` is applied outside the graph: ONNX Runtime's descriptors of the
    rescaled clouds averaged are torch's, and differ from those of the clouds as given."""
    cfg = BEV_SMALL.model_copy(update={"embed_scales": (0.85, 1.0, 1.18)})
    model = trained_bev_like(cfg)
    x = clouds(4, n=300, seed=9).numpy() * 0.8
    want = Encoder(model, cfg).embed(x)
    got = onnx_of(model, cfg).embed(x)
    assert cosines(got, want).min() >= MIN_COS
    plain = onnx_of(model, BEV_SMALL).embed(x)
    assert np.abs(got - plain).max() > 10 * np.abs(got - want).max()
