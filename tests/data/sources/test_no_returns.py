"""Missing returns written as points: an Ouster OS1-64's organised cloud as its ROS driver
publishes it (every beam of every column, a beam that saw nothing at the sensor's origin or at
its beam's origin), read from a bag, a KITTI-style file and a scan folder: those points
dropped, the real ones kept in order, and the drop counted."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources.kitti import KittiSequence
from pnvlad_service.data.sources.registry import source_named
from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import NO_RETURN_M, drop_no_returns, read_scan

BEAMS, COLUMNS = 64, 1024
#: OS1-64 (rev C): beams from +16.6 to -16.6 degrees; the beam's origin 15.806 mm from the axis.
ALTITUDES_DEG = np.linspace(16.6, -16.6, BEAMS)
BEAM_ORIGIN_M = 0.015806
SENSOR_HEIGHT_M = 1.9

#: ouster_ros::Point: x, y, z (+ padding), intensity, t, reflectivity, ring, ambient, range.
OUSTER_POINT = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
        "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
        "itemsize": 48,
    }
)


def ouster_scan(at_beam_origin: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One OS1-64 sweep (64 x 1024, ring-major) of a street: ground 1.9 m below, a building
    face 9 m to the left up to 5 m high, a post 0.45 m away (a real return, 4.5 times the
    no-return radius), and the sky and the open street beyond 120 m (no return).
    Returns (structured points, bool [N]: which are real returns)."""
    alt = np.radians(ALTITUDES_DEG)[:, None]
    az = np.radians(np.arange(COLUMNS) * 360.0 / COLUMNS)[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(alt) * np.cos(az), np.cos(alt) * np.sin(az),
                                     np.sin(alt) + 0 * az), axis=-1)  # fmt: skip
    rng = np.full((BEAMS, COLUMNS), np.inf)
    down = d[..., 2] < 0
    rng[down] = SENSOR_HEIGHT_M / -d[..., 2][down]  # the ground
    left = d[..., 1] > 0
    wall = np.where(left, 9.0 / np.where(left, d[..., 1], 1), np.inf)
    rng = np.minimum(rng, np.where(wall * d[..., 2] < 5.0, wall, np.inf))  # up to 5 m high
    post = (np.abs(np.degrees(az) - 200.0) < 2.0) & (np.abs(np.degrees(alt)) < 10.0)
    rng = np.where(post, 0.45, rng)
    real = rng < 120.0
    r_mm = np.where(real, np.round(rng * 1000.0), 0.0)
    arr = np.zeros((BEAMS, COLUMNS), dtype=OUSTER_POINT)
    offset = BEAM_ORIGIN_M * np.stack(np.broadcast_arrays(np.cos(az), np.sin(az), 0 * az), -1)
    xyz = r_mm[..., None] / 1000.0 * d + np.where(real[..., None] | at_beam_origin, offset, 0.0)
    for k, n in enumerate("xyz"):
        arr[n] = xyz[..., k]
    arr["range"], arr["ring"] = r_mm, np.arange(BEAMS)[:, None]
    arr["t"] = np.arange(COLUMNS)[None, :] * 97_656  # ns across the 100 ms sweep
    arr["intensity"] = np.where(real, 40.0, 0.0)
    return arr.reshape(-1), real.reshape(-1)


def _xyz(arr: np.ndarray) -> np.ndarray:
    return np.stack([arr["x"], arr["y"], arr["z"]], axis=1)


@pytest.mark.parametrize("at_beam_origin", [False, True])
def test_the_missing_returns_of_an_ouster_sweep_are_dropped(at_beam_origin: bool) -> None:
    arr, real = ouster_scan(at_beam_origin)
    assert 0.2 < 1 - real.mean() < 0.6  # the sky and the open street: a real sweep's share
    pts = _xyz(arr)
    kept, dropped = drop_no_returns(pts)
    assert dropped == int((~real).sum())
    np.testing.assert_array_equal(kept, pts[real])  # ring-major order kept
    assert np.linalg.norm(kept, axis=1).min() == pytest.approx(0.45 + BEAM_ORIGIN_M, abs=1e-3)
    assert NO_RETURN_M < 0.45  # a real return this close is kept


