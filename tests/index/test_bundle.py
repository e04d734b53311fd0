"""The loaded bundle: exact search against a plain loop, metadata rows and their pickle-free
round trip, hash checks on load, and search results as matches."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.index.build import list_database_submaps
from pnvlad_service.index.bundle import METADATA_FIELDS, IndexBundle, Metadata
from pnvlad_service.index.manifest import INDEX_FILE, METADATA_FILE, Manifest
from tests.index.helpers import PER_RUN, RUNS, read_cloud


def test_flat_search_equals_a_plain_loop(world: dict[str, Path], encoder) -> None:
    bundle = IndexBundle.load(world["bundle"])
    records = list_database_submaps(world["tree"])
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


def test_bundle_properties_come_from_the_manifest(world: dict[str, Path]) -> None:
    bundle = IndexBundle.load(world["bundle"])
    assert isinstance(bundle.manifest, Manifest)
    assert (bundle.dim, bundle.count, bundle.key) == (16, 2 * PER_RUN, "Flat")
    assert bundle.bundle_id == bundle.manifest.files[INDEX_FILE][:16]
    assert len(bundle.bundle_id) == 16 and bundle.path == world["bundle"]


def test_metadata_rows_follow_the_csvs_and_load_without_pickle(world: dict[str, Path]) -> None:
    with np.load(world["bundle"] / METADATA_FILE, allow_pickle=False) as z:
        assert all(z[f].dtype != object for f in z.files)
    meta = Metadata.load(world["bundle"] / METADATA_FILE)
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
            assert r["utm_zone"] == ""
            row += 1
    # Byte-exact round trip through to_bytes / load.
    again = world["base"] / "again.npz"
    again.write_bytes(meta.to_bytes())
    meta2 = Metadata.load(again)
    for f in METADATA_FIELDS:
        np.testing.assert_array_equal(getattr(meta, f), getattr(meta2, f))


def test_corrupted_file_is_detected(world: dict[str, Path], tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(world["bundle"], copy)
    data = bytearray((copy / "metadata.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "metadata.npz").write_bytes(bytes(data))
    assert Manifest.read(copy).verify_files(copy) == {"index.faiss": True, "metadata.npz": False}
    with pytest.raises(InputError, match=r"metadata\.npz"):
        IndexBundle.load(copy)


def test_matches_rank_from_one_and_drop_missing_ids(world: dict[str, Path]) -> None:
    bundle = IndexBundle.load(world["bundle"])
    dist = np.array([[0.5, 0.75, 1.0]], dtype=np.float32)
    ids = np.array([[7, -1, 3]], dtype=np.int64)
    (row,) = bundle.matches(dist, ids)
    assert [(m.rank, m.id, m.distance) for m in row] == [(1, 7, 0.5), (2, 3, 1.0)]
    assert row[0].submap_id == str(bundle.metadata.submap_id[7])
    assert row[1].northing == float(bundle.metadata.northing[3])


def test_search_checks_the_query_shape_and_caps_k(world: dict[str, Path]) -> None:
    bundle = IndexBundle.load(world["bundle"])
    with pytest.raises(InputError, match=r"expected descriptors \[Q, 16\]"):
        bundle.search(np.zeros((2, 8), dtype=np.float32), 1)
    q = bundle.index.reconstruct_n(0, 2)
    dist, ids = bundle.search(q, 10 * bundle.count)
    assert ids.shape == (2, bundle.count) and ids[:, 0].tolist() == [0, 1]
    np.testing.assert_allclose(dist[:, 0], 0.0, atol=1e-3)
