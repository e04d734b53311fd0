"""Geometry in the bundle: every row back in metres within float16's bound, the poses of the
sidecars, append on add, bundles without sidecars, and the refusals at load (truncated file,
a flipped byte caught by the full hash, by the sampled rows or at fetch, a changed table)."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import CorruptFileError, InputError
from pnvlad_service.index import build as ib
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.index.geometry import POINTS_FILE, ROW_BYTES, TABLE_FILE, row_digest
from pnvlad_service.index.manifest import MANIFEST_FILE, Manifest
from pnvlad_service.io.submap import read_submap
from tests.index.helpers import PER_RUN, RUNS, free_port, make_checkpoint, make_tree

N = 2 * PER_RUN


@pytest.fixture(scope="module")
def geo(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tree whose runs all have frame sidecars, a model and its Flat bundle (with geometry)."""
    base = tmp_path_factory.mktemp("geometry")
    tree = make_tree(base / "tree", frames=True)
    ckpt = make_checkpoint(base / "ckpt")
    bundle = base / "geo.index"
    ib.build_bundle(bundle, ckpt, tree, progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "bundle": bundle}


def _frames(tree: Path, records) -> list:
    t = BenchmarkTree(tree)
    return [t.frames(r.dataset, r.run, r.kind)[r.row] for r in records]


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x40
    path.write_bytes(bytes(data))


# -- what is stored ------------------------------------------------------------------------


def test_every_row_is_the_submap_in_metres_within_float16s_bound(geo) -> None:
    bundle = IndexBundle.load(geo["bundle"])
    g = bundle.geometry
    assert g is not None and (g.count, g.points) == (N, 4096)
    records = ib.list_database_submaps(geo["tree"])
    frames = _frames(geo["tree"], records)
    for i, (rec, fr) in enumerate(zip(records, frames, strict=True)):
        normalised = read_submap(geo["tree"] / rec.path)
        want = fr.local_m(normalised)
        # float16 has 10 fraction bits: a value in [2**-k, 2**(1-k)) rounds to within 2**(-k-11),
        # so |x - f16(x)| <= 2**-12 for |x| <= 1; in metres that is |scale| * 2**-12.
        bound = abs(fr.scale) * 2.0**-12 + 1e-9
        got = g.metres(i)
        assert got.dtype == np.float64 and got.shape == (4096, 3)
        assert np.abs(got - want).max() <= bound
        # ... and the stored row is exactly the nearest float16 of each coordinate.
        np.testing.assert_array_equal(g.raw(i), normalised.astype("<f2"))
        np.testing.assert_array_equal(g.map_pose(i), fr.map_pose)
        assert g.scale(i) == fr.scale
    assert any(fr.scale < 0 for fr in frames)  # negated clouds are covered
    assert bundle.metadata.submap_id[5] == records[5].submap_id  # row i is submap i
    many = g.metres_many([7, 2])
    np.testing.assert_array_equal(many[0], g.metres(7))
    np.testing.assert_array_equal(many[1], g.metres(2))
    with pytest.raises(IndexError):
        g.metres(N)


def test_manifest_records_the_geometry_and_its_size(geo) -> None:
    doc = json.loads((geo["bundle"] / MANIFEST_FILE).read_text())
    entry = doc["geometry"]
    f16, table = geo["bundle"] / POINTS_FILE, geo["bundle"] / TABLE_FILE
    assert entry["count"] == N and entry["points"] == 4096 and entry["dtype"] == "<f2"
    assert entry["bytes"] == f16.stat().st_size == N * 4096 * 3 * 2
    assert entry["points_sha256"] == Manifest.read(geo["bundle"]).geometry.points_sha256
    import hashlib

    assert entry["table_sha256"] == hashlib.sha256(table.read_bytes()).hexdigest()
    assert entry["points_sha256"] == hashlib.sha256(f16.read_bytes()).hexdigest()
    assert set(doc["files"]) == {"index.faiss", "metadata.npz"}  # as before
    per_submap = (f16.stat().st_size + table.stat().st_size) / N
    assert per_submap <= 30_000  # the target: measured, 24,576 + the table
    assert Manifest.read(geo["bundle"]).to_json() == doc


