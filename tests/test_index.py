"""Index bundles: exact search against a plain loop, metadata and manifest round trips, hash
checks, atomic builds, the auto key at the FAISS guideline boundaries, approximate recall,
appending runs, the sharded (torchrun, gloo) build and the `pnvlad index` commands.

The helpers at the top (a tiny benchmark tree, a small random model) are shared with
test_server.py and test_localize.py.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.index import bundle as ix

RUNS = ("2014-05-19-13-20-57", "2014-06-26-09-24-58")
PER_RUN = 16


def make_tree(root: Path, runs: tuple[str, ...] = RUNS, per_run: int = PER_RUN) -> Path:
    """A benchmark tree: ``oxford/<run>/pointcloud_20m/<ts>.bin`` + CSV. Run k's submap i is
    run 0's submap i plus 0.01 noise, so the places repeat across runs."""
    rng = np.random.default_rng(7)
    base = rng.uniform(-0.9, 0.9, (per_run, 4096, 3))
    for r, run in enumerate(runs):
        folder = root / "oxford" / run / "pointcloud_20m"
        folder.mkdir(parents=True)
        lines = ["timestamp,northing,easting"]
        for i in range(per_run):
            ts = 1_400_000_000_000_000 + 1_000_000 * (1000 * r + i)
            pts = base[i] + (0.01 * rng.standard_normal((4096, 3)) if r else 0.0)
            pts.clip(-1, 1).astype("<f8").tofile(folder / f"{ts}.bin")
            lines.append(f"{ts},{5735000.0 + 20.0 * i + 0.25 * r},{620000.0 + 1.5 * r}")
        (folder.parent / "pointcloud_locations_20m.csv").write_text("\n".join(lines) + "\n")
    return root


def make_checkpoint(path: Path, seed: int = 0) -> Path:
    """A small randomly initialised PointNetVLAD (16-d descriptors) saved as a checkpoint."""
    import torch

    from pnvlad_service.models.config import ModelConfig
    from pnvlad_service.models.pointnetvlad import build_model
    from pnvlad_service.models.store import save_model

    torch.manual_seed(seed)
    cfg = ModelConfig.compact(
        stem_widths=(8, 8),
        trunk_widths=(16, 32),
        tnet_point_widths=(8, 16),
        tnet_fc_widths=(16, 8),
        cluster_size=4,
        output_dim=16,
    )
    model = build_model(cfg)
    # Non-trivial batch-norm statistics, so folding them is exercised.
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
    return save_model(path, model, cfg)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def read_cloud(root: Path, rel: str) -> np.ndarray:
    return np.fromfile(root / rel, dtype="<f8").reshape(-1, 3)


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("index")
    tree = make_tree(base / "tree")
    ckpt = make_checkpoint(base / "ckpt")
    bundle = base / "flat.index"
    ix.build_bundle(bundle, ckpt, tree, progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "bundle": bundle}


@pytest.fixture(scope="module")
def encoder(world: dict[str, Path]):
    return ix.load_encoder(world["ckpt"])


def test_flat_search_equals_a_plain_loop(world: dict[str, Path], encoder) -> None:
    bundle = ix.IndexBundle.load(world["bundle"])
    records = ix.list_database_submaps(world["tree"])
    db = encoder.embed(np.stack([read_cloud(world["tree"], r.path) for r in records]))
    queries = db[[0, 5, PER_RUN + 3]] + np.float32(1e-3)
    dist, ids = bundle.search(queries, 4)
    for q, drow, irow in zip(queries, dist, ids, strict=True):
        expected = sorted(
            (float(np.sqrt(sum((float(a) - float(b)) ** 2 for a, b in zip(q, v, strict=True)))), j)
            for j, v in enumerate(db)
        )[:4]
        assert [j for _, j in expected] == irow.tolist()
        np.testing.assert_allclose(drow, [d for d, _ in expected], rtol=1e-4, atol=1e-5)


def test_metadata_rows_follow_the_csvs_and_load_without_pickle(world: dict[str, Path]) -> None:
    with np.load(world["bundle"] / ix.METADATA_FILE, allow_pickle=False) as z:
        assert all(z[f].dtype != object for f in z.files)
    meta = ix.Metadata.load(world["bundle"] / ix.METADATA_FILE)
    assert len(meta) == 2 * PER_RUN
    row = 0
    for run in RUNS:
        lines = (world["tree"] / "oxford" / run / "pointcloud_locations_20m.csv").read_text()
        for line in lines.splitlines()[1:]:
            ts, n, e = line.split(",")
            r = meta.row(row)
            assert r["run"] == run and r["dataset"] == "oxford"
            assert r["timestamp"] == int(ts)
            assert r["northing"] == float(n) and r["easting"] == float(e)
            assert r["path"] == f"oxford/{run}/pointcloud_20m/{ts}.bin"
            assert r["submap_id"] == f"oxford/{run}/{ts}"
            row += 1
    # Byte-exact round trip through to_bytes / load.
    again = world["base"] / "again.npz"
    again.write_bytes(meta.to_bytes())
    meta2 = ix.Metadata.load(again)
    for f in ix.METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(meta, f), getattr(meta2, f))


