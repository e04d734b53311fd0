"""Building bundles: listing a tree's submaps, atomic builds, approximate keys and their
recall, appending runs, the sharded (torchrun, gloo) build and the `pnvlad index` commands."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.tree import Submap
from pnvlad_service.errors import InputError
from pnvlad_service.index import build as ib
from pnvlad_service.index.bundle import METADATA_FIELDS, IndexBundle
from pnvlad_service.index.manifest import Manifest
from pnvlad_service.io.submap import read_submap
from pnvlad_service.models.runtimes import load_encoder
from tests.index.helpers import PER_RUN, RUNS, free_port, make_checkpoint


def test_database_submaps_are_the_trees_records(world: dict[str, Path]) -> None:
    records = ib.list_database_submaps(world["tree"])
    assert all(isinstance(r, Submap) for r in records) and len(records) == 2 * PER_RUN
    assert [r.run for r in records] == [RUNS[0]] * PER_RUN + [RUNS[1]] * PER_RUN
    assert records[3].submap_id == f"oxford/{RUNS[0]}/{records[3].timestamp}"
    assert records[3].kind == "test" and records[3].row == 3 and records[3].utm_zone == ""
    assert [r.run for r in ib.list_database_submaps(world["tree"], runs=[RUNS[1]])] == [
        RUNS[1]
    ] * PER_RUN
    with pytest.raises(InputError, match="runs not found"):
        ib.list_database_submaps(world["tree"], runs=["nope"])
    with pytest.raises(InputError, match="no train-layout submaps"):
        ib.list_database_submaps(world["tree"], layout="train")
    with pytest.raises(InputError, match="layout must be"):
        ib.list_database_submaps(world["tree"], layout="val")


def test_embedded_submaps_are_the_encoders_descriptors(world: dict[str, Path], encoder) -> None:
    records = ib.list_database_submaps(world["tree"])[:7]
    got = ib.embed_submaps(encoder, world["tree"], records, batch_size=3, progress=False)
    clouds = np.stack([read_submap(world["tree"] / r.path) for r in records])
    assert clouds.shape == (7, 4096, 3) and clouds.dtype == np.float64
    np.testing.assert_allclose(got, encoder.embed(clouds.astype(np.float32)), atol=1e-5)
    assert ib.embed_submaps(encoder, world["tree"], [], progress=False).shape == (0, 16)


def test_interrupted_build_leaves_no_bundle(world: dict[str, Path], encoder, tmp_path) -> None:
    class Failing:
        dim = encoder.dim
        calls = 0

        def embed(self, points: np.ndarray) -> np.ndarray:
            Failing.calls += 1
            if Failing.calls == 2:
                raise KeyboardInterrupt
            return encoder.embed(points)

    out = tmp_path / "map.index"
    with pytest.raises(KeyboardInterrupt):
        ib.build_bundle(
            out, world["ckpt"], world["tree"], encoder=Failing(), batch_size=4, progress=False
        )
    assert not out.exists()
    # Failing in the writing stage (bad key) also leaves nothing.
    with pytest.raises(InputError):
        ib.build_bundle(out, world["ckpt"], world["tree"], index_key="IVF4,PQ4", progress=False)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == []


def test_existing_bundle_needs_overwrite(world: dict[str, Path]) -> None:
    with pytest.raises(InputError, match="already exists"):
        ib.build_bundle(world["bundle"], world["ckpt"], world["tree"], progress=False)


@pytest.mark.parametrize(
    ("key", "params"), [("HNSW8", {"efSearch": 128}), ("IVF2,Flat", {"nprobe": 2})]
)
def test_approximate_bundles_record_recall(world: dict[str, Path], tmp_path, key, params) -> None:
    rep = ib.build_bundle(
        tmp_path / "b", world["ckpt"], world["tree"], index_key=key, progress=False
    )
    m = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert m["search_params"] == params
    # With every list probed (IVF) or a wide beam on 32 vectors (HNSW) the search is exact.
    assert rep.recall_at_1 == m["recall_at_1_vs_exact"] == 1.0
    assert rep.manifest is not None and rep.manifest.to_json() == m
    b = IndexBundle.load(tmp_path / "b")
    flat = IndexBundle.load(world["bundle"])
    q = np.stack([flat.index.reconstruct(i) for i in range(0, 32, 5)])
    assert b.search(q, 1)[1][:, 0].tolist() == flat.search(q, 1)[1][:, 0].tolist()


def test_pq_with_too_few_vectors_says_how_many(world: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InputError, match="at least 256 vectors"):
        ib.build_bundle(
            tmp_path / "b", world["ckpt"], world["tree"], index_key="IVF2,PQ4", progress=False
        )


def test_build_accepts_a_training_run_directory(world: dict[str, Path], tmp_path: Path) -> None:
    run = tmp_path / "run"
    shutil.copytree(world["ckpt"], run / "model")
    rep = ib.build_bundle(tmp_path / "b", run, world["tree"], progress=False)
    assert rep.manifest is not None
    assert rep.manifest.model.checkpoint == str((run / "model").resolve())
    flat = IndexBundle.load(world["bundle"])
    assert rep.manifest.model.weights_sha256 == flat.manifest.model.weights_sha256
    got = IndexBundle.load(tmp_path / "b").index.reconstruct_n(0, flat.count)
    np.testing.assert_allclose(got, flat.index.reconstruct_n(0, flat.count), atol=1e-6)


# -- add -----------------------------------------------------------------------------------


def test_add_a_run_equals_building_both(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "grow.index"
    ib.build_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[0]], progress=False)
    first = Manifest.read(out)
    ib.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)
    grown, full = IndexBundle.load(out), IndexBundle.load(world["bundle"])
    assert grown.count == full.count == 2 * PER_RUN
    for f in METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(grown.metadata, f), getattr(full.metadata, f))
    q = np.stack([full.index.reconstruct(i) for i in range(full.count)])
    np.testing.assert_array_equal(grown.search(q, 3)[1], full.search(q, 3)[1])
    m = grown.manifest
    assert [e["runs"] for e in m.indexed] == [(RUNS[0],), (RUNS[1],)]  # frozen: tuples
    assert (m.created, m.build, m.model) == (first.created, first.build, first.model)
    assert m.verify_files(out) == {"index.faiss": True, "metadata.npz": True}
    with pytest.raises(InputError, match="already in the bundle"):
        ib.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)


def test_add_refuses_other_weights(world: dict[str, Path], tmp_path: Path) -> None:
    other = make_checkpoint(tmp_path / "other", seed=1)
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    before = (copy / "manifest.json").read_bytes()
    with pytest.raises(InputError, match="other weights") as err:
        ib.add_to_bundle(copy, other, world["tree"], runs=[RUNS[1]], progress=False)
    assert str(copy / "manifest.json") in str(err.value)
    assert str(other / "model.safetensors") in str(err.value)
    assert (copy / "manifest.json").read_bytes() == before


# -- sharded build -------------------------------------------------------------------------


@pytest.mark.slow
def test_sharded_build_equals_single_process(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "sharded.index"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc-per-node",
        "2",
        "--master-port",
        str(free_port()),
        "-m",
        "pnvlad_cli.main",
        "index",
        "build",
        "-m",
        str(world["ckpt"]),
        "-r",
        str(world["tree"]),
        "-o",
        str(out),
        "-b",
        "5",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    sharded, single = IndexBundle.load(out), IndexBundle.load(world["bundle"])
    assert sharded.manifest.build == {"processes": 2, "embed_seconds": pytest.approx(0, abs=1e9)}
    for f in METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(sharded.metadata, f), getattr(single.metadata, f))
    a = sharded.index.reconstruct_n(0, sharded.count)
    b = single.index.reconstruct_n(0, single.count)
    np.testing.assert_allclose(a, b, atol=1e-5)
    assert sharded.manifest.model == single.manifest.model


# -- CLI -----------------------------------------------------------------------------------


def test_cli_build_and_info(world: dict[str, Path], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    runner = CliRunner()
    out = tmp_path / "cli.index"
    args = ["-m", str(world["ckpt"]), "-r", str(world["tree"]), "-o", str(out)]
    res = runner.invoke(app, ["index", "build", *args, "-k", "auto"])
    assert res.exit_code == 0, res.output
    assert "embedded 32 submaps" in res.output and "clouds/s" in res.output
    assert json.loads((out / "manifest.json").read_text())["index_key"] == "Flat"
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 0 and "index.faiss" in res.output and "sha256 OK" in res.output
    assert "[OK (same weights)]" in res.output
    res = runner.invoke(app, ["index", "info", str(out), "--json"])
    doc = json.loads(res.output)
    assert doc["manifest"] == json.loads((out / "manifest.json").read_text())
    assert doc["files_ok"] == {"index.faiss": True, "metadata.npz": True}
    (out / "index.faiss").write_bytes((out / "index.faiss").read_bytes() + b"x")
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 1 and "sha256 MISMATCH" in res.output
    res = runner.invoke(app, ["index", "build", *args])
    assert res.exit_code == 2 and "already exists" in res.output
    args[-1] = str(tmp_path / "x")
    res = runner.invoke(app, ["index", "build", *args, "--run", "nope"])
    assert res.exit_code == 2 and "nope" in res.output


def test_cli_takes_a_training_run_and_the_long_checkpoint_flag(
    world: dict[str, Path], tmp_path: Path
) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    runner = CliRunner()
    run = tmp_path / "run"
    shutil.copytree(world["ckpt"], run / "model")
    out = tmp_path / "run.index"
    tree = ["-r", str(world["tree"])]
    res = runner.invoke(app, ["index", "build", "-m", str(run), *tree, "-o", str(out), *RUNS_0])
    assert res.exit_code == 0, res.output
    assert Manifest.read(out).model.checkpoint == str((run / "model").resolve())
    res = runner.invoke(app, ["index", "add", str(out), "--checkpoint", str(run), *tree, *RUNS_1])
    assert res.exit_code == 0, res.output
    assert f"added {PER_RUN} submaps" in res.output and f"{2 * PER_RUN} vectors" in res.output
    # -c is no model flag any more (it only ever means --config).
    res = runner.invoke(app, ["index", "build", "-c", str(run), *tree, "-o", str(tmp_path / "c")])
    assert res.exit_code == 2 and "No such option" in res.output
    # The recorded model gone or changed shows in `info`.
    shutil.rmtree(run / "model")
    make_checkpoint(run / "model", seed=1)
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 0 and "[DIFFERENT weights]" in res.output
    shutil.rmtree(run)
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 0 and "[missing]" in res.output


RUNS_0 = ["--run", RUNS[0]]
RUNS_1 = ["--run", RUNS[1]]


def test_load_encoder_takes_the_known_weights_hash_or_hashes_itself(world) -> None:
    from pnvlad_service.models.store import model_identity, weights_sha256

    ident = model_identity(world["ckpt"])
    want = weights_sha256(world["ckpt"])
    assert load_encoder(world["ckpt"]).weights_sha256 == want
    assert load_encoder(world["ckpt"], identity=ident).weights_sha256 == want


def test_a_bev_netvlad_model_builds_a_bundle_that_finds_each_submap(
    world: dict[str, Path], tmp_path: Path
) -> None:
    """The bird's-eye model goes the PointNet models' way: checkpoint, encoder, bundle; each
    database submap, embedded again, is its own nearest neighbour at distance 0."""
    import torch

    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import save_model

    torch.manual_seed(0)
    cfg = ModelConfig.bev(bev_widths=(8, 16), bev_strides=(2, 2), cluster_size=4, output_dim=16)
    ckpt = save_model(tmp_path / "bev", build_model(cfg).eval(), cfg)
    bundle = tmp_path / "bev.index"
    ib.build_bundle(bundle, ckpt, world["tree"], progress=False)
    b = IndexBundle.load(bundle)
    records = ib.list_database_submaps(world["tree"])
    desc = ib.embed_submaps(load_encoder(ckpt), world["tree"], records, progress=False)
    dist, ids = b.search(desc, 1)
    assert b.dim == 16 and b.count == len(records)
    assert ids[:, 0].tolist() == list(range(len(records)))
    np.testing.assert_allclose(dist[:, 0], 0, atol=1e-5)


def test_a_map_of_a_heading_model_holds_four_turns_an_entry(
    world: dict[str, Path], tmp_path: Path
) -> None:
    """A model that turns clouds to their own heading knows it only modulo a quarter turn: its
    map holds every entry at the four quarter turns, and a query turned by any of them finds
    its entry first, at distance 0, once; `index add` keeps the four."""
    from pnvlad_service.models.embedding import quarter_turn
    from pnvlad_service.models.inference import Encoder

    ckpt = make_checkpoint(tmp_path / "heading", canonical_heading=True)
    runs = ib.list_database_submaps(world["tree"])
    first = sorted({r.run for r in runs})[0]
    out = ib.build_bundle(tmp_path / "turned.index", ckpt, world["tree"], runs=[first],
                          progress=False)  # fmt: skip
    bundle = IndexBundle.load(out.path)
    n = len([r for r in runs if r.run == first])
    assert bundle.turns == 4 and bundle.count == n and bundle.index.ntotal == 4 * n
    assert bundle.manifest.map_record.turns == 4 and out.count == n
    enc = Encoder.from_checkpoint(ckpt)
    rec = [r for r in runs if r.run == first][2]
    cloud = read_submap(world["tree"] / rec.path).astype(np.float32)
    for k in range(4):
        d, ids = bundle.search(enc.embed(quarter_turn(cloud, k)[None]), 5)
        assert ids[0, 0] == 2 and d[0, 0] < 1e-5
        assert len(set(ids[0].tolist())) == 5  # each entry once, at its nearest turn
    others = sorted({r.run for r in runs} - {first})
    ib.add_to_bundle(out.path, ckpt, world["tree"], runs=others, progress=False)
    grown = IndexBundle.load(out.path)
    assert grown.count == len(runs) and grown.index.ntotal == 4 * len(runs)


def test_a_tree_says_how_its_windows_laid_scans_only_where_its_runs_agree(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The bundle's G and window settings come from the runs' prepare records: the same in
    every run, they are the tree's; G differing refuses the build, windows differing leave
    the bundle without window settings (and say so)."""
    import json
    from types import SimpleNamespace

    from pnvlad_service.errors import InputError
    from pnvlad_service.index.tree_records import tree_accumulation, tree_preprocess_config

    def record(run: str, points: int, g: dict) -> SimpleNamespace:
        d = tmp_path / "area" / run
        d.mkdir(parents=True, exist_ok=True)
        doc = {"max_points_per_scan": points, "min_scan_spacing_m": 0.05, "max_range_m": None,
               "g_config": g}  # fmt: skip
        (d / ".prepare-pointcloud_20m.json").write_text(json.dumps(doc))
        return SimpleNamespace(path=f"area/{run}/pointcloud_20m/1.bin", kind="test")

    g = {"target_points": 4096}
    same = [record("a", 8000, g), record("b", 8000, g)]
    assert tree_accumulation(tmp_path, same) == {"max_points_per_scan": 8000,
                                                 "min_scan_spacing_m": 0.05}  # fmt: skip
    assert tree_preprocess_config(tmp_path, same) == g
    mixed = [*same, record("c", 3000, g)]
    with caplog.at_level("WARNING"):
        assert tree_accumulation(tmp_path, mixed) is None
    assert "area/c differs" in caplog.text
    with pytest.raises(InputError, match="area/d differs"):
        tree_preprocess_config(tmp_path, [*same, record("d", 8000, {"target_points": 1024})])
