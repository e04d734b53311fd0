"""data.sources.rosbag: ROS bags (written here with rosbags' own writers) as drives.

The main check writes the scans and poses of a KITTI-style sequence (two real KITTI scans of
unknown frames, thinned, on made-up poses) into ROS 1 and ROS 2 bags, as Odometry and as /tf,
and runs both through ``prepare_drive``: same timestamps, poses and scans, byte-identical
submaps and CSVs. KITTI 00's recorded poses of frames 90-95, with the scans of frames 94 and
95, check real rotations through odometry and /tf chains. The rest covers cloud layouts
(organised with NaN returns, float64, extra fields, big-endian), pose sources, and every bad
input; the decoder and the interpolation alone are tested in test_pointcloud2.py and
test_pose_streams.py.
"""

from __future__ import annotations

import math
import shutil
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from pnvlad_service.data.prepare import prepare_drive
from pnvlad_service.data.sources.kitti import KittiSequence, kitti_poses_to_world
from pnvlad_service.data.sources.rosbag import BagTopic, RosbagClouds, RosbagDrive, list_topics
from pnvlad_service.data.sources.rosbag_write import (
    BagWriter,
    odometry,
    pointcloud2,
    tf_message,
    write_drive_bag,
)
from pnvlad_service.errors import InputError, MissingDependencyError
from tests.data.helpers import ListDrive, tree_bytes
from tests.data.sources.test_pose_streams import yaw_pose
from tests.kitti00 import TR, camera_pose, relative_pose

FRAMES = 40
STEP_M = 1.5
EPOCH_US = 1_700_000_000_000_000  # scans at a realistic epoch: ns stamps near 1.7e18
FAST = {"max_points_per_scan": 2000, "progress": False}
ORIGIN = (5_735_712.768124, 620_084.402381)
KITTI_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])

# (ROS version, ROS 2 storage, bag name)
FORMATS = [(1, "sqlite3", "drive.bag"), (2, "sqlite3", "drive_db3"), (2, "mcap", "drive_mcap")]


def make_sequence(root: Path, real_scans: Path, frames: int = FRAMES) -> Path:
    """A KITTI-style sequence of two real scans (every 6th point), alternating, 1.5 m apart.

    kitti00_000000.bin and kitti00_000005.bin are real HDL-64E scans of unknown frames (not
    frames 0 and 5 of KITTI 00): the poses here are made up, and the tests that use this only
    need real clouds to carry through bags and prepare unchanged."""
    seq = root / "seq"
    (seq / "velodyne").mkdir(parents=True)
    scans = [
        np.fromfile(real_scans / name, dtype=KITTI_POINT)[::6]
        for name in ("kitti00_000000.bin", "kitti00_000005.bin")
    ]
    for i in range(frames):
        scans[i % 2].tofile(seq / "velodyne" / f"{i:06d}.bin")
    poses = "".join(f"1 0 0 0 0 1 0 0 0 0 1 {STEP_M * i!r}\n" for i in range(frames))
    (seq / "poses.txt").write_text(poses)
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6f}\n" for i in range(frames)))
    return seq


def bag_of_sequence(
    path: Path, seq: Path, *, ros: int, storage: str = "sqlite3", poses_as: str = "odom"
) -> Path:
    """The sequence's scans (x, y, z, intensity as in the .bin) and local poses as a bag."""
    kitti = KittiSequence(seq, time_offset_us=EPOCH_US)  # local: origin 0, yaw 0
    with BagWriter(path, ros=ros, storage=storage) as bag:  # type: ignore[arg-type]
        t = bag.types
        if poses_as == "tf":
            static = tf_message(t, [("base_link", "velodyne", np.eye(4), EPOCH_US * 1000)])
            bag.write("/tf_static", static, EPOCH_US * 1000)
        for i, f in enumerate(kitti.files):
            ns = int(kitti.timestamps[i]) * 1000
            bag.write(
                "/velodyne_points", pointcloud2(t, np.fromfile(f, KITTI_POINT), ns, "velodyne"), ns
            )
            if poses_as == "odom":
                bag.write("/odom", odometry(t, kitti.poses[i], ns, "odom", "velodyne"), ns)
            else:
                bag.write("/tf", tf_message(t, [("odom", "base_link", kitti.poses[i], ns)]), ns)
    return path


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory, real_scans: Path) -> Path:
    return make_sequence(tmp_path_factory.mktemp("rosbag_seq"), real_scans)