def test_manifest_records_model_files_and_what_was_indexed(world: dict[str, Path]) -> None:
    m = json.loads((world["bundle"] / "manifest.json").read_text())
    assert (m["format"], m["version"], m["dim"], m["metric"]) == ("pnvlad-index", 1, 16, "l2")
    assert m["index_key"] == "Flat" and m["count"] == 2 * PER_RUN
    sha = lambda p: hashlib.sha256(Path(p).read_bytes()).hexdigest()  # noqa: E731
    assert m["model"]["weights_sha256"] == sha(world["ckpt"] / "model.safetensors")
    for name in ("index.faiss", "metadata.npz"):
        assert m["files"][name] == sha(world["bundle"] / name)
    assert m["indexed"][0]["runs"] == list(RUNS) and m["indexed"][0]["layout"] == "test"
    assert m["recall_at_1_vs_exact"] is None  # exact index
    assert m["created"].endswith("+00:00")


def test_corrupted_file_is_detected(world: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    data = bytearray((copy / "metadata.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "metadata.npz").write_bytes(bytes(data))
    assert ix.verify_bundle(copy) == {"index.faiss": True, "metadata.npz": False}
    with pytest.raises(InputError, match=r"metadata\.npz"):
        ix.IndexBundle.load(copy)


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
        ix.build_bundle(
            out, world["ckpt"], world["tree"], encoder=Failing(), batch_size=4, progress=False
        )
    assert not out.exists()
    # Failing in the writing stage (bad key) also leaves nothing.
    with pytest.raises(InputError):
        ix.build_bundle(out, world["ckpt"], world["tree"], index_key="IVF4,PQ4", progress=False)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(".")] == []


def test_existing_bundle_needs_overwrite(world: dict[str, Path]) -> None:
    with pytest.raises(InputError, match="already exists"):
        ix.build_bundle(world["bundle"], world["ckpt"], world["tree"], progress=False)


# -- auto key ------------------------------------------------------------------------------


def test_auto_key_at_the_guideline_boundaries() -> None:
    big = 10**15
    assert ix.choose_index_key(1, 256, big) == "Flat"
    assert ix.choose_index_key(100_000, 256, big) == "Flat"
    assert ix.choose_index_key(100_001, 256, big) == "HNSW32"
    assert ix.choose_index_key(9_999_999, 256, big) == "HNSW32"
    assert ix.choose_index_key(10_000_000, 256, big).startswith("OPQ64,IVF")
    # HNSW32 needs n (4 d + 8 M) bytes; one byte less and IVF-Flat (n (4 d + 8)) takes over.
    n, d = 1_000_000, 256
    hnsw = n * (4 * d + 8 * 32)
    assert ix.choose_index_key(n, d, hnsw) == "HNSW32"
    assert ix.choose_index_key(n, d, hnsw - 1) == "IVF8192,Flat"
    ivf_flat = n * (4 * d + 8)
    assert ix.choose_index_key(n, d, ivf_flat) == "IVF8192,Flat"
    assert ix.choose_index_key(n, d, ivf_flat - 1) == "IVF8192,PQ64"
    assert ix.choose_index_key(n, d, n * (16 + 8)) == "IVF8192,PQ16"
    # A small map that does not fit as Flat is compressed (lists capped at n / 39 -> 1024).
    assert ix.choose_index_key(50_000, 256, 50_000 * 4 * 256 - 1) == "IVF1024,PQ64"
    with pytest.raises(InputError):
        ix.choose_index_key(0, 256)


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=1, max_value=10**9))
def test_ivf_lists_follow_the_guideline(n: int) -> None:
    k = ix.ivf_lists(n)
    assert k >= 1 and k & (k - 1) == 0  # a power of two
    if n >= 312**2:  # from here on 8√n <= n / 39: the 39-points-a-list cap does not bind
        assert 4 * n**0.5 <= k <= 16 * n**0.5
    assert k <= max(1, n // 39)


def test_min_training_vectors() -> None:
    assert ix.min_training_vectors("Flat") == 1
    assert ix.min_training_vectors("IVF1024,Flat") == 1024
    assert ix.min_training_vectors("IVF16,PQ8") == 256
    assert ix.min_training_vectors("OPQ16,IVF4096,PQ16x4") == 4096


def test_recall_at_1_against_a_loop() -> None:
    import faiss

    rng = np.random.default_rng(1)
    x = rng.standard_normal((200, 8)).astype(np.float32)
    y = x.copy()
    y[::3] += rng.standard_normal((len(y[::3]), 8)).astype(np.float32)  # a third of rows moved
    index = faiss.IndexFlatL2(8)
    index.add(y)
    got = ix.recall_at_1(index, x, sample=200)
    hits = 0
    for q in x:
        nearest = min(range(len(y)), key=lambda j: float(((y[j] - q) ** 2).sum()))
        hits += float(((x[nearest] - q) ** 2).sum()) <= 1e-6
    assert got == pytest.approx(hits / len(x))
    assert got < 1.0


@pytest.mark.parametrize(
    ("key", "params"), [("HNSW8", {"efSearch": 128}), ("IVF2,Flat", {"nprobe": 2})]
)
def test_approximate_bundles_record_recall(world: dict[str, Path], tmp_path, key, params) -> None:
    rep = ix.build_bundle(
        tmp_path / "b", world["ckpt"], world["tree"], index_key=key, progress=False
    )
    m = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert m["search_params"] == params
    # With every list probed (IVF) or a wide beam on 32 vectors (HNSW) the search is exact.
    assert rep.recall_at_1 == m["recall_at_1_vs_exact"] == 1.0
    b = ix.IndexBundle.load(tmp_path / "b")
    flat = ix.IndexBundle.load(world["bundle"])
    q = np.stack([flat.index.reconstruct(i) for i in range(0, 32, 5)])
    assert b.search(q, 1)[1][:, 0].tolist() == flat.search(q, 1)[1][:, 0].tolist()


def test_pq_with_too_few_vectors_says_how_many(world: dict[str, Path], tmp_path: Path) -> None:
    with pytest.raises(InputError, match="at least 256 vectors"):
        ix.build_bundle(
            tmp_path / "b", world["ckpt"], world["tree"], index_key="IVF2,PQ4", progress=False
        )


# -- add -----------------------------------------------------------------------------------


def test_add_a_run_equals_building_both(world: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "grow.index"
    ix.build_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[0]], progress=False)
    ix.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)
    grown, full = ix.IndexBundle.load(out), ix.IndexBundle.load(world["bundle"])
    assert grown.count == full.count == 2 * PER_RUN
    for f in ix.METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(grown.metadata, f), getattr(full.metadata, f))
    q = np.stack([full.index.reconstruct(i) for i in range(full.count)])
    np.testing.assert_array_equal(grown.search(q, 3)[1], full.search(q, 3)[1])
    m = grown.manifest
    assert [e["runs"] for e in m["indexed"]] == [[RUNS[0]], [RUNS[1]]]
    assert ix.verify_bundle(out) == {"index.faiss": True, "metadata.npz": True}
    with pytest.raises(InputError, match="already in the bundle"):
        ix.add_to_bundle(out, world["ckpt"], world["tree"], runs=[RUNS[1]], progress=False)


