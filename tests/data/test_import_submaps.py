"""Submaps made elsewhere (pnvlad_service.data.import_submaps, `pnvlad data import`): the tiny
city's test submaps, put back in UTM metres as another pipeline would hand them over, imported
into a new tree that `pnvlad index build` stores the geometry of, so answers can be verified."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.frames import frames_path, read_frames_csv
from pnvlad_service.data.tree import BenchmarkTree, check_tree
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import read_submap


@pytest.fixture(scope="module")
def elsewhere(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Run 1's test submaps as absolute UTM clouds (.npy) and their CSV."""
    tree = BenchmarkTree(tiny)
    run = tree.runs("business")[1]
    base = tmp_path_factory.mktemp("elsewhere")
    (base / "submaps").mkdir()
    clouds = {}
    for sub, frame in zip(tree.submaps("business", run, "test"),
                          tree.frames("business", run, "test"), strict=True):  # fmt: skip
        utm = frame.local_m(read_submap(tiny / sub.path)) + frame.origin
        np.save(base / "submaps" / f"{sub.timestamp}.npy", utm)
        clouds[sub.timestamp] = utm
    shutil.copy(tree.csv_path("business", run, "test"), base / "locations.csv")
    return {"base": base, "clouds": clouds, "run": run}


def test_import_writes_a_run_whose_sidecar_gives_the_metres_back(elsewhere: dict) -> None:
    base = elsewhere["base"]
    out = base / "tree" / "city" / "run1"
    res = CliRunner().invoke(app, ["data", "import", str(base / "submaps"), "--locations",
                                   str(base / "locations.csv"), "--origin", "utm",
                                   "--out", str(out), "--no-progress"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert check_tree(base / "tree").ok
    tree = BenchmarkTree(base / "tree")
    subs = tree.submaps("city", "run1", "test")
    frames = read_frames_csv(frames_path(tree.csv_path("city", "run1", "test")))
    assert (
        [s.timestamp for s in subs] == sorted(elsewhere["clouds"]) == [f.timestamp for f in frames]
    )
    for sub, frame in zip(subs, frames, strict=True):
        back = frame.local_m(read_submap(base / "tree" / sub.path)) + frame.origin
        utm = elsewhere["clouds"][sub.timestamp]
        # G's points, back in metres through the sidecar, lie on the submap handed over (G
        # averaged them in voxels about a metre wide and dropped what it took for ground).
        assert np.median(cKDTree(utm).query(back)[0]) < 0.5
        assert frame.origin[0] == pytest.approx(sub.easting) and frame.origin[1] == pytest.approx(
            sub.northing
        )
    # What G the submaps went through is recorded for the bundle's raw queries.
    assert (out / ".prepare-pointcloud_20m.json").is_file()


def test_a_bundle_of_imported_submaps_verifies(elsewhere: dict, tmp_path: Path) -> None:
    from pnvlad_service.data.import_submaps import import_submaps
    from pnvlad_service.index.build import build_bundle
    from pnvlad_service.localization.query.localizer import Localizer
    from tests.index.helpers import make_checkpoint

    base = elsewhere["base"]
    root = tmp_path / "tree"
    import_submaps(base / "submaps", base / "locations.csv", root / "city" / "run1",
                   origin="utm", progress=False)  # fmt: skip
    ckpt = make_checkpoint(tmp_path / "ckpt")
    build_bundle(tmp_path / "map.index", ckpt, root, progress=False)
    with Localizer.load(tmp_path / "map.index", ckpt) as loc:
        assert loc.can_verify  # the geometry the sidecar made possible
        stamp = sorted(elsewhere["clouds"])[3]
        cloud = elsewhere["clouds"][stamp] - [*elsewhere["clouds"][stamp][:, :2].mean(0), 0.0]
        answer = loc.localize(cloud, kind="scan", top_n=3).to_json()
    assert answer["verification"] is not None and answer["map_kind"] == "submap"


def test_import_refuses_what_it_cannot_read(elsewhere: dict, tmp_path: Path) -> None:
    from pnvlad_service.data.import_submaps import import_submaps

    base = elsewhere["base"]
    bad = tmp_path / "bad.csv"
    bad.write_text((base / "locations.csv").read_text() + "123,5.0,6.0\n")
    with pytest.raises(InputError, match="no submap file 123"):
        import_submaps(base / "submaps", bad, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()  # nothing written before every file was found
    with pytest.raises(InputError, match="position or utm"):
        import_submaps(base / "submaps", base / "locations.csv", tmp_path / "o", origin="gps")