def test_a_scan_file_and_a_kitti_sequence_drop_and_count_them(tmp_path: Path) -> None:
    arr, real = ouster_scan()
    pts = _xyz(arr)
    # KITTI's layout (x, y, z, reflectance float32), two scans of a sequence
    seq = tmp_path / "seq"
    (seq / "velodyne").mkdir(parents=True)
    for i in range(2):
        np.c_[pts, np.full(len(pts), 0.4)].astype("<f4").tofile(seq / "velodyne" / f"{i:06d}.bin")
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1 1\n")
    got, dropped = read_scan(seq / "velodyne" / "000000.bin", "kitti")
    np.testing.assert_array_equal(got, pts[real].astype(np.float32))
    assert dropped == int((~real).sum())
    drive = KittiSequence(seq)
    for i in range(2):
        np.testing.assert_array_equal(drive.scan(i), got)
    assert (drive.no_returns.points, drive.no_returns.scans) == (2 * dropped, 2)
    line = source_named("kitti").report(drive)
    assert (
        line
        == f"{2 * dropped:,} missing returns (points at the sensor's origin) dropped from 2 scans"
    )
    # a scan folder with a pose CSV: the same
    scans = tmp_path / "scans"
    scans.mkdir()
    np.save(scans / "1000000.npy", pts)
    (tmp_path / "poses.csv").write_text("timestamp,northing,easting,yaw_deg\n1000000,0,0,0\n")
    csv_drive = source_named("csv").open(scans, _options(tmp_path / "poses.csv"))
    np.testing.assert_array_equal(csv_drive.scan(0), pts[real])
    assert csv_drive.no_returns.points == dropped


def _options(poses: Path):
    from pnvlad_service.data.sources.registry import DriveOptions

    return DriveOptions(poses=poses)


def test_a_scan_of_nothing_but_missing_returns_is_refused(tmp_path: Path) -> None:
    np.zeros((2048, 4), dtype="<f4").tofile(tmp_path / "blind.bin")
    with pytest.raises(InputError, match=r"blind\.bin: all 2,048 points lie within 0\.1 m"):
        read_scan(tmp_path / "blind.bin", "kitti")


def test_an_ouster_bag_drops_nans_and_zeros_and_reports_both(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from pnvlad_service.data.sources.registry import rosbag_report
    from pnvlad_service.data.sources.rosbag import RosbagDrive
    from pnvlad_service.data.sources.rosbag_write import BagWriter, odometry, pointcloud2

    arr, real = ouster_scan()
    arr = arr.copy()
    arr["x"][5], arr["y"][5], arr["z"][5] = np.nan, np.nan, np.nan  # a NaN too (beam 0)
    keep = real.copy()
    keep[5] = False
    t0 = 1_700_000_000_000_000_000
    with BagWriter(tmp_path / "os1.bag") as bag:
        bag.write("/ouster/points", pointcloud2(bag.types, arr, t0 + 10**8, "os_sensor",
                                                height=BEAMS), t0 + 10**8)  # fmt: skip
        for k in range(3):
            ns = t0 + k * 10**8
            bag.write("/odom", odometry(bag.types, np.eye(4), ns, "odom", "os_sensor"), ns)
    with RosbagDrive(tmp_path / "os1.bag", "/ouster/points", pose_topic="/odom") as drive:
        got = drive.scan(0)
        np.testing.assert_array_equal(got, _xyz(arr)[keep])
        assert not real[5]  # the NaN took the place of one of the sky's zeros
        assert drive.stats.nonfinite_points == 1
        assert drive.no_returns.points == int((~real).sum()) - 1
        line = rosbag_report(drive)
    assert "1 NaN returns dropped from 1 scans" in line
    assert f"{drive.no_returns.points:,} missing returns" in line
    assert math.isfinite(float(got.sum()))