def test_a_tree_without_sidecars_builds_without_geometry(world, geo, tmp_path, caplog) -> None:
    bundle = IndexBundle.load(world["bundle"])
    assert bundle.geometry is None and bundle.manifest.geometry is None
    assert "geometry" not in json.loads((world["bundle"] / MANIFEST_FILE).read_text())
    assert not (world["bundle"] / POINTS_FILE).exists()
    # An older bundle (no geometry key) still loads.
    assert IndexBundle.load(Path(__file__).parent / "bundle_v1").geometry is None
    # One run without a sidecar: built without geometry, and the log names the run.
    tree = make_tree(tmp_path / "tree", frames=(RUNS[0],))
    with caplog.at_level(logging.WARNING, logger="pnvlad_service.index.build"):
        rep = ib.build_bundle(tmp_path / "a.index", geo["ckpt"], tree, progress=False)
    assert rep.manifest is not None and rep.manifest.geometry is None
    lines = [r.getMessage() for r in caplog.records if "without geometry" in r.getMessage()]
    assert len(lines) == 1 and f"oxford/{RUNS[1]}" in lines[0] and RUNS[0] not in lines[0]
    with pytest.raises(InputError, match=f"oxford/{RUNS[1]}"):
        ib.build_bundle(
            tmp_path / "b.index", geo["ckpt"], tree, progress=False, geometry="required"
        )
    assert not (tmp_path / "b.index").exists()
    rep = ib.build_bundle(tmp_path / "c.index", geo["ckpt"], geo["tree"], progress=False,
                          geometry="off")  # fmt: skip
    assert rep.manifest is not None and rep.manifest.geometry is None


def test_add_keeps_the_old_rows_and_appends_the_new(geo, tmp_path) -> None:
    out = tmp_path / "grow.index"
    ib.build_bundle(out, geo["ckpt"], geo["tree"], runs=[RUNS[0]], progress=False)
    assert IndexBundle.load(out).geometry.count == PER_RUN
    ib.add_to_bundle(out, geo["ckpt"], geo["tree"], runs=[RUNS[1]], progress=False)
    grown, full = IndexBundle.load(out), IndexBundle.load(geo["bundle"])
    assert grown.geometry.count == N and grown.manifest.geometry.count == N
    # Same rows, same table as building both runs at once.
    assert (out / POINTS_FILE).read_bytes() == (geo["bundle"] / POINTS_FILE).read_bytes()
    for i in (0, PER_RUN - 1, PER_RUN, N - 1):
        np.testing.assert_array_equal(grown.geometry.metres(i), full.geometry.metres(i))
        np.testing.assert_array_equal(grown.geometry.map_pose(i), full.geometry.map_pose(i))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries


def test_add_refuses_runs_without_sidecars_unless_geometry_is_dropped(geo, tmp_path) -> None:
    tree = make_tree(tmp_path / "tree", frames=(RUNS[0],))
    out = tmp_path / "g.index"
    ib.build_bundle(out, geo["ckpt"], tree, runs=[RUNS[0]], progress=False)
    before = (out / MANIFEST_FILE).read_text()
    with pytest.raises(InputError, match=f"oxford/{RUNS[1]} has no frame sidecar"):
        ib.add_to_bundle(out, geo["ckpt"], tree, runs=[RUNS[1]], progress=False)
    assert (out / MANIFEST_FILE).read_text() == before  # untouched
    ib.add_to_bundle(out, geo["ckpt"], tree, runs=[RUNS[1]], progress=False, geometry="off")
    after = IndexBundle.load(out)
    assert after.count == N and after.geometry is None and not (out / POINTS_FILE).exists()
    # A bundle without geometry cannot gain it on add: "required" says so, "auto" adds none.
    plain = tmp_path / "plain.index"
    ib.build_bundle(plain, geo["ckpt"], geo["tree"], runs=[RUNS[0]], progress=False,
                    geometry="off")  # fmt: skip
    with pytest.raises(InputError, match="has no geometry"):
        ib.add_to_bundle(plain, geo["ckpt"], geo["tree"], runs=[RUNS[1]], progress=False,
                         geometry="required")  # fmt: skip
    ib.add_to_bundle(plain, geo["ckpt"], geo["tree"], runs=[RUNS[1]], progress=False)
    assert IndexBundle.load(plain).geometry is None


