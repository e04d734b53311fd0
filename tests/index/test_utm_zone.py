"""A map's UTM zone: given once (``data prepare --utm-zone`` or ``index build --utm-zone``),
recorded with the runs, carried by the bundle's every entry and every answer; a malformed or
conflicting zone refused with the field named and nothing written."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.prepare import prepare_drive
from pnvlad_service.errors import InputError
from pnvlad_service.index.build import add_to_bundle, build_bundle
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.index.tree_records import tree_utm_zone
from pnvlad_service.localization.query.answers import match_json
from tests.data.helpers import ListDrive
from tests.index.helpers import make_checkpoint

NORTH, EAST = 5_735_000.0, 620_000.0  # Oxford, zone 30U


def _drive(seed: int) -> ListDrive:
    """45 scans of a street 0.5 m apart, heading north-east from (NORTH, EAST)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-15, 15, 3000)
    street = np.vstack(
        [
            np.c_[x[:1000], rng.uniform(-8, 8, 1000), np.full(1000, -1.7)],
            np.c_[x[1000:], np.repeat([-8.0, 8.0], 1000), rng.uniform(-1.7, 6, 2000)],
        ]
    )
    yaw = math.radians(45)
    poses = np.tile(np.eye(4), (45, 1, 1))
    poses[:, :2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    along = np.arange(45) * 0.5
    poses[:, 0, 3] = EAST + along * math.cos(yaw)
    poses[:, 1, 3] = NORTH + along * math.sin(yaw)
    return ListDrive([street] * 45, poses, [10**15 + 50_000 * i for i in range(45)])


def _prepare(root: Path, run: str, zone: str, seed: int = 0) -> Path:
    out = root / "area" / run
    prepare_drive(_drive(seed), out, kinds=("test",), utm_zone=zone, progress=False)
    return out


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_checkpoint(tmp_path_factory.mktemp("zone") / "ckpt")


def test_the_zone_goes_from_prepare_to_every_answer(tmp_path: Path, ckpt: Path) -> None:
    tree = tmp_path / "tree"
    run = _prepare(tree, "a", " 30u ")
    record = json.loads((run / ".prepare-pointcloud_20m.json").read_text())
    assert record["utm_zone"] == "30U"  # canonical
    build_bundle(tmp_path / "map.index", ckpt, tree, progress=False)
    bundle = IndexBundle.load(tmp_path / "map.index")
    assert bundle.metadata.utm_zone.tolist() == ["30U"] * bundle.count
    d, i = bundle.search(np.zeros((1, bundle.dim), dtype=np.float32), 1)
    match = bundle.matches(d, i)[0][0]
    assert match_json(match)["utm_zone"] == "30U"
    # The zone makes the entry a place on Earth: Oxford, 51.75 N 1.26 W.
    from pnvlad_service.io.utm import to_latlon

    pytest.importorskip("pyproj")
    lat, lon = to_latlon(match.utm_zone, match.easting, match.northing)
    assert lat == pytest.approx(51.75, abs=0.01) and lon == pytest.approx(-1.26, abs=0.01)


def test_index_build_gives_a_zone_to_runs_prepared_without_one(tmp_path: Path, ckpt) -> None:
    tree = tmp_path / "tree"
    _prepare(tree, "a", "")
    build_bundle(tmp_path / "none.index", ckpt, tree, progress=False)
    assert set(IndexBundle.load(tmp_path / "none.index").metadata.utm_zone.tolist()) == {""}
    res = CliRunner().invoke(
        app,
        ["index", "build", "-m", str(ckpt), "-r", str(tree), "-o", str(tmp_path / "z.index"),
         "--utm-zone", "30U", "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert set(IndexBundle.load(tmp_path / "z.index").metadata.utm_zone.tolist()) == {"30U"}
    res = CliRunner().invoke(app, ["index", "info", str(tmp_path / "z.index")])
    assert res.exit_code == 0 and [x.split()[2:] for x in res.output.splitlines()
                                   if x.startswith("utm zone")] == [["30U"]]  # fmt: skip
    res = CliRunner().invoke(app, ["index", "info", str(tmp_path / "none.index")])
    assert "utm zone" in res.output and "unknown" in res.output
    res = CliRunner().invoke(
        app,
        ["index", "build", "-m", str(ckpt), "-r", str(tree), "-o", str(tmp_path / "bad.index"),
         "--utm-zone", "30Z", "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 2 and "--utm-zone: '30Z'" in res.output
    assert not (tmp_path / "bad.index").exists()


def test_a_run_of_another_zone_is_refused(tmp_path: Path, ckpt: Path) -> None:
    tree = tmp_path / "tree"
    _prepare(tree, "a", "30U")
    build_bundle(tmp_path / "map.index", ckpt, tree, progress=False)
    before = (tmp_path / "map.index" / "metadata.npz").read_bytes()
    other = tmp_path / "other"
    _prepare(other, "b", "31U", seed=1)
    with pytest.raises(InputError, match=r"^utm_zone: .*31U.*30U"):
        add_to_bundle(tmp_path / "map.index", ckpt, other, progress=False)
    assert (tmp_path / "map.index" / "metadata.npz").read_bytes() == before
    # A run prepared without a zone joins the bundle's.
    plain = tmp_path / "plain"
    _prepare(plain, "c", "", seed=2)
    add_to_bundle(tmp_path / "map.index", ckpt, plain, progress=False)
    assert set(IndexBundle.load(tmp_path / "map.index").metadata.utm_zone.tolist()) == {"30U"}


def test_runs_agree_on_one_zone(tmp_path: Path) -> None:
    def record(run: str, zone: str | None) -> SimpleNamespace:
        d = tmp_path / "area" / run
        d.mkdir(parents=True)
        doc = {} if zone is None else {"utm_zone": zone}
        (d / ".prepare-pointcloud_20m.json").write_text(json.dumps(doc))
        return SimpleNamespace(path=f"area/{run}/pointcloud_20m/1.bin", kind="test")

    a, b, none = record("a", "32n"), record("b", "32N"), record("c", None)
    assert tree_utm_zone(tmp_path, [a, b, none]) == "32N"
    assert tree_utm_zone(tmp_path, [none]) == ""
    assert tree_utm_zone(tmp_path, [none], " 17 SOUTH") == "17 south"
    assert tree_utm_zone(tmp_path, [a], "32N") == "32N"
    with pytest.raises(InputError, match=r"^--utm-zone: 33N given, .* 32N"):
        tree_utm_zone(tmp_path, [a], "33N")
    with pytest.raises(InputError, match=r"^utm_zone: run area/d records another"):
        tree_utm_zone(tmp_path, [a, b, record("d", "33N")])
    with pytest.raises(InputError, match=r"\.prepare-pointcloud_20m\.json: 'x1'"):
        tree_utm_zone(tmp_path, [record("e", "x1")])


def test_prepare_refuses_a_malformed_zone_before_writing(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"^utm_zone: '61U'"):
        prepare_drive(_drive(0), tmp_path / "run", kinds=("test",), utm_zone="61U")
    assert not (tmp_path / "run").exists()
    res = CliRunner().invoke(
        app,
        ["data", "prepare", "--kitti", str(tmp_path / "seq"), "--utm-zone", "north",
         "--out", str(tmp_path / "run")],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert res.output.strip().count("\n") == 0 and "--utm-zone: 'north'" in res.output
    assert not (tmp_path / "run").exists()


def test_runs_with_a_zone_give_it_to_a_bundle_without_one(tmp_path: Path, ckpt: Path) -> None:
    tree = tmp_path / "tree"
    _prepare(tree, "a", "")
    build_bundle(tmp_path / "map.index", ckpt, tree, progress=False)
    before = IndexBundle.load(tmp_path / "map.index")
    old = before.metadata.submap_id.tolist()
    assert set(before.metadata.utm_zone.tolist()) == {""}
    zoned = tmp_path / "zoned"
    _prepare(zoned, "b", "30u", seed=1)
    res = CliRunner().invoke(
        app, ["index", "add", str(tmp_path / "map.index"), "-m", str(ckpt), "-r", str(zoned),
              "--no-progress"],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    after = IndexBundle.load(tmp_path / "map.index")
    meta = after.metadata
    assert after.count == 2 * len(old) and meta.submap_id.tolist()[: len(old)] == old
    assert set(meta.utm_zone.tolist()) == {"30U"}  # every entry, the old ones too: no mix
    np.testing.assert_array_equal(meta.northing[: len(old)], before.metadata.northing)
    res = CliRunner().invoke(app, ["index", "info", str(tmp_path / "map.index")])
    assert [x.split()[2:] for x in res.output.splitlines() if x.startswith("utm zone")] == [["30U"]]