@pytest.fixture(scope="module")
def kitti_run(sequence: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The KITTI path's run of the sequence, placed in UTM and turned by 30 degrees."""
    out = tmp_path_factory.mktemp("rosbag_kitti") / "run"
    drive = KittiSequence(sequence, origin_ne=ORIGIN, yaw_deg=30.0, time_offset_us=EPOCH_US)
    prepare_drive(drive, out, **FAST)
    return out


# --------------------------------------------------------------------------------------------
# The same drive as a KITTI sequence and as a bag


@pytest.mark.parametrize(("ros", "storage", "name"), FORMATS)
@pytest.mark.parametrize("poses_as", ["odom", "tf"])
def test_bag_is_the_same_drive_as_the_kitti_sequence(
    sequence: Path, tmp_path: Path, ros: int, storage: str, name: str, poses_as: str
) -> None:
    bag = bag_of_sequence(tmp_path / name, sequence, ros=ros, storage=storage, poses_as=poses_as)
    kitti = KittiSequence(sequence, origin_ne=ORIGIN, yaw_deg=30.0, time_offset_us=EPOCH_US)
    pose = {"pose_topic": "/odom"} if poses_as == "odom" else {"tf_frame": "odom"}
    with RosbagDrive(bag, "/velodyne_points", origin_ne=ORIGIN, yaw_deg=30.0, **pose) as drive:
        assert drive.name == Path(name).stem
        assert drive.frame_id == "velodyne"
        assert drive.timestamps.dtype == np.int64
        np.testing.assert_array_equal(drive.timestamps, kitti.timestamps)
        assert drive.poses.dtype == np.float64
        assert np.array_equal(drive.poses, kitti.poses)  # bit for bit
        for i in (0, 1, 17, FRAMES - 1, 3):  # out of order: the stream reopens
            got = drive.scan(i)
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, kitti.scan(i))
        assert drive.stats.clouds == drive.stats.scans == FRAMES
        assert drive.stats.dropped() == ""


