"""Submaps cut to a square box about their location (``box_m``): the points kept, the box's
place and axes, the record that carries it to the index and the query windows, bad values."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.accumulate import (
    ScanCache,
    WindowAccumulator,
    travelled_distance,
    used_scans,
)
from pnvlad_service.data.cuts import submap_cuts
from pnvlad_service.data.prepare import laid_window, prepare_drive
from pnvlad_service.data.run_folder import recorded_accumulation
from pnvlad_service.errors import InputError
from pnvlad_service.index.manifest import MapRecord
from pnvlad_service.index.tree_records import tree_accumulation
from pnvlad_service.preprocess.filter_g import GConfig
from tests.data.helpers import ListDrive, tree_bytes

YAW = math.radians(30)  # the drive heads 30 degrees north of east: a turned box would show
STEP_M = 0.5
SCANS = 45  # 22 m of travel: one 20 m window, centred on scan 20
#: G in metres (no normalisation, no ground removal), so a kept point's place can be checked.
METRES = GConfig(target_points=1024, normalize=False, remove_ground=False)


def field_drive(seed: int = 0) -> ListDrive:
    """A drive through a field of random points 80 m x 80 m x 10 m about each sensor, far
    wider than any box tried; poses at UTM coordinates, heading :data:`YAW`."""
    rng = np.random.default_rng(seed)
    c, s = math.cos(YAW), math.sin(YAW)
    poses = np.tile(np.eye(4), (SCANS, 1, 1))
    poses[:, :3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    along = np.arange(SCANS) * STEP_M
    poses[:, 0, 3] = 620_000.0 + along * c
    poses[:, 1, 3] = 5_735_000.0 + along * s
    scans = [rng.uniform([-40, -40, -2], [40, 40, 8], size=(3000, 3)) for _ in range(SCANS)]
    return ListDrive(scans, poses, [10**15 + 50_000 * i for i in range(SCANS)])


def _window(drive: ListDrive, box_m: float | None) -> np.ndarray:
    """The cloud prepare hands to G for the drive's one test window."""
    travelled = travelled_distance(drive.poses)
    (cut,) = submap_cuts(travelled, 20.0, 20.0)
    cache = ScanCache(drive, seed=0, max_points_per_scan=None, max_range_m=None)
    return laid_window(cut, cache, drive.poses, used_scans(travelled, 0.05), box_m)


@pytest.mark.parametrize("box_m", [10.0, 25.0, 30.0])
def test_the_box_keeps_the_points_of_a_utm_square_centred_on_the_submap(box_m: float) -> None:
    drive = field_drive()
    whole, boxed = _window(drive, None), _window(drive, box_m)
    half = box_m / 2
    inside = (np.abs(whole[:, 0]) <= half) & (np.abs(whole[:, 1]) <= half)
    # Exactly the points of the square, in their order, none moved.
    np.testing.assert_array_equal(boxed, whole[inside])
    assert 0 < len(boxed) < len(whole)
    # Centred: the field fills the square to each of its four edges (points every few cm).
    for axis in (0, 1):
        assert boxed[:, axis].max() == pytest.approx(half, abs=0.2)
        assert boxed[:, axis].min() == pytest.approx(-half, abs=0.2)
    # UTM-aligned, not turned to the 30-degree heading: a square turned with the car would
    # reach half * (cos 30 + sin 30) = 1.37 half along x at its corners.
    assert np.abs(boxed[:, :2]).max() <= half


def test_prepare_writes_the_boxed_window_and_records_the_box(tmp_path: Path) -> None:
    drive = field_drive()
    prepare_drive(drive, tmp_path / "run", box_m=25.0, g_config=METRES, progress=False)
    (name,) = [p.name for p in (tmp_path / "run" / "pointcloud_20m").iterdir()]
    pts = np.fromfile(tmp_path / "run" / "pointcloud_20m" / name).reshape(-1, 3)
    assert len(pts) == METRES.target_points
    # G's voxel averages of points inside a square stay inside it (metres, about the centre).
    assert np.abs(pts[:, :2]).max() <= 12.5
    assert np.ptp(pts[:, 0]) > 20 and np.ptp(pts[:, 1]) > 20
    for folder in ("pointcloud_20m", "pointcloud_20m_10overlap"):
        record = json.loads((tmp_path / "run" / f".prepare-{folder}.json").read_text())
        assert record["box_m"] == 25.0
        assert recorded_accumulation(tmp_path / "run", folder) == {
            "max_points_per_scan": 10_000,
            "min_scan_spacing_m": 0.05,
            "box_m": 25.0,
        }


