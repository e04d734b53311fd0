"""localization/outputs: a drive's steps written by each sink and read back by an independent
reader (the ``mcap`` reader with the file's protobuf schemas, ``rosbags``, evo's file
interface), compared with the steps that went in; the ``map`` frame, the rotations and the
covariance's 21 values; a sink that fails is dropped with one error while the others go on."""

from __future__ import annotations

import math
import socket
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pnvlad_service.errors import InputError
from pnvlad_service.localization.outputs.sinks import Outputs, open_outputs
from pnvlad_service.localization.outputs.step import (
    COVARIANCE_COLUMNS,
    UNKNOWN_VARIANCE,
    DriveStep,
    Frames,
    MapView,
    from_upper_triangle,
    quaternion,
    roll_pitch_yaw,
    upper_triangle,
)
from pnvlad_service.localization.outputs.trajectory import Trajectories

EAST, NORTH = 619_234.5, 5_734_721.25
T0_NS = 1_772_813_593_000_000_000


def pose_at(k: int) -> np.ndarray:
    """A pose of a drive heading west with some roll and pitch (sensor -> UTM)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("ZYX", [math.pi - 0.01 * k, 0.02, -0.015]).as_matrix()
    out[:3, 3] = [EAST - 4.0 * k, NORTH + 0.1 * k, 4.0 + 0.01 * k]
    return out


def covariance(k: int) -> np.ndarray:
    a = np.random.default_rng(k).normal(size=(6, 6))
    return a @ a.T * 1e-3 + np.eye(6) * 1e-4


def steps(n: int = 12) -> list[DriveStep]:
    """Searching for 3 scans (no pose), then tracking with a covariance on even scans; the
    truth on every scan but the last."""
    out = []
    for k in range(n):
        has = k >= 3
        truth = pose_at(k).copy()
        truth[0, 3] += 0.5
        out.append(DriveStep(
            scan=k, stamp_ns=T0_NS + k * 400_000_000 + 123, state="tracking" if has else
            "searching", how="registered" if has else None, verified=has,
            pose=pose_at(k) if has else None,
            covariance=covariance(k) if has and k % 2 == 0 else None,
            truth=truth if k < n - 1 else None,
            points=np.random.default_rng(k).normal(size=(500, 3)).astype(np.float32),
            pose_error_m=0.5 if has else None, sigma_m=0.2 if has else None,
        ))  # fmt: skip
    return out


def a_map() -> MapView:
    entries = np.array([[EAST - 40.0 * k, NORTH, 3.0] for k in range(5)])
    cloud = entries[:, None, :] + np.random.default_rng(0).normal(size=(5, 50, 3))
    return MapView(entries=entries, cloud=cloud.reshape(-1, 3), utm_zone="32U")


# -- the frame, the rotations, the covariance -------------------------------------------------


def test_the_map_frame_is_utm_less_a_rounded_origin() -> None:
    frames = Frames.around(np.array([619_234.5, 618_999.0]), np.array([5_734_721.0, 5_735_100.0]))
    assert frames.origin == (618_000.0, 5_734_000.0)
    moved = frames.to_map(pose_at(2))
    assert moved[0, 3] == pytest.approx(pose_at(2)[0, 3] - 618_000.0, abs=1e-9)
    assert np.array_equal(moved[:3, :3], pose_at(2)[:3, :3])
    assert Frames.around(np.array([np.nan]), np.array([np.nan])).origin == (0.0, 0.0)


def test_quaternion_and_roll_pitch_yaw_agree_with_scipy() -> None:
    rng = np.random.default_rng(3)
    for rot in Rotation.random(200, random_state=rng):
        m = rot.as_matrix()
        q = np.array(quaternion(m))
        ref = rot.as_quat()
        assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-9 and q[3] >= 0
        roll, pitch, yaw = roll_pitch_yaw(m)
        back = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()
        assert np.abs(back - m).max() < 1e-9


def test_a_long_path_is_thinned_evenly_and_keeps_its_last_pose() -> None:
    from pnvlad_service.localization.outputs.step import thinned

    assert thinned(list(range(5)), 10) == [0, 1, 2, 3, 4]
    long = list(range(10_001))
    out = thinned(long, 2000)
    assert len(out) <= 2000 and out[0] == 0 and out[-1] == 10_000
    assert len(set(np.diff(out[:-1]))) == 1  # evenly


def test_the_covariance_round_trips_through_its_21_values() -> None:
    c = covariance(5)
    values = upper_triangle(c)
    assert len(values) == len(COVARIANCE_COLUMNS) == 21
    assert COVARIANCE_COLUMNS[:2] == ("cov_x_x", "cov_x_y") and COVARIANCE_COLUMNS[-1] == (
        "cov_yaw_yaw"
    )
    assert values[6] == c[1, 1] and values[1] == c[0, 1] and values[-1] == c[5, 5]
    assert np.array_equal(from_upper_triangle(values), c)
    with pytest.raises(ValueError, match="21 values"):
        from_upper_triangle(values[:20])


# -- TUM and KITTI, read by evo ---------------------------------------------------------------


def test_tum_and_kitti_files_read_by_evo_give_back_the_poses(tmp_path: Path) -> None:
    fi = pytest.importorskip("evo.tools.file_interface")
    done = steps()
    with Outputs([Trajectories(tmp_path / "drive")]) as outputs:
        outputs.start(a_map())
        for s in done:
            outputs.step(s)
    frames = a_map().frames()
    names = sorted(p.name for p in outputs.written)
    assert names == ["drive.kitti", "drive.kitti.times", "drive.truth.kitti", "drive.truth.tum",
                     "drive.tum"]  # fmt: skip
    posed = [s for s in done if s.pose is not None]
    tum = fi.read_tum_trajectory_file(str(tmp_path / "drive.tum"))
    assert tum.num_poses == len(posed)
    assert np.allclose(tum.timestamps, [s.stamp_ns / 1e9 for s in posed], rtol=0, atol=1e-6)
    for got, s in zip(tum.poses_se3, posed, strict=True):
        assert np.abs(got - frames.to_map(s.pose)).max() < 1e-8
    truth = fi.read_tum_trajectory_file(str(tmp_path / "drive.truth.tum"))
    assert truth.num_poses == sum(s.truth is not None for s in done)
    both = [s for s in posed if s.truth is not None]
    kitti = fi.read_kitti_poses_file(str(tmp_path / "drive.kitti"))
    kitti_truth = fi.read_kitti_poses_file(str(tmp_path / "drive.truth.kitti"))
    assert kitti.num_poses == kitti_truth.num_poses == len(both)
    for got, gt, s in zip(kitti.poses_se3, kitti_truth.poses_se3, both, strict=True):
        assert np.abs(got - frames.to_map(s.pose)).max() < 1e-8
        assert np.abs(gt - frames.to_map(s.truth)).max() < 1e-8
    times = np.loadtxt(tmp_path / "drive.kitti.times")
    assert np.allclose(times, [s.stamp_ns / 1e9 for s in both], rtol=0, atol=1e-6)
    head = (tmp_path / "drive.tum").read_text().splitlines()[0]
    assert "UTM east, north, up minus (619000.000, 5734000.000) m, zone 32U" in head


# -- the ROS 2 bag, read by rosbags ------------------------------------------------------------


def test_the_ros2_bag_read_by_rosbags(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from rosbags.highlevel import AnyReader

    done = steps()
    outputs = open_outputs(ros2_bag=tmp_path / "drive_ros2")
    outputs.start(a_map())
    for s in done:
        outputs.step(s)
    assert outputs.close() == [tmp_path / "drive_ros2"] and outputs.errors == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive_ros2"]  # nothing left beside
    frames = a_map().frames()
    posed = [s for s in done if s.pose is not None]
    with AnyReader([tmp_path / "drive_ros2"]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {
            "/pnvlad/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
            "/pnvlad/path": "nav_msgs/msg/Path",
            "/pnvlad/truth": "geometry_msgs/msg/PoseStamped",
            "/pnvlad/fix": "sensor_msgs/msg/NavSatFix",
            "/pnvlad/state": "std_msgs/msg/String",
            "/tf": "tf2_msgs/msg/TFMessage",
            "/tf_static": "tf2_msgs/msg/TFMessage",
        }
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts["/pnvlad/pose"] == counts["/tf"] == len(posed)
        # The path every 10th scan (scan 11 here; scans 1-3 had no pose) and at the end.
        assert counts["/pnvlad/path"] == 2
        paths = [c for c in reader.connections if c.topic == "/pnvlad/path"]
        *_, (_, _, raw) = reader.messages(paths)
        path = reader.deserialize(raw, paths[0].msgtype)
        assert counts["/pnvlad/state"] == len(done) and counts["/tf_static"] == 1
        assert counts["/pnvlad/truth"] == sum(s.truth is not None for s in done)
        poses = [c for c in reader.connections if c.topic == "/pnvlad/pose"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(poses)]
        static = next(c for c in reader.connections if c.topic == "/tf_static")
        (_, _, raw), = reader.messages([static])  # fmt: skip
        origin = reader.deserialize(raw, static.msgtype).transforms[0]
    assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec for p in path.poses] == [
        s.stamp_ns for s in posed
    ]
    assert (origin.header.frame_id, origin.child_frame_id) == ("utm", "map")
    assert (origin.transform.translation.x, origin.transform.translation.y) == frames.origin
    for msg, s in zip(msgs, posed, strict=True):
        assert msg.header.frame_id == "map"
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == s.stamp_ns
        p, want = msg.pose.pose.position, frames.to_map(s.pose)
        assert (p.x, p.y, p.z) == pytest.approx(tuple(want[:3, 3]), abs=1e-9)
        o = msg.pose.pose.orientation
        assert np.allclose([o.x, o.y, o.z, o.w], quaternion(want[:3, :3]), atol=1e-12)
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        expected = s.covariance if s.covariance is not None else np.eye(6) * UNKNOWN_VARIANCE
        assert np.array_equal(cov, expected)


# -- the MCAP, read by the mcap reader with the file's own schemas -------------------------------


def test_the_mcap_read_by_the_mcap_reader(tmp_path: Path) -> None:
    pytest.importorskip("foxglove")
    reader_mod = pytest.importorskip("mcap.reader")
    from pnvlad_service.localization.outputs.mcap_track import _Decoders, read_track

    done = steps()
    outputs = open_outputs(mcap=tmp_path / "drive.mcap")
    outputs.start(a_map())
    for s in done:
        outputs.step(s)
    assert outputs.close() == [tmp_path / "drive.mcap"] and outputs.errors == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive.mcap"]
    with open(tmp_path / "drive.mcap", "rb") as fh:
        reader = reader_mod.make_reader(fh)
        summary = reader.get_summary()
        schemas = {summary.channels[c].topic: summary.schemas[summary.channels[c].schema_id].name
                   for c in summary.channels}  # fmt: skip
        counts = {summary.channels[c].topic: n
                  for c, n in summary.statistics.channel_message_counts.items()}  # fmt: skip
        dec = _Decoders()
        first = next(reader.iter_messages(topics=["/pnvlad/pose"]))
        pose = dec.decode(first[0], first[2].data)
    assert schemas["/pnvlad/pose"] == "foxglove.PoseInFrame"
    assert schemas["/pnvlad/scan"] == "foxglove.PointCloud"
    assert schemas["/pnvlad/pose/covariance"] == "foxglove.SceneUpdate"
    assert schemas["/tf"] == "foxglove.FrameTransforms"
    assert schemas["/pnvlad/fix"] == "foxglove.LocationFix"
    posed = [s for s in done if s.pose is not None]
    assert counts["/pnvlad/pose"] == counts["/pnvlad/scan"] == counts["/pnvlad/fix"] == len(posed)
    assert counts["/pnvlad/pose/covariance"] == sum(s.covariance is not None for s in posed)
    assert counts["/pnvlad/state"] == len(done)
    assert counts["/pnvlad/path"] == counts["/pnvlad/truth/path"] == 3  # steps 1, 11, the end
    assert counts["/pnvlad/map/entries"] == counts["/pnvlad/map/cloud"] == 1
    assert counts["/tf"] == len(posed) + 1  # map -> sensor each pose, utm -> map once
    frames = a_map().frames()
    want = frames.to_map(posed[0].pose)
    assert pose.frame_id == "map"
    assert pose.timestamp.seconds * 10**9 + pose.timestamp.nanos == posed[0].stamp_ns
    got = pose.pose.position
    assert (got.x, got.y, got.z) == pytest.approx(tuple(want[:3, 3]), abs=1e-9)
    track = read_track(tmp_path / "drive.mcap")  # in UTM again
    assert np.abs(track.pose_enu - [s.pose[:3, 3] for s in posed]).max() < 1e-6
    assert list(track.pose_ns) == [s.stamp_ns for s in posed]
    assert np.abs(track.entries - a_map().entries).max() < 1e-3  # float32 in the map frame


# -- failures and the zone ---------------------------------------------------------------------


def test_a_port_in_use_an_unwritable_output_and_a_bad_zone_are_one_error_each(
    tmp_path: Path,
) -> None:
    pytest.importorskip("foxglove")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        blocked = tmp_path / "file"
        blocked.write_text("")
        outputs = open_outputs(foxglove=("127.0.0.1", port), ros2_bag=blocked / "drive_ros2",
                               trajectories=tmp_path / "ok" / "drive")  # fmt: skip
    assert len(outputs.errors) == 2 and len(outputs.sinks) == 1
    assert f"--foxglove 127.0.0.1:{port}: " in outputs.errors[0]
    assert "Address already in use" in outputs.errors[0]
    assert "file" in outputs.errors[1] and all("\n" not in e for e in outputs.errors)
    outputs.start(a_map(), utm_zone="99Q")
    assert outputs.errors[2] == "utm_zone: '99Q': UTM zone number 99 is not in 1-60 (e.g. " \
        "'30U', '32N', '17 south')"  # fmt: skip
    for s in steps():
        outputs.step(s)
    assert [p.name for p in outputs.close()] == [
        "drive.tum",
        "drive.truth.tum",
        "drive.kitti",
        "drive.truth.kitti",
        "drive.kitti.times",
    ]
    assert len(outputs.errors) == 3


class Breaks:
    """A sink whose disk fills at its third step."""

    name = "--breaks"

    def __init__(self) -> None:
        self.seen, self.aborted = 0, False

    def start(self, frames: Frames, view: MapView | None) -> None:
        pass

    def step(self, step: DriveStep) -> None:
        self.seen += 1
        if self.seen == 3:
            raise OSError(28, "No space left on device")

    def abort(self) -> None:
        self.aborted = True

    def close(self) -> list[Path]:
        raise AssertionError("a failed sink is aborted, not closed")


def test_a_sink_that_fails_midway_is_dropped_and_the_others_go_on(tmp_path: Path) -> None:
    broken = Breaks()
    outputs = Outputs([broken, Trajectories(tmp_path / "drive")])
    outputs.start(None)  # no map: the frame from the first position
    done = steps()
    for s in done:
        outputs.step(s)
    written = outputs.close()
    assert broken.seen == 3 and broken.aborted
    assert outputs.errors == ["--breaks: [Errno 28] No space left on device"]
    assert (tmp_path / "drive.tum").read_text().count("\n") == 1 + sum(
        s.pose is not None for s in done
    )
    assert tmp_path / "drive.tum" in written
    # The frame came from the first step with a position: the first truth.
    assert "minus (619000.000, 5734000.000) m;" in (tmp_path / "drive.tum").read_text()


def test_latitude_and_longitude_with_a_zone_and_none_without(tmp_path: Path) -> None:
    pytest.importorskip("pyproj")
    pytest.importorskip("rosbags")
    from rosbags.highlevel import AnyReader

    seen = []

    def latlon(zone: str, east: float, north: float) -> tuple[float, float]:
        seen.append((zone, east, north))
        from pnvlad_service.localization.outputs.sinks import utm_latlon

        return utm_latlon(zone, east, north)

    for zone, name in (("32U", "zoned"), ("", "unzoned")):
        outputs = Outputs([], latlon=latlon)
        outputs.add(lambda n=name: __import__(
            "pnvlad_service.localization.outputs.ros2bag", fromlist=["Ros2Bag"]
        ).Ros2Bag(tmp_path / n))  # fmt: skip
        outputs.start(a_map(), utm_zone=zone)
        for s in steps():
            outputs.step(s)
        outputs.close()
        assert outputs.errors == []
    posed = [s for s in steps() if s.pose is not None]
    assert [z for z, _, _ in seen] == ["32U"] * len(posed)  # none asked without a zone
    with AnyReader([tmp_path / "zoned"]) as reader:
        fix = [c for c in reader.connections if c.topic == "/pnvlad/fix"]
        msg = reader.deserialize(next(reader.messages(fix))[2], fix[0].msgtype)
    with AnyReader([tmp_path / "unzoned"]) as reader:
        assert "/pnvlad/fix" not in {c.topic for c in reader.connections}
    # Zone 32's central meridian is 9 degrees east; 619 km east of its false easting 500 km.
    assert 51.0 < msg.latitude < 52.5 and 10.5 < msg.longitude < 11.0
    import pyproj

    lon, lat = pyproj.Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(
        posed[0].pose[0, 3], posed[0].pose[1, 3]
    )
    assert (msg.latitude, msg.longitude) == pytest.approx((lat, lon), abs=1e-9)
    assert posed[0].covariance is None and msg.position_covariance_type == 0  # UNKNOWN


def test_the_host_and_port_of_foxglove() -> None:
    from pnvlad_service.localization.outputs.foxglove_view import parse_host_port

    assert parse_host_port("") == ("127.0.0.1", 8765)
    assert parse_host_port(":9000") == ("127.0.0.1", 9000)
    assert parse_host_port("0.0.0.0:8766") == ("0.0.0.0", 8766)
    assert parse_host_port("localhost") == ("localhost", 8765)
    with pytest.raises(InputError, match="--foxglove: 'a:b' is not HOST:PORT"):
        parse_host_port("a:b")
    with pytest.raises(InputError, match="--foxglove: port 70000 is not in 0-65535"):
        parse_host_port(":70000")


def test_the_layout_names_what_the_view_streams(tmp_path: Path) -> None:
    """docs/foxglove_layout.json: every panel of its tree configured, every topic it draws one
    the view writes, every field it plots one of ``/pnvlad/state``'s."""
    import json

    pytest.importorskip("foxglove")
    reader_mod = pytest.importorskip("mcap.reader")
    from pnvlad_service.localization.outputs.foxglove_view import STATE_SCHEMA

    outputs = open_outputs(mcap=tmp_path / "drive.mcap")
    outputs.start(a_map())
    for s in steps():
        outputs.step(s)
    outputs.close()
    with open(tmp_path / "drive.mcap", "rb") as fh:
        summary = reader_mod.make_reader(fh).get_summary()
    streamed = {c.topic for c in summary.channels.values()}
    layout = json.loads((Path(__file__).parents[2] / "docs" / "foxglove_layout.json").read_text())
    panels = layout["configById"]

    def leaves(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert isinstance(node, dict)
        return leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    three_d = next(v for k, v in panels.items() if k.startswith("3D!"))
    drawn = set(three_d["topics"])
    paths = [p["value"] for k, v in panels.items() for p in v.get("paths", [])]
    others = {v.get("topicPath") or v.get("followTopic") for v in panels.values()} - {None}
    assert drawn | others <= streamed and {"/pnvlad/scan", "/pnvlad/pose"} <= drawn
    fields = {p.split(".", 1)[1] for p in paths if p.startswith("/pnvlad/state.")}
    assert fields and fields <= set(STATE_SCHEMA["properties"]) and len(fields) == len(paths)


def test_a_ros2_bag_named_like_a_ros1_file_or_already_there_is_refused(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    (tmp_path / "there").mkdir()
    outputs = open_outputs(ros2_bag=tmp_path / "drive.bag")
    outputs.add(lambda: __import__(
        "pnvlad_service.localization.outputs.ros2bag", fromlist=["Ros2Bag"]
    ).Ros2Bag(tmp_path / "there"))  # fmt: skip
    assert outputs.sinks == [] and outputs.errors == [
        f"{tmp_path / 'drive.bag'}: a ROS 2 bag is a folder; .bag names a ROS 1 bag's file "
        "(readers tell them by it): name it without .bag",
        f"{tmp_path / 'there'}: already exists (a bag is never overwritten)",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["there"]


def test_without_pyproj_the_outputs_go_on_without_latitude(tmp_path: Path) -> None:
    from pnvlad_service.errors import MissingDependencyError

    calls = []

    def latlon(zone: str, east: float, north: float) -> tuple[float, float]:
        calls.append(zone)
        raise MissingDependencyError("pyproj", "geo", "latitude and longitude")

    outputs = Outputs([Trajectories(tmp_path / "drive")], latlon=latlon)
    outputs.start(a_map(), utm_zone="32U")
    for s in steps():
        outputs.step(s)
    assert (tmp_path / "drive.tum") in outputs.close()
    assert calls == ["32U"] and len(outputs.errors) == 1
    assert "pip install 'pnvlad[geo]'" in outputs.errors[0]