def test_scans_are_decoded_only_when_asked_for(
    sequence: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pnvlad_service.data.sources.rosbag as rosbag

    decoded: list[int] = []
    real = rosbag.decode_pointcloud2

    def counting(msg):
        decoded.append(msg.header.stamp.nanosec)
        return real(msg)

    monkeypatch.setattr(rosbag, "decode_pointcloud2", counting)
    bag = bag_of_sequence(tmp_path / "lazy.bag", sequence, ros=1)
    with RosbagDrive(bag, "/velodyne_points", pose_topic="/odom") as drive:
        assert len(decoded) == 1  # opening checks the first cloud's fields, no more
        drive.scan(7)
        drive.scan(8)
        assert decoded[1:] == [700_000_000, 800_000_000]


@pytest.mark.parametrize(
    ("ros", "storage", "poses_as"), [(1, "sqlite3", "odom"), (2, "mcap", "tf")]
)
def test_bag_prepares_byte_identical_submaps(
    sequence: Path, kitti_run: Path, tmp_path: Path, ros: int, storage: str, poses_as: str
) -> None:
    bag = bag_of_sequence(
        tmp_path / ("d.bag" if ros == 1 else "d"),
        sequence,
        ros=ros,
        storage=storage,
        poses_as=poses_as,
    )
    pose = {"pose_topic": "/odom"} if poses_as == "odom" else {"tf_frame": "odom"}
    with RosbagDrive(bag, "/velodyne_points", origin_ne=ORIGIN, yaw_deg=30.0, **pose) as drive:
        result = prepare_drive(drive, tmp_path / "run", **FAST)
    assert [r.submaps for r in result.layouts] == [4, 2]
    ours, theirs = tree_bytes(tmp_path / "run"), tree_bytes(kitti_run)
    assert sorted(ours) == sorted(theirs)
    assert len([k for k in ours if k.endswith(".bin")]) == 6
    for key in theirs:
        assert ours[key] == theirs[key], key  # submaps and CSV rows, byte for byte


@pytest.mark.real_scans
def test_real_kitti_rotations_as_odometry_and_as_a_tf_chain(
    real_scans: Path, tmp_path: Path
) -> None:
    """Six real KITTI 00 poses, frames 90-95 (turning 4 degrees), with sequence 00's
    calibration; the clouds of frames 94 and 95 (the real scans of those frames) at theirs.
    Read back as odometry, as a /tf chain through a base_link and as a base_link odometry, the
    drive's poses are the recorded ones, and the move between its two scans is the data
    README's inv(P_94) P_95 (tests/kitti00.py)."""
    cam = np.stack([camera_pose(real_scans, i)[:3] for i in range(90, 96)])
    from scipy.spatial.transform import Rotation

    velo = kitti_poses_to_world(cam, TR)  # velodyne -> local world, z up
    # KITTI prints 7 digits, so its matrices are rotations to 1e-7 only; a quaternion is exact.
    velo[:, :3, :3] = Rotation.from_matrix(velo[:, :3, :3]).as_matrix()
    scans = [np.fromfile(real_scans / f"kitti00_0000{i}.bin", KITTI_POINT) for i in (94, 95)]
    # A base_link 0.8 m behind and 1.7 m below the lidar, pitched by 2 degrees.
    extrinsic = np.eye(4)
    c, s = math.cos(math.radians(2.0)), math.sin(math.radians(2.0))
    extrinsic[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    extrinsic[:3, 3] = [0.8, 0.0, 1.7]  # base_link <- velodyne
    stamp = [EPOCH_US * 1000 + k * 100_000_000 for k in range(6)]
    path = tmp_path / "real.bag"
    with BagWriter(path) as bag:
        t = bag.types
        bag.write("/tf_static", tf_message(t, [("base_link", "velodyne", extrinsic, stamp[0])]), 0)
        for k in range(6):
            if k in (4, 5):
                cloud = pointcloud2(t, scans[k - 4], stamp[k], "velodyne")
                bag.write("/points", cloud, stamp[k])
            bag.write("/odom", odometry(t, velo[k], stamp[k], "odom", "velodyne"), stamp[k])
            base = velo[k] @ np.linalg.inv(extrinsic)  # odom <- base_link
            bag.write("/tf", tf_message(t, [("odom", "base_link", base, stamp[k])]), stamp[k])
            bag.write("/base_odom", odometry(t, base, stamp[k], "odom", "base_link"), stamp[k])
    expected = velo[[4, 5]]
    truth = relative_pose(real_scans, 94, 95)  # scan 95 -> scan 94, numpy alone
    for pose in ({"pose_topic": "/odom"}, {"tf_frame": "odom"}, {"pose_topic": "/base_odom"}):
        with RosbagDrive(path, "/points", **pose) as drive:
            np.testing.assert_allclose(drive.poses, expected, atol=1e-9)
            step = np.linalg.inv(drive.poses[0]) @ drive.poses[1]
            np.testing.assert_allclose(step, truth, atol=1e-6)  # 1e-7 rotations: 1e-6 m
            assert drive.timestamps.tolist() == [EPOCH_US + 400_000, EPOCH_US + 500_000]
            np.testing.assert_array_equal(drive.scan(1), scans[1][["x", "y", "z"]].tolist())
    with RosbagDrive(path, "/points", pose_topic="/base_odom") as drive:
        assert "/tf_static base_link <- velodyne" in drive.pose_source
    # The lidar posed in the base frame: a fixed frame below the common ancestor works too.
    with RosbagDrive(path, "/points", tf_frame="base_link") as drive:
        np.testing.assert_allclose(drive.poses, np.stack([extrinsic] * 2), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Cloud layouts


def one_cloud_bag(path: Path, cloud_of, *, ros: int = 1, n_poses: int = 3) -> Path:
    """A bag of one cloud (``cloud_of(types, stamp_ns)``) at t = 0.1 s and odometry around it."""
    with BagWriter(path, ros=ros) as bag:  # type: ignore[arg-type]
        t0 = EPOCH_US * 1000
        bag.write("/points", cloud_of(bag.types, t0 + 100_000_000), t0 + 100_000_000)
        for k in range(n_poses):
            ns = t0 + k * 100_000_000
            bag.write("/odom", odometry(bag.types, np.eye(4), ns, "odom", "lidar"), ns)
    return path


def test_organised_cloud_drops_and_counts_nan_returns(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    grid = rng.uniform(-30, 30, size=(16, 64, 3)).astype(np.float32)  # 16 rings x 64 columns
    grid[rng.random((16, 64)) < 0.2] = np.nan  # missing returns
    grid[3, 5, 1] = np.inf
    pts = grid.reshape(-1, 3)
    bag = one_cloud_bag(
        tmp_path / "organised.bag",
        lambda t, ns: pointcloud2(t, pts, ns, "lidar", height=16, row_padding=12),
    )
    with RosbagDrive(bag, "/points", pose_topic="/odom") as drive:
        got = drive.scan(0)
        finite = np.isfinite(pts).all(axis=1)
        np.testing.assert_array_equal(got, pts[finite])  # row order kept
        assert drive.stats.nonfinite_points == int((~finite).sum()) > 150
        assert drive.stats.scans_with_nonfinite == 1


@pytest.mark.parametrize("ros", [1, 2])
def test_float64_cloud_keeps_its_precision(tmp_path: Path, ros: int) -> None:
    pts = np.array([[1.0 + 1e-12, -2.5, 3.25], [620_084.402381, 5_735_712.768124, 0.1]])
    bag = one_cloud_bag(
        tmp_path / ("f64.bag" if ros == 1 else "f64"),
        lambda t, ns: pointcloud2(t, pts, ns, "lidar"),
        ros=ros,
    )
    with RosbagDrive(bag, "/points", pose_topic="/odom") as drive:
        got = drive.scan(0)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, pts)


@pytest.mark.parametrize("order", ["<", ">"])
def test_cloud_with_extra_fields_in_any_order_and_byte_order(tmp_path: Path, order: str) -> None:
    # An Ouster-like point: intensity first, then x, y, z, a ring, a time, padding to 32 bytes.
    dtype = np.dtype(
        {
            "names": ["intensity", "x", "y", "z", "ring", "t"],
            "formats": [
                order + "f4",
                order + "f4",
                order + "f4",
                order + "f4",
                order + "u2",
                order + "u4",
            ],
            "offsets": [0, 4, 8, 12, 16, 20],
            "itemsize": 32,
        }
    )
    rng = np.random.default_rng(1)
    arr = np.zeros(500, dtype=dtype)
    for n in "xyz":
        arr[n] = rng.uniform(-50, 50, 500)
    arr["intensity"], arr["ring"], arr["t"] = 7.0, np.arange(500) % 64, 123456
    bag = one_cloud_bag(tmp_path / "extra.bag", lambda t, ns: pointcloud2(t, arr, ns, "lidar"))
    with RosbagDrive(bag, "/points", pose_topic="/odom") as drive:
        got = drive.scan(0)
    assert got.dtype == np.float32 and got.shape == (500, 3)
    np.testing.assert_array_equal(got, np.stack([arr["x"], arr["y"], arr["z"]], axis=1))


# --------------------------------------------------------------------------------------------
# Poses


def test_scans_outside_the_pose_stream_are_dropped_and_counted(tmp_path: Path) -> None:
    t0 = EPOCH_US * 1000
    cloud_s = [0.05, 0.25, 0.30, 0.30000001, 2.6, 3.9, 4.2]  # seconds after t0
    pose_s = [0.1, 0.2, 0.4, 0.5, 3.5, 4.0]  # a 3-second gap between 0.5 and 3.5
    poses = [
        yaw_pose(0, (0, 0, 0)),
        yaw_pose(0, (1, 0, 0)),
        yaw_pose(0, (3, 0, 0)),
        yaw_pose(0, (4, 0, 0)),
        yaw_pose(90, (4, 30, 0)),
        yaw_pose(90, (4, 35, 0)),
    ]
    pts = np.zeros((4, 3), np.float32)
    path = tmp_path / "gaps.bag"
    with BagWriter(path) as bag:
        for s in cloud_s:
            ns = t0 + round(s * 1e9)
            bag.write("/points", pointcloud2(bag.types, pts, ns, "lidar"), ns)
        for s, pose in zip(pose_s, poses, strict=True):
            ns = t0 + round(s * 1e9)
            bag.write("/pose", posestamped(bag.types, pose, ns), ns)
    with RosbagDrive(path, "/points", pose_topic="/pose") as drive:
        s = drive.stats
        assert (s.clouds, s.before_poses, s.after_poses, s.in_pose_gaps) == (7, 1, 1, 1)
        assert s.duplicate_stamps == 1  # 0.30 s and 0.30000001 s are the same microsecond
        assert s.scans == len(drive) == 3
        assert "1 before the pose stream" in s.dropped()
        assert drive.timestamps.tolist() == [
            EPOCH_US + 250_000,
            EPOCH_US + 300_000,
            EPOCH_US + 3_900_000,
        ]
        # 0.25 s and 0.30 s: a quarter and half of the way from (1, 0) at 0.2 s to (3, 0) at
        # 0.4 s; 3.9 s: 80 % of the way from 30 m to 35 m north.
        np.testing.assert_allclose(drive.poses[0, :3, 3], [1.5, 0.0, 0.0], atol=1e-7)
        np.testing.assert_allclose(drive.poses[1, :3, 3], [2.0, 0.0, 0.0], atol=1e-7)
        np.testing.assert_allclose(drive.poses[2], yaw_pose(90, (4, 34, 0)), atol=1e-7)
    # Without a gap limit the scan at 2.6 s is interpolated across the gap.
    with RosbagDrive(path, "/points", pose_topic="/pose", max_pose_gap_s=None) as drive:
        assert drive.stats.in_pose_gaps == 0 and len(drive) == 4


def posestamped(types, pose: np.ndarray, ns: int, covariance: bool = False):
    from pnvlad_service.data.sources.rosbag_write import _header, _pose_parts

    position, orientation = _pose_parts(types, pose)
    msg = types["geometry_msgs/msg/Pose"](position=position, orientation=orientation)
    if covariance:
        msg = types["geometry_msgs/msg/PoseWithCovariance"](pose=msg, covariance=np.zeros(36))
        return types["geometry_msgs/msg/PoseWithCovarianceStamped"](
            header=_header(types, ns, "map"), pose=msg
        )
    return types["geometry_msgs/msg/PoseStamped"](header=_header(types, ns, "map"), pose=msg)


@pytest.mark.parametrize("ros", [1, 2])
def test_pose_with_covariance_and_out_of_order_stamps(tmp_path: Path, ros: int) -> None:
    t0 = EPOCH_US * 1000
    path = tmp_path / ("cov.bag" if ros == 1 else "cov")
    pts = np.zeros((2, 3), np.float32)
    with BagWriter(path, ros=ros) as bag:  # type: ignore[arg-type]
        # Clouds recorded out of their stamps' order (a driver that buffers).
        for s in (0.3, 0.1, 0.2):
            ns = t0 + round(s * 1e9)
            bag.write("/points", pointcloud2(bag.types, pts + s, ns, "lidar"), t0 + 10**9)
        for k in range(5):
            ns = t0 + k * 100_000_000
            msg = posestamped(bag.types, yaw_pose(0, (k, 0, 0)), ns, covariance=True)
            bag.write("/amcl_pose", msg, ns)
    with RosbagDrive(path, "/points", pose_topic="/amcl_pose") as drive:
        assert drive.timestamps.tolist() == [
            EPOCH_US + 100_000,
            EPOCH_US + 200_000,
            EPOCH_US + 300_000,
        ]
        np.testing.assert_allclose(drive.poses[:, 0, 3], [1.0, 2.0, 3.0], atol=1e-7)
        assert [float(drive.scan(i)[0, 0]) for i in (2, 0, 1)] == pytest.approx([0.3, 0.1, 0.2])
        assert "PoseWithCovarianceStamped" in drive.pose_source


def test_zero_header_stamps_fall_back_to_bag_time(tmp_path: Path, caplog) -> None:
    t0 = EPOCH_US * 1000
    path = tmp_path / "nostamp.bag"
    with BagWriter(path) as bag:
        for k in range(4):
            ns = t0 + k * 100_000_000
            bag.write("/points", pointcloud2(bag.types, np.zeros((1, 3), np.float32), 0, "l"), ns)
            bag.write("/odom", odometry(bag.types, yaw_pose(0, (k, 0, 0)), 0, "odom", "l"), ns)
    with RosbagDrive(path, "/points", pose_topic="/odom") as drive:
        assert drive.timestamps.tolist() == [EPOCH_US + k * 100_000 for k in range(4)]
        np.testing.assert_array_equal(drive.poses[:, 0, 3], [0.0, 1.0, 2.0, 3.0])
    assert "zero header stamps" in caplog.text


# --------------------------------------------------------------------------------------------
# Topics, bad input


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four clouds in frame 'lidar', odometry, /tf odom -> base -> lidar, a string topic."""
    path = tmp_path_factory.mktemp("rosbag_small") / "small.bag"
    t0 = EPOCH_US * 1000
    with BagWriter(path) as bag:
        t = bag.types
        bag.write(
            "/tf_static", tf_message(t, [("base", "lidar", yaw_pose(0, (0, 0, 1.8)), t0)]), t0
        )
        for k in range(4):
            ns = t0 + k * 100_000_000
            bag.write("/points", pointcloud2(t, np.ones((5, 3), np.float32), ns, "lidar"), ns)
            bag.write("/odom", odometry(t, yaw_pose(0, (k, 0, 0)), ns, "odom", "lidar"), ns)
            bag.write("/tf", tf_message(t, [("odom", "base", yaw_pose(0, (k, 0, 0)), ns)]), ns)
        bag.write("/note", t["std_msgs/msg/String"](data="hello"), t0)
    return path


def test_list_topics(small_bag: Path) -> None:
    assert list_topics(small_bag) == [
        BagTopic("/note", "std_msgs/msg/String", 1),
        BagTopic("/odom", "nav_msgs/msg/Odometry", 4),
        BagTopic("/points", "sensor_msgs/msg/PointCloud2", 4),
        BagTopic("/tf", "tf2_msgs/msg/TFMessage", 4),
        BagTopic("/tf_static", "tf2_msgs/msg/TFMessage", 1),
    ]


def test_clouds_without_poses(small_bag: Path) -> None:
    with RosbagClouds(small_bag, "/points") as clouds:
        assert clouds.timestamps.tolist() == [EPOCH_US + k * 100_000 for k in range(4)]
        assert clouds.scan(2).shape == (5, 3)
        assert not hasattr(clouds, "poses")
        assert repr(clouds) == f"RosbagClouds({str(small_bag)!r}, '/points', 4 scans)"


def test_tf_chain_through_a_static_transform(small_bag: Path) -> None:
    with RosbagDrive(small_bag, "/points", tf_frame="odom") as drive:
        np.testing.assert_allclose(drive.poses[:, :3, 3], [[k, 0, 1.8] for k in range(4)])
        assert drive.pose_source == "/tf odom <- lidar"


def bad(match: str, bag: Path):
    """pytest.raises for an InputError about ``bag`` whose message matches ``match``."""

    class _Check:
        def __enter__(self):
            self.ctx = pytest.raises(InputError, match=match)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = self.ctx.__exit__(*exc)
            assert self.info.value.source == str(bag)
            return handled

    return _Check()


def test_topic_errors_name_the_bag_and_the_topic(small_bag: Path) -> None:
    with bad(r"topic '/velodyne' not found \(PointCloud2 topics in the bag: /points\)", small_bag):
        RosbagDrive(small_bag, "/velodyne", pose_topic="/odom")
    with bad(
        r"topic '/odom' holds nav_msgs/msg/Odometry, not sensor_msgs/msg/PointCloud2", small_bag
    ):
        RosbagDrive(small_bag, "/odom", pose_topic="/odom")
    with bad(
        r"topic '/points' holds sensor_msgs/msg/PointCloud2, not nav_msgs/msg/Odometry or",
        small_bag,
    ):
        RosbagDrive(small_bag, "/points", pose_topic="/points")
    with bad(r"topic '/gps' not found \(pose topics in the bag: /odom\)", small_bag):
        RosbagDrive(small_bag, "/points", pose_topic="/gps")
    with bad(r"no chain of transforms from 'map' to the clouds' frame 'lidar'", small_bag):
        RosbagDrive(small_bag, "/points", tf_frame="map")
    with bad("either a pose topic or a /tf fixed frame", small_bag):
        RosbagDrive(small_bag, "/points")
    with bad("either a pose topic or a /tf fixed frame", small_bag):
        RosbagDrive(small_bag, "/points", pose_topic="/odom", tf_frame="odom")
    with bad("no /tf2 topic", small_bag):
        RosbagDrive(small_bag, "/points", tf_frame="odom", tf_topics=("/tf2", "/tf_static"))


def test_not_a_bag(tmp_path: Path) -> None:
    text = tmp_path / "notes.bag"
    text.write_text("not a bag\n")
    with bad("not a readable ROS bag", text):
        RosbagDrive(text, "/points", pose_topic="/odom")
    with bad("not a readable ROS bag", text):
        list_topics(text)
    other = tmp_path / "scan.pcd"
    other.write_text("# .PCD v0.7\n")
    with bad("not a ROS bag", other):
        list_topics(other)
    folder = tmp_path / "folder"
    folder.mkdir()
    with bad("not a readable ROS bag", folder):
        list_topics(folder)
    with bad("no such bag", tmp_path / "missing.bag"):
        list_topics(tmp_path / "missing.bag")
    fake_db3 = tmp_path / "fake.db3"
    fake_db3.write_bytes(b"\x00" * 4096)
    with bad("not a readable ROS bag", fake_db3):
        list_topics(fake_db3)


def test_a_ros1_bag_under_another_name_gets_a_hint(small_bag: Path, tmp_path: Path) -> None:
    renamed = tmp_path / "small.rosbag"
    shutil.copy(small_bag, renamed)
    with bad(r"starts like a ROS 1 bag: name it \*\.bag", renamed):
        list_topics(renamed)


@pytest.mark.parametrize("fmt", FORMATS)
def test_truncated_bag(sequence: Path, tmp_path: Path, fmt) -> None:
    ros, storage, name = fmt
    path = bag_of_sequence(tmp_path / name, sequence, ros=ros, storage=storage)
    files = [path] if path.is_file() else [f for f in path.iterdir() if f.suffix != ".yaml"]
    for f in files:
        data = f.read_bytes()
        f.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(InputError, match=r"truncated|not a readable ROS bag") as exc:  # noqa: SIM117
        with RosbagDrive(path, "/velodyne_points", pose_topic="/odom") as drive:
            for i in range(len(drive)):
                drive.scan(i)
    assert exc.value.source == str(path)


def test_damage_found_while_reading_scans(small_bag: Path) -> None:
    from rosbags.rosbag1 import ReaderError

    with RosbagDrive(small_bag, "/points", pose_topic="/odom") as drive:
        drive.scan(1)
        reader = drive._reader

        def broken(*args, **kwargs):
            yield from ()
            raise ReaderError("Expected to find message data.")

        reader.messages = broken  # type: ignore[union-attr,method-assign]
        with bad(
            r"topic '/points': cannot read the bag \(truncated or damaged\? Expected", small_bag
        ):
            drive.scan(0)  # backwards: the stream reopens


def test_cloud_without_xyz_and_with_integer_xyz(tmp_path: Path) -> None:
    polar = np.zeros(10, dtype=[("range", "<f4"), ("azimuth", "<f4"), ("elevation", "<f4")])
    bag = one_cloud_bag(tmp_path / "polar.bag", lambda t, ns: pointcloud2(t, polar, ns, "lidar"))
    with bad(
        r"topic '/points': message 0: PointCloud2 without field\(s\) x, y, z \(fields: "
        r"range, azimuth, elevation\)",
        bag,
    ):
        RosbagDrive(bag, "/points", pose_topic="/odom")
    ints = np.zeros(10, dtype=[("x", "<i2"), ("y", "<i2"), ("z", "<i2")])
    bag = one_cloud_bag(tmp_path / "ints.bag", lambda t, ns: pointcloud2(t, ints, ns, "lidar"))
    with bad("field x is INT16: x, y and z must be float32 or float64", bag):
        RosbagDrive(bag, "/points", pose_topic="/odom")


def write_late_poses_bag(path: Path, with_tf: bool = False) -> Path:
    """Three clouds whose poses (Odometry, and /tf with ``with_tf``) all come a minute later."""
    t0 = EPOCH_US * 1000
    with BagWriter(path) as bag:
        for k in range(3):
            ns = t0 + k * 100_000_000
            bag.write("/points", pointcloud2(bag.types, np.ones((3, 3), np.float32), ns, "l"), ns)
            late = ns + 60 * 10**9
            bag.write("/odom", odometry(bag.types, np.eye(4), late, "odom", "l"), late)
            if with_tf:
                bag.write("/tf", tf_message(bag.types, [("odom", "l", np.eye(4), late)]), late)
    return path


def test_poses_that_do_not_overlap_the_clouds(tmp_path: Path) -> None:
    path = write_late_poses_bag(tmp_path / "late.bag", with_tf=True)
    with bad(
        r"pose topic '/odom' does not overlap the clouds on '/points': poses "
        r"1700000060\.000\.\.1700000060\.200 s, clouds 1700000000\.000\.\.1700000000\.200 s",
        path,
    ):
        RosbagDrive(path, "/points", pose_topic="/odom")
    with bad(r"/tf \(odom <- l\) does not overlap the clouds", path):
        RosbagDrive(path, "/points", tf_frame="odom")


def test_missing_rosbags_names_the_extra(monkeypatch: pytest.MonkeyPatch, small_bag: Path) -> None:
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # import raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'pnvlad\[rosbag\]'"):
        list_topics(small_bag)


def test_header_parse_matches_the_deserialiser(small_bag: Path) -> None:
    from rosbags.highlevel import AnyReader

    from pnvlad_service.data.sources.pointcloud2 import header_stamp

    with AnyReader([small_bag]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/points")
        for _, _, raw in reader.messages(connections=[conn]):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert header_stamp(raw, ros2=False) == (stamp, "lidar")
    with pytest.raises(struct.error):
        header_stamp(b"\x00" * 10, ros2=False)


# --------------------------------------------------------------------------------------------
# A drive written as a bag


@pytest.mark.parametrize(("ros", "storage"), [(1, "sqlite3"), (2, "mcap")])
def test_write_drive_bag_round_trip_in_utm(tmp_path: Path, ros: int, storage: str) -> None:
    rng = np.random.default_rng(3)
    scans = [rng.normal(size=(50, 3)).astype(np.float32) for _ in range(5)]
    poses = np.stack(
        [yaw_pose(10.0 * k, (620_000.0 + k, 5_735_000.0 + 2 * k, 40.0)) for k in range(5)]
    )
    truth = poses.copy()
    truth[:, 0, 3] += 0.5
    stamps = [EPOCH_US + k * 100_000 for k in range(5)]
    path = tmp_path / ("w.bag" if ros == 1 else "w")
    write_drive_bag(
        ListDrive(scans, poses, stamps),
        path,
        origin_ne=(5_735_000.0, 620_000.0),
        truth=truth,
        ros=ros,
        storage=storage,
    )  # type: ignore[arg-type]
    names = [t.name for t in list_topics(path)]
    assert names == ["/ground_truth", "/odom", "/points"]
    for topic, expected in (("/odom", poses), ("/ground_truth", truth)):
        with RosbagDrive(
            path, "/points", pose_topic=topic, origin_ne=(5_735_000.0, 620_000.0)
        ) as d:
            assert d.timestamps.tolist() == stamps
            np.testing.assert_allclose(d.poses, expected, atol=1e-6)
            for i in range(5):
                np.testing.assert_array_equal(d.scan(i), scans[i])
    with pytest.raises(InputError, match="already exists"):
        write_drive_bag(ListDrive(scans, poses, stamps), path)


# --------------------------------------------------------------------------------------------
# CLI: pnvlad data prepare --rosbag


def run_cli(*args: str):
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    return CliRunner().invoke(app, ["data", "prepare", *args])


def test_cli_prepare_rosbag_gives_the_kitti_bytes(
    sequence: Path, kitti_run: Path, tmp_path: Path
) -> None:
    bag = bag_of_sequence(tmp_path / "d.bag", sequence, ros=1, poses_as="tf")
    origin = f"{ORIGIN[0]!r},{ORIGIN[1]!r}"
    out = tmp_path / "bench" / "city" / "run"
    res = run_cli(
        "--rosbag", str(bag), "--cloud-topic", "/velodyne_points", "--tf", "odom",
        "--origin", origin, "--yaw", "30", "--points-per-scan", "2000", "--out", str(out),
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "pointcloud_20m_10overlap: 4 submaps" in res.output
    assert f"d.bag: {FRAMES} of {FRAMES} clouds on /velodyne_points used; poses from /tf" in (
        res.output
    )
    assert tree_bytes(out) == tree_bytes(kitti_run)


def test_cli_list_topics(small_bag: Path) -> None:
    res = run_cli("--rosbag", str(small_bag), "--list")
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    assert lines[0].split() == ["TOPIC", "TYPE", "MESSAGES", "USE", "WITH"]
    assert lines[2].split() == ["/odom", "nav_msgs/msg/Odometry", "4", "--pose-topic"]
    assert lines[3].split() == ["/points", "sensor_msgs/msg/PointCloud2", "4", "--cloud-topic"]
    assert lines[4].split() == ["/tf", "tf2_msgs/msg/TFMessage", "4", "--tf", "FRAME"]
    assert len(lines) == 6


def test_cli_bad_rosbag_input_exits_2_with_one_line(small_bag: Path, tmp_path: Path) -> None:
    text = tmp_path / "notes.bag"
    text.write_text("not a bag\n")
    out = tmp_path / "run"
    base = ["--out", str(out)]
    bag = ["--rosbag", str(small_bag)]
    cases = [
        ([*bag, "--cloud-topic", "/points", "--pose-topic", "/odom2"], "topic '/odom2' not found"),
        ([*bag, "--cloud-topic", "/odom", "--pose-topic", "/odom"], "holds nav_msgs/msg/Odometry"),
        ([*bag, "--cloud-topic", "/points"], "--rosbag needs --pose-topic TOPIC or --tf FRAME"),
        ([*bag, "--pose-topic", "/odom"], "--rosbag needs --cloud-topic"),
        ([*bag, "--cloud-topic", "/points", "--pose-topic", "/odom", "--tf", "odom"], "not both"),
        ([*bag, "--cloud-topic", "/points", "--tf", "map"], "no chain of transforms from 'map'"),
        ([*bag, "--cloud-topic", "/points", "--pose-topic", "/odom", "--poses", "p.csv"],
         "do not apply to --rosbag"),
        (["--rosbag", str(text), "--cloud-topic", "/p", "--tf", "odom"], "not a readable ROS bag"),
        (["--kitti", str(tmp_path), "--cloud-topic", "/points"], "--cloud-topic: applies to"),
        (["--kitti", str(tmp_path), "--rosbag", str(small_bag)], "give one of --kitti"),
        (["--list"], "--list: applies to --rosbag only"),
    ]  # fmt: skip
    for args, message in cases:
        res = run_cli(*args, *base)
        assert res.exit_code == 2, (args, res.output)
        errors = [line for line in res.output.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and message in errors[0], (args, res.output)
    res = run_cli(*bag, "--cloud-topic", "/points", "--pose-topic", "/odom")
    assert res.exit_code == 2 and "--out: missing" in res.output
    assert not out.exists()


def test_cli_poses_that_do_not_overlap_leave_nothing(tmp_path: Path) -> None:
    path = write_late_poses_bag(tmp_path / "late.bag")
    out = tmp_path / "run"
    res = run_cli("--rosbag", str(path), "--cloud-topic", "/points", "--pose-topic", "/odom",
                  "--out", str(out))  # fmt: skip
    assert res.exit_code == 2
    assert f"error: {path}: pose topic '/odom' does not overlap the clouds" in res.output
    assert not out.exists()