# -- refusals at load and at fetch ---------------------------------------------------------


def test_a_truncated_points_file_is_refused_at_load_naming_it(geo, tmp_path) -> None:
    bad = _copy(geo["bundle"], tmp_path / "t.index")
    f16 = bad / POINTS_FILE
    os.truncate(f16, N * ROW_BYTES - 1)
    msg = f"geometry.f16 is truncated: {N * ROW_BYTES - 1:,} bytes where {N} rows need"
    with pytest.raises(InputError, match=msg) as exc:
        IndexBundle.load(bad)
    assert exc.value.source == str(f16)
    with pytest.raises(InputError, match="is truncated"):  # checked even without verify
        IndexBundle.load(bad, verify=False)
    with open(f16, "ab") as fh:
        fh.write(b"\0\0")
    with pytest.raises(InputError, match=r"geometry\.f16 has"):
        IndexBundle.load(bad)


def test_a_flipped_byte_is_caught_by_the_full_hash(geo, tmp_path) -> None:
    bad = _copy(geo["bundle"], tmp_path / "f.index")
    _flip(bad / POINTS_FILE, 9 * ROW_BYTES + 100)
    with pytest.raises(InputError, match=r"geometry.f16 does not match .*row 9") as exc:
        IndexBundle.load(bad)
    assert exc.value.source == str(bad / POINTS_FILE)


def test_a_flipped_byte_is_caught_by_the_sample_or_at_fetch(geo, tmp_path) -> None:
    """Above the full-hash threshold (here 0 bytes) start-up checks sampled rows only."""
    bad = _copy(geo["bundle"], tmp_path / "s.index")
    big = {"geometry_hash_max_bytes": 0}
    g = IndexBundle.load(bad, **big).geometry
    sampled = set(g.sample(4).tolist())
    assert {0, N - 1} <= sampled and len(sampled) <= 6
    assert g.sample(4).tolist() == IndexBundle.load(bad, **big).geometry.sample(4).tolist()
    g.close()
    # In a sampled row: refused at load, naming the file and the row.
    _flip(bad / POINTS_FILE, (N - 1) * ROW_BYTES + 7)
    with pytest.raises(InputError, match=f"geometry.f16 row {N - 1} does not match"):
        IndexBundle.load(bad, **big, geometry_sample_rows=0)
    _flip(bad / POINTS_FILE, (N - 1) * ROW_BYTES + 7)  # back
    # In a row the sample misses: start-up passes, the fetch refuses.
    _flip(bad / POINTS_FILE, 5 * ROW_BYTES + 3)
    bundle = IndexBundle.load(bad, **big, geometry_sample_rows=0)
    assert bundle.geometry is not None
    bundle.geometry.metres(4)  # its neighbours are fine
    with pytest.raises(CorruptFileError, match=r"geometry.f16: row 5 does not match its digest"):
        bundle.geometry.metres(5)
    with pytest.raises(CorruptFileError):
        bundle.geometry.metres_many([4, 5])


def test_a_changed_table_is_refused(geo, tmp_path) -> None:
    bad = _copy(geo["bundle"], tmp_path / "n.index")
    with np.load(bad / TABLE_FILE) as z:
        cols = {k: z[k] for k in z.files}
    cols["scale"][3] *= 2.0
    np.savez(bad / TABLE_FILE, **cols)
    with pytest.raises(InputError, match=r"geometry\.npz does not match the manifest's sha256"):
        IndexBundle.load(bad)


