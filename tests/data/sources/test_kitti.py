"""data.sources.kitti: KITTI sequences -> timestamps, UTM poses, scans.

Expectations are hand-worked pose conversions and the real KITTI scans of frames 94 and 95
registered by their recorded poses (tests/kitti00.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources.kitti import KittiSequence, kitti_poses_to_world
from pnvlad_service.errors import InputError
from tests.data.helpers import STEP_M, make_kitti_sequence
from tests.kitti00 import TR, camera_pose, relative_pose

# --------------------------------------------------------------------------------------------
# Pose conversion


def test_kitti_forward_motion_becomes_velodyne_x_and_east() -> None:
    cam = np.zeros((2, 3, 4))
    cam[:, :, :3] = np.eye(3)
    cam[1, 2, 3] = 4.3  # 4.3 m forward along the camera's z
    world = kitti_poses_to_world(cam)
    np.testing.assert_allclose(world[1, :3, 3], [4.3, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(world[1, :3, :3], np.eye(3), atol=1e-12)
    # Facing north (yaw 90 deg) and placed in UTM: forward is +northing.
    world = kitti_poses_to_world(cam, origin_ne=(5_700_000.0, 620_000.0), yaw_deg=90.0)
    np.testing.assert_allclose(world[0, :3, 3], [620_000.0, 5_700_000.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(world[1, :3, 3], [620_000.0, 5_700_004.3, 0.0], atol=1e-6)
    # Camera moving right (+x) and down (+y) = velodyne right (-y) and down (-z).
    cam[1, :, 3] = [1.0, 2.0, 0.0]
    np.testing.assert_allclose(kitti_poses_to_world(cam)[1, :3, 3], [0.0, -1.0, -2.0], atol=1e-9)


def test_kitti_left_turn_becomes_counter_clockwise_yaw() -> None:
    # Camera turned 90 deg to the left: its forward axis z points along camera-0's -x.
    turn = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    assert np.allclose(turn @ [0, 0, 1], [-1, 0, 0])
    cam = np.zeros((2, 3, 4))
    cam[0, :, :3] = np.eye(3)  # the first scan faces --yaw (0: east)
    cam[1, :, :3] = turn
    world = kitti_poses_to_world(cam)
    rz90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(world[1, :3, :3], rz90, atol=1e-12)
    # A sequence cut from a longer one (its first line not the identity) starts at the origin
    # facing --yaw all the same: the poses are taken relative to the first.
    rebased = kitti_poses_to_world(cam[::-1])
    np.testing.assert_allclose(rebased[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(rebased[1, :3, :3], rz90.T, atol=1e-12)


@pytest.mark.real_scans
def test_real_kitti_poses_register_the_real_scans(real_scans: Path) -> None:
    """KITTI 00 frames 94 and 95 (consecutive, 0.47 m apart) with their recorded poses (lines
    94 and 95 of kitti00_poses.txt): the conversion must put the real scans on each other."""
    from scipy.spatial import cKDTree

    cam = np.stack([camera_pose(real_scans, i)[:3] for i in (94, 95)])
    # Hand-worked: with the nominal calibration, velodyne (x, y, z) = camera (z, -x, -y); the
    # first scan at the origin, the second where frame 94's velodyne axes see it.
    perm = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    nominal = kitti_poses_to_world(cam)
    np.testing.assert_allclose(nominal[0], np.eye(4), atol=1e-9)
    r94 = perm @ cam[0, :, :3] @ perm.T
    moved = r94.T @ perm @ (cam[1, :, 3] - cam[0, :, 3])
    np.testing.assert_allclose(nominal[1, :3, 3], moved, atol=1e-6)
    # With sequence 00's calibration: the relative pose is the data README's inv(P_94) P_95.
    world = kitti_poses_to_world(cam, TR)
    step = np.linalg.inv(world[0]) @ world[1]  # scan 95 -> scan 94
    np.testing.assert_allclose(step, relative_pose(real_scans, 94, 95), atol=1e-6)
    assert np.linalg.norm(step[:3, 3]) == pytest.approx(0.4748, abs=1e-3)

    def load(name: str) -> np.ndarray:
        """Points within 40 m and above the road (z > -1.2 m: the sensor is 1.73 m up)."""
        pts = np.fromfile(real_scans / name, dtype=np.float32).reshape(-1, 4)[:, :3]
        pts = pts.astype(np.float64)
        pts = pts[np.linalg.norm(pts, axis=1) < 40.0]
        return pts[pts[:, 2] > -1.2][::4]

    a, b = load("kitti00_000094.bin"), load("kitti00_000095.bin")
    tree = cKDTree(a @ world[0, :3, :3].T + world[0, :3, 3])

    def misfit(pose: np.ndarray, shift: np.ndarray | None = None) -> float:
        """Mean distance of scan 95 placed at ``pose`` (then moved by ``shift``, world axes)
        to the nearest point of scan 94, each capped at 0.5 m."""
        points = b @ pose[:3, :3].T + pose[:3, 3] + (0.0 if shift is None else shift)
        return float(np.mean(np.minimum(tree.query(points)[0], 0.5)))

    aligned = misfit(world[1])
    # Every sign or axis mistake in the conversion moves scan 95 the wrong way; the converted
    # pose must fit clearly better than each (and than no motion at all). The wrong moves are
    # the true one (0.47 m, world axes) turned or misread.
    move = world[1, :3, 3] - world[0, :3, 3]
    d = float(np.linalg.norm(move))
    ahead = world[0, :3, 0]  # scan 94's forward axis in the world
    cam_move = cam[1, :, 3] - cam[0, :, 3]  # the same move in KITTI's camera-0 axes
    wrong = {
        "no motion": misfit(world[0]),
        "backwards": misfit(world[0], -move),
        "sideways": misfit(world[0], d * world[0, :3, 1]),
        "camera z read as up": misfit(world[0], d * world[0, :3, 2]),
        "camera axes unconverted": misfit(world[0], cam_move),
    }
    assert ahead @ move > 0.99 * d  # the car drove forward
    for name, value in wrong.items():
        assert aligned < 0.8 * value, (name, aligned, value)


def test_kitti_calib_file_is_used(tmp_path: Path, real_scans: Path) -> None:
    seq = make_kitti_sequence(tmp_path, real_scans, frames=2)
    # A Tr equal to the nominal rotation plus an offset: pure translations are unaffected.
    (seq / "calib.txt").write_text(
        "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 0.1 0 0 -1 0.2 1 0 0 -0.3\n"
    )
    drive = KittiSequence(seq)
    np.testing.assert_allclose(drive.poses[1, :3, 3], [STEP_M, 0.0, 0.0], atol=1e-9)
    (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match="Tr"):
        KittiSequence(seq)


def test_kitti_sequence_reads_times_and_rejects_mismatches(
    tmp_path: Path, real_scans: Path
) -> None:
    seq = make_kitti_sequence(tmp_path, real_scans, frames=3)
    drive = KittiSequence(seq, time_offset_us=1_000_000)
    assert drive.timestamps.dtype == np.int64
    assert drive.timestamps.tolist() == [1_000_000, 1_100_000, 1_200_000]
    pts = drive.scan(0)
    assert pts.shape == (124_668, 3)
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(InputError, match="1 poses for 3 scans") as exc:
        KittiSequence(seq)
    assert exc.value.source == str(seq / "poses.txt")
    (seq / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n" * 3)
    with pytest.raises(InputError, match="expected 12 numbers"):
        KittiSequence(seq)


def test_kitti_scans_go_through_the_kitti_reader(tmp_path: Path, real_scans: Path) -> None:
    # Scan 1 of the sequence is kitti00_000005.bin (a real scan of unknown frame, no pose
    # needed): what is checked is that it comes back as read by hand, and the reader's error.
    seq = make_kitti_sequence(tmp_path, real_scans, frames=2)
    drive = KittiSequence(seq)
    raw = np.fromfile(real_scans / "kitti00_000005.bin", dtype="<f4").reshape(-1, 4)
    assert np.array_equal(drive.scan(1), raw[:, :3])
    truncated = seq / "velodyne" / "000001.bin"
    truncated.unlink()
    truncated.write_bytes(raw.tobytes()[:-4])
    with pytest.raises(InputError, match="not a multiple of 16 bytes") as exc:
        drive.scan(1)
    assert exc.value.source == str(truncated)