def test_add_refuses_other_weights(world: dict[str, Path], tmp_path: Path) -> None:
    other = make_checkpoint(tmp_path / "other", seed=1)
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    with pytest.raises(InputError, match="other weights"):
        ix.add_to_bundle(copy, other, world["tree"], runs=[RUNS[1]], progress=False)


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
        "-c",
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
    sharded, single = ix.IndexBundle.load(out), ix.IndexBundle.load(world["bundle"])
    assert sharded.manifest["build"]["processes"] == 2
    for f in ix.METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(sharded.metadata, f), getattr(single.metadata, f))
    a = sharded.index.reconstruct_n(0, sharded.count)
    b = single.index.reconstruct_n(0, single.count)
    np.testing.assert_allclose(a, b, atol=1e-5)
    assert sharded.manifest["model"] == single.manifest["model"]


# -- CLI -----------------------------------------------------------------------------------


def test_cli_build_and_info(world: dict[str, Path], tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    runner = CliRunner()
    out = tmp_path / "cli.index"
    res = runner.invoke(
        app,
        [
            "index",
            "build",
            "-c",
            str(world["ckpt"]),
            "-r",
            str(world["tree"]),
            "-o",
            str(out),
            "-k",
            "auto",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "embedded 32 submaps" in res.output and "clouds/s" in res.output
    assert json.loads((out / "manifest.json").read_text())["index_key"] == "Flat"
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 0 and "index.faiss" in res.output and "sha256 OK" in res.output
    (out / "index.faiss").write_bytes((out / "index.faiss").read_bytes() + b"x")
    res = runner.invoke(app, ["index", "info", str(out)])
    assert res.exit_code == 1 and "sha256 MISMATCH" in res.output
    res = runner.invoke(
        app, ["index", "build", "-c", str(world["ckpt"]), "-r", str(world["tree"]), "-o", str(out)]
    )
    assert res.exit_code == 2 and "already exists" in res.output
    args = ["-c", str(world["ckpt"]), "-r", str(world["tree"]), "-o", str(tmp_path / "x")]
    res = runner.invoke(app, ["index", "build", *args, "--run", "nope"])
    assert res.exit_code == 2 and "nope" in res.output


def test_ivf_pq_skips_polysemous_training() -> None:
    import faiss

    x = np.random.default_rng(0).standard_normal((300, 16)).astype(np.float32)
    index = ix.make_index(x, "IVF2,PQ4")
    ivf = faiss.downcast_index(faiss.extract_index_ivf(index))
    assert ivf.do_polysemous_training is False
    assert index.ntotal == 300
