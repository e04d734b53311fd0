"""Writing ROS bags: a drive's scans and poses as PointCloud2 and Odometry (or /tf) messages.

The other side of :mod:`pnvlad_service.data.sources.rosbag`, for users without a bag of their own (a
synthetic run written as a bag, benchmarks/make_rosbag.py) and for the tests, which write small
bags with ``rosbags``' own writers (extra ``rosbag``):

- :class:`BagWriter`: a new ROS 1 ``.bag`` (``ros=1``) or ROS 2 bag folder (``ros=2``, sqlite3
  or mcap storage), messages built from the writer's typestore (``writer.types``).
- :func:`pointcloud2` / :func:`odometry` / :func:`tf_message` / :func:`navsatfix`: messages
  from numpy arrays.
- :func:`write_drive_bag`: every scan of a drive with its pose, in a local ``odom`` frame whose
  origin is ``origin_ne`` in UTM (so ``--origin`` with the same numbers puts it back).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from pnvlad_service.data.sources.pointcloud2 import POINTFIELD_TYPES
from pnvlad_service.errors import InputError, MissingDependencyError

TF_TYPE = "tf2_msgs/msg/TFMessage"

#: numpy type code -> PointField datatype.
_POINTFIELD = {code: datatype for datatype, code in POINTFIELD_TYPES.items()}


class BagWriter:
    """A new bag at ``path``: ROS 1 (``.bag`` file) or ROS 2 (a folder, sqlite3 or mcap).

    ``ros`` defaults to 1 for a ``.bag`` path and 2 otherwise. ``writer.types[name]`` are the
    message classes (``"sensor_msgs/msg/PointCloud2"``, ...); :meth:`write` serialises a message
    and adds its topic on first use. A context manager; an exception inside it removes nothing
    (``rosbags`` refuses to overwrite, so a failed bag must be deleted before writing again).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        ros: Literal[1, 2] | None = None,
        storage: Literal["sqlite3", "mcap"] = "sqlite3",
    ) -> None:
        try:
            from rosbags.typesys import Stores, get_typestore
        except ImportError:
            raise MissingDependencyError("rosbags", "rosbag", "Writing ROS bags") from None
        self.path = Path(path)
        self.ros = ros if ros is not None else (1 if self.path.suffix == ".bag" else 2)
        if self.path.exists():
            raise InputError("already exists (a bag is never overwritten)", self.path)
        if self.ros == 1:
            from rosbags.rosbag1 import Writer as Writer1
            from rosbags.typesys import get_types_from_msg

            self.typestore = get_typestore(Stores.ROS1_NOETIC)
            # Noetic's store lacks tf2_msgs; its definition is one line.
            self.typestore.register(
                get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_TYPE)
            )
            self._writer: Any = Writer1(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
            self.typestore = get_typestore(Stores.ROS2_HUMBLE)
            self._writer = Writer2(self.path, version=9, storage_plugin=plugin)
        self.types = self.typestore.types
        self._connections: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        self._writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self._writer.close()

    def write(self, topic: str, msg: Any, time_ns: int) -> None:
        """Append ``msg`` (of the writer's types) to ``topic`` at bag time ``time_ns``."""
        msgtype = msg.__msgtype__
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = conn
        if self.ros == 1:
            raw = self.typestore.serialize_ros1(msg, msgtype)
        else:
            raw = self.typestore.serialize_cdr(msg, msgtype)
        self._writer.write(conn, int(time_ns), raw)


def _header(types: Any, stamp_ns: int, frame_id: str) -> Any:
    time = types["builtin_interfaces/msg/Time"](
        sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000)
    )
    header = types["std_msgs/msg/Header"]
    if "seq" in header.__dataclass_fields__:  # ROS 1
        return header(seq=0, stamp=time, frame_id=frame_id)
    return header(stamp=time, frame_id=frame_id)


def pointcloud2(
    types: Any,
    points: np.ndarray,
    stamp_ns: int,
    frame_id: str,
    *,
    height: int = 1,
    row_padding: int = 0,
) -> Any:
    """A PointCloud2 message of ``points``: float [N, 3] (fields x, y, z) or a structured array.

    A structured array's fields (any numeric types, e.g. x, y, z, intensity, ring, time) become
    the message's, at their offsets; its byte order sets ``is_bigendian``. ``height`` > 1 makes
    an organised cloud of ``height`` rows (N must divide); ``row_padding`` bytes are added after
    each row (``row_step`` > ``width * point_step``).
    """
    arr = np.asarray(points)
    if arr.dtype.names is None:
        arr = np.ascontiguousarray(arr)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise ValueError(f"points must be [N, 3] or a structured array, got {arr.shape}")
        flat = arr.astype(arr.dtype.newbyteorder("="), copy=False)
        arr = np.rec.fromarrays(flat.T, names="x,y,z").view(np.ndarray)
    arr = arr.reshape(-1)
    field_cls = types["sensor_msgs/msg/PointField"]
    names = arr.dtype.names
    fields = []
    for name in names:
        dt, offset = arr.dtype.fields[name][:2]
        code = _POINTFIELD[f"{dt.kind}{dt.itemsize}"]
        fields.append(field_cls(name=name, offset=offset, datatype=code, count=1))
    big = any(arr.dtype.fields[n][0].byteorder == ">" for n in names)
    if len(arr) % height:
        raise ValueError(f"{len(arr)} points do not make {height} rows")
    width = len(arr) // height
    step = arr.dtype.itemsize
    rows = arr.view(np.uint8).reshape(height, width * step)
    data = np.zeros((height, width * step + row_padding), dtype=np.uint8)
    data[:, : width * step] = rows
    return types["sensor_msgs/msg/PointCloud2"](
        header=_header(types, stamp_ns, frame_id),
        height=height,
        width=width,
        fields=fields,
        is_bigendian=bool(big),
        point_step=step,
        row_step=width * step + row_padding,
        data=data.reshape(-1),
        is_dense=all(n in names and bool(np.isfinite(arr[n]).all()) for n in "xyz"),
    )