def test_no_box_is_the_submap_of_every_point_and_a_box_holding_all_changes_nothing(
    tmp_path: Path,
) -> None:
    drive = field_drive()
    default = prepare_drive(drive, tmp_path / "default", progress=False)
    prepare_drive(drive, tmp_path / "zero", box_m=0, progress=False)
    prepare_drive(drive, tmp_path / "wide", box_m=1000.0, progress=False)
    prepare_drive(drive, tmp_path / "boxed", box_m=25.0, progress=False)
    assert [r.written for r in default.layouts] == [1, 1]
    same = tree_bytes(tmp_path / "default")
    assert tree_bytes(tmp_path / "zero") == same
    assert tree_bytes(tmp_path / "wide") == same  # a box around every point cuts nothing
    boxed = tree_bytes(tmp_path / "boxed")
    assert boxed.keys() == same.keys()
    submap = f"pointcloud_20m/{10**15 + 50_000 * 20}.bin"  # the window centred on scan 20
    assert boxed[submap] != same[submap]


def test_the_box_travels_to_the_bundle_and_the_query_windows(tmp_path: Path) -> None:
    from pnvlad_service.data.tree import BenchmarkTree

    drive = field_drive()
    prepare_drive(drive, tmp_path / "ds" / "run", box_m=20.0, progress=False)
    records = BenchmarkTree(tmp_path).submaps("ds", "run", "test")
    acc = tree_accumulation(tmp_path, records)
    assert acc is not None and acc["box_m"] == 20.0
    # Through the manifest's JSON, as GET /info gives it, into an accumulator.
    doc = json.loads(json.dumps(MapRecord(accumulation=acc).to_json()))
    window = WindowAccumulator.for_map(MapRecord.from_json(doc), window_m=10.0, frame="enu")
    assert window.box_m == 20.0 and window.max_points_per_scan == 10_000
    plain = WindowAccumulator.laid_as({}, window_m=10.0, frame="enu")
    assert plain.box_m is None
    for i in range(SCANS):
        window.add(drive.scans[i], drive.poses[i])
        plain.add(drive.scans[i], drive.poses[i])
    whole, boxed = plain.cloud(), window.cloud()
    assert np.abs(boxed[:, :2]).max() <= 10.0 and boxed[:, 0].max() > 9.5
    assert len(boxed) < len(whole)
    # The box is applied in the world's axes before the cloud is turned to the sensor's.
    turned = WindowAccumulator.laid_as({"box_m": 20.0}, window_m=10.0, frame="sensor")
    for i in range(SCANS):
        turned.add(drive.scans[i], drive.poses[i])
    c, s = math.cos(YAW), math.sin(YAW)
    np.testing.assert_allclose(turned.cloud(), boxed @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]))


@pytest.mark.parametrize("bad", [-5.0, float("nan"), float("inf")])
def test_a_bad_box_is_refused_before_anything_is_written(tmp_path: Path, bad: float) -> None:
    drive = field_drive()
    for kinds in (("train", "test"), ("keyframe",)):
        with pytest.raises(InputError) as exc:
            prepare_drive(drive, tmp_path / "run", kinds=kinds, box_m=bad, progress=False)
        assert exc.value.source == "box_m" and "\n" not in str(exc.value)
    assert not (tmp_path / "run").exists()
    for bad_window in ({"box_m": bad}, {"box_m": 0.0}):
        with pytest.raises(InputError) as exc:
            WindowAccumulator.laid_as(bad_window)
        assert exc.value.source == "box_m"


def test_resume_with_another_box_is_refused(tmp_path: Path) -> None:
    drive = field_drive()
    prepare_drive(drive, tmp_path / "run", box_m=20.0, progress=False)
    with pytest.raises(InputError, match="box_m"):
        prepare_drive(drive, tmp_path / "run", box_m=30.0, resume=True, progress=False)