def test_malformed_geometry_entries_are_refused(geo, tmp_path) -> None:
    bad = _copy(geo["bundle"], tmp_path / "m.index")
    doc = json.loads((bad / MANIFEST_FILE).read_text())
    for change, match in (
        ({"count": "32"}, r"geometry keys of the wrong type: \['count'\]"),
        ({"points_sha256": 5}, "points_sha256"),
        ({"count": N - 1}, "geometry has 31 rows where the index has 32"),
        ({"dtype": "<f4"}, "not supported"),
    ):
        (bad / MANIFEST_FILE).write_text(json.dumps({**doc, "geometry": {**doc["geometry"],
                                                                          **change}}))  # fmt: skip
        with pytest.raises(InputError, match=match):
            IndexBundle.load(bad)
    (bad / MANIFEST_FILE).write_text(json.dumps({**doc, "geometry": [1]}))
    with pytest.raises(InputError, match="wrong type"):
        Manifest.read(bad)


def test_row_digest_is_blake2b_of_the_rows_bytes() -> None:
    import hashlib

    row = np.arange(4096 * 3, dtype="<f2").reshape(4096, 3)
    want = int.from_bytes(hashlib.blake2b(row.tobytes(), digest_size=8).digest(), "little")
    assert row_digest(row) == want == row_digest(row.tobytes())


# -- CLI and the sharded build -------------------------------------------------------------


def test_cli_geometry_flag_and_info(geo, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    tree = make_tree(tmp_path / "tree", frames=(RUNS[0],))
    runner = CliRunner()
    args = ["index", "build", "-m", str(geo["ckpt"]), "-r", str(tree)]
    res = runner.invoke(app, [*args, "-o", str(tmp_path / "a"), "--geometry", "required"])
    assert res.exit_code == 2 and f"oxford/{RUNS[1]}" in res.output
    res = runner.invoke(app, [*args, "-o", str(tmp_path / "a"), "--geometry", "maybe"])
    assert res.exit_code == 2 and "auto, required, off" in res.output
    res = runner.invoke(app, [*args, "-o", str(tmp_path / "b"), "--run", RUNS[0]])
    assert res.exit_code == 0, res.output
    assert f"geometry: {PER_RUN} submaps, 24.6 KB each" in res.output
    res = runner.invoke(app, ["index", "info", str(tmp_path / "b")])
    assert res.exit_code == 0 and "checks OK" in res.output, res.output
    add = ["index", "add", str(tmp_path / "b"), "-m", str(geo["ckpt"]), "-r", str(tree)]
    res = runner.invoke(app, [*add, "--run", RUNS[1]])
    assert res.exit_code == 2 and f"oxford/{RUNS[1]} has no frame sidecar" in res.output
    os.truncate(tmp_path / "b" / POINTS_FILE, 100)
    res = runner.invoke(app, ["index", "info", str(tmp_path / "b")])
    assert res.exit_code == 1 and "geometry.f16 is truncated" in res.output


@pytest.mark.slow
def test_sharded_build_writes_the_same_geometry(geo, tmp_path: Path) -> None:
    out = tmp_path / "sharded.index"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--master-port", str(free_port()), "-m", "pnvlad_cli.main", "index", "build",
           "-m", str(geo["ckpt"]), "-r", str(geo["tree"]), "-o", str(out), "-b", "5"]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert IndexBundle.load(out).manifest.build["processes"] == 2
    assert (out / POINTS_FILE).read_bytes() == (geo["bundle"] / POINTS_FILE).read_bytes()
    with np.load(out / TABLE_FILE) as a, np.load(geo["bundle"] / TABLE_FILE) as b:
        for col in ("origin", "centre", "scale", "digest"):
            np.testing.assert_array_equal(a[col], b[col])