def _pose_parts(types: Any, pose: np.ndarray) -> tuple[Any, Any]:
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=np.float64)
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return (
        types["geometry_msgs/msg/Point"](x=pose[0, 3], y=pose[1, 3], z=pose[2, 3]),
        types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
    )


def odometry(
    types: Any, pose: np.ndarray, stamp_ns: int, frame_id: str = "odom", child: str = "velodyne"
) -> Any:
    """A nav_msgs/Odometry: ``pose`` float64 [4, 4] is ``frame_id`` <- ``child``; no twist."""
    position, orientation = _pose_parts(types, pose)
    pose_msg = types["geometry_msgs/msg/Pose"](position=position, orientation=orientation)
    cov = np.zeros(36)
    twist = types["geometry_msgs/msg/Twist"](
        linear=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return types["nav_msgs/msg/Odometry"](
        header=_header(types, stamp_ns, frame_id),
        child_frame_id=child,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg, covariance=cov),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov.copy()),
    )


def navsatfix(
    types: Any,
    latitude: float,
    longitude: float,
    altitude: float,
    stamp_ns: int,
    frame_id: str = "gps",
    std_m: float | None = None,
) -> Any:
    """A sensor_msgs/NavSatFix (status: a fix) at WGS 84 ``latitude``, ``longitude`` (degrees)
    and ``altitude`` (metres); ``std_m``: the horizontal standard deviation, written as a
    diagonal ``position_covariance`` (type 2, diagonal known), else type 0 (unknown)."""
    cov = np.zeros(9)
    kind = 0
    if std_m is not None:
        cov[0] = cov[4] = std_m**2 / 2.0
        cov[8] = std_m**2
        kind = 2
    status = types["sensor_msgs/msg/NavSatStatus"](status=0, service=1)
    return types["sensor_msgs/msg/NavSatFix"](
        header=_header(types, stamp_ns, frame_id),
        status=status,
        latitude=float(latitude),
        longitude=float(longitude),
        altitude=float(altitude),
        position_covariance=cov,
        position_covariance_type=kind,
    )


def tf_message(types: Any, transforms: list[tuple[str, str, np.ndarray, int]]) -> Any:
    """A tf2_msgs/TFMessage of (parent, child, float64 [4, 4] parent <- child, stamp ns)."""
    out = []
    for parent, child, pose, stamp in transforms:
        position, rotation = _pose_parts(types, pose)
        out.append(
            types["geometry_msgs/msg/TransformStamped"](
                header=_header(types, stamp, parent),
                child_frame_id=child,
                transform=types["geometry_msgs/msg/Transform"](
                    translation=types["geometry_msgs/msg/Vector3"](
                        x=position.x, y=position.y, z=position.z
                    ),
                    rotation=rotation,
                ),
            )
        )
    return types[TF_TYPE](transforms=out)


def write_drive_bag(
    drive: Any,
    path: str | Path,
    *,
    origin_ne: tuple[float, float] = (0.0, 0.0),
    cloud_topic: str = "/points",
    odom_topic: str = "/odom",
    frame_id: str = "lidar",
    odom_frame: str = "odom",
    truth: np.ndarray | None = None,
    truth_topic: str = "/ground_truth",
    tf_topic: str | None = None,
    ros: Literal[1, 2] | None = None,
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
    progress: bool = False,
) -> Path:
    """Write every scan of ``drive`` (PointCloud2, float32 x, y, z) and its pose (Odometry).

    Poses are written in ``odom_frame``, the UTM frame shifted so that ``origin_ne`` (northing,
    easting) is its origin (``RosbagDrive(..., origin_ne=origin_ne)`` reads them back in UTM);
    ``truth`` (float64 [T, 4, 4], UTM) adds a second Odometry topic, e.g. a simulated drive's
    true poses; ``tf_topic`` (e.g. ``"/tf"``) also writes each pose as a transform
    ``odom_frame`` <- ``frame_id``. Messages are stamped with the drive's timestamps (µs -> ns).
    """
    shift = np.array([origin_ne[1], origin_ne[0], 0.0])
    poses = np.asarray(drive.poses, dtype=np.float64).copy()
    poses[:, :3, 3] -= shift
    if truth is not None:
        truth = np.asarray(truth, dtype=np.float64).copy()
        truth[:, :3, 3] -= shift
    from pnvlad_service.progress import tqdm

    with BagWriter(path, ros=ros, storage=storage) as bag:
        for i in tqdm(range(len(drive)), desc="bag", unit="scan", disable=not progress):
            ns = int(drive.timestamps[i]) * 1000
            pts = np.asarray(drive.scan(i), dtype=np.float32)
            bag.write(cloud_topic, pointcloud2(bag.types, pts, ns, frame_id), ns)
            bag.write(odom_topic, odometry(bag.types, poses[i], ns, odom_frame, frame_id), ns)
            if truth is not None:
                msg = odometry(bag.types, truth[i], ns, odom_frame, frame_id)
                bag.write(truth_topic, msg, ns)
            if tf_topic is not None:
                msg = tf_message(bag.types, [(odom_frame, frame_id, poses[i], ns)])
                bag.write(tf_topic, msg, ns)
    return Path(path)
