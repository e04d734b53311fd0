"""A recorded ROS bag as a drive: PointCloud2 scans with their poses, read lazily.

:class:`RosbagDrive` has the face of every other drive (the ``Drive`` protocol of
:mod:`pnvlad_service.data.drive`): ``timestamps`` int64 [T] µs, ``poses`` float64 [T, 4, 4]
sensor-to-world (x east, y north, z up, UTM metres) and ``scan(i)`` [N, 3] sensor frame, so the
bag is cut into submaps by the same code path as a KITTI sequence or a CSV drive.

- Bags: ROS 1 ``.bag``, ROS 2 folders (``metadata.yaml``; sqlite3 or mcap storage) and bare
  ``.db3`` / ``.mcap`` files, read by the pure-Python ``rosbags`` library (the extra ``rosbag``),
  imported only when a bag is opened.
- Clouds: ``sensor_msgs/msg/PointCloud2`` with fields x, y, z of type float32 or float64, any
  point step, extra fields (intensity, ring, time, ...), organised (height > 1, rows possibly
  padded) or not, either byte order. Decoded with a numpy structured dtype, no per-point loop;
  points with a NaN or infinite coordinate (an organised cloud's missing returns) are dropped
  and counted in :attr:`RosbagDrive.stats`, and so are the missing returns a driver writes as
  points at the sensor's origin (Ouster's; :func:`~pnvlad_service.io.readers.drop_no_returns`),
  in :attr:`RosbagDrive.no_returns`.
- Poses: a topic of ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseStamped`` or
  ``geometry_msgs/msg/PoseWithCovarianceStamped`` (the pose of the message's child frame,
  else of the cloud's frame, in its header frame), or the transforms of ``/tf`` and
  ``/tf_static`` from a fixed frame to the cloud's frame, chained through as many frames as the
  tree holds. Poses are interpolated to each scan's header time, linearly in position and by
  slerp in rotation; scans before or after the pose stream, or in a gap of it longer than
  ``max_pose_gap_s``, are dropped and counted. An odometry pose of another frame than the
  cloud's is moved to the cloud's frame through ``/tf_static`` when the bag has that extrinsic.
- Placement: the fixed frame (the odometry's ``odom``, the ``--tf`` frame) is taken as a local
  metric frame with z up; ``origin_ne`` (northing, easting) puts its origin in UTM and
  ``yaw_deg`` turns its x axis counter-clockwise from east, exactly as a KITTI sequence is
  placed (:func:`.kitti.kitti_poses_to_world`; translations snapped to the same grid, so a bag
  and a KITTI sequence of the same scans and poses give the same bytes).

Clouds are decoded by :mod:`.pointcloud2`, poses interpolated and /tf chained by
:mod:`.pose_streams`. Scans are read lazily: opening the drive indexes the cloud topic (each
message's bag time and header stamp, parsed from the first bytes of the message without
decoding the cloud) and reads the pose stream; :meth:`RosbagDrive.scan` decodes
one cloud. Reads in time order stream through the bag (what the submap cutter does); a jump back
or far ahead reopens the stream at the message's bag time. Every problem with the bag (not a
bag, truncated, a missing topic or one of another type, a cloud without x/y/z, poses that do not
overlap the clouds) is an :class:`~pnvlad_service.errors.InputError` whose source is the bag and
whose message names the topic.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from pnvlad_service.data.drive import place_in_utm
from pnvlad_service.data.sources.pointcloud2 import CloudError, decode_pointcloud2, header_stamp
from pnvlad_service.data.sources.pose_streams import (
    POSE_AFTER,
    POSE_BEFORE,
    POSE_GAP,
    POSE_OK,
    PoseStream,
    TransformTree,
    rotations,
)
from pnvlad_service.data.sources.returns import NoReturnCount
from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.io.readers import drop_no_returns

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

log = logging.getLogger(__name__)

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
POSE_COV_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: Message types a ``pose_topic`` may have.
POSE_TYPES = (ODOMETRY_TYPE, POSE_STAMPED_TYPE, POSE_COV_TYPE)


#: A read this many messages or fewer ahead of the stream's position advances the stream;
#: farther (or backwards) it is reopened at the message's bag time.
_STREAM_AHEAD = 32


def _anyreader() -> type[AnyReader]:
    try:
        from rosbags.highlevel import AnyReader
    except ImportError:
        raise MissingDependencyError("rosbags", "rosbag", "Reading ROS bags") from None
    return AnyReader


def _open_bag(bag: Path) -> AnyReader:
    """An open ``AnyReader`` on ``bag``; InputError (source: the bag) when it cannot be read."""
    if not bag.exists():
        raise InputError("no such bag (a ROS 1 .bag, a ROS 2 bag folder, .db3 or .mcap)", bag)
    if bag.is_file() and bag.suffix not in (".bag", ".db3", ".mcap"):
        with open(bag, "rb") as fh:
            head = fh.read(13)
        hint = (
            "it starts like a ROS 1 bag: name it *.bag"
            if head.startswith(b"#ROSBAG")
            else "expected a ROS 1 .bag, a ROS 2 bag folder (metadata.yaml), .db3 or .mcap"
        )
        raise InputError(f"not a ROS bag ({hint})", bag)
    any_reader = _anyreader()
    from rosbags.typesys import Stores, get_typestore

    try:
        # ROS 2 bags recorded before Iron carry no message definitions: use the standard ones.
        reader = any_reader([bag], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except Exception as exc:  # rosbags raises many kinds (ReaderError, apsw, struct, KeyError)
        raise InputError(
            f"not a readable ROS bag (truncated, damaged or another format: {_reason(exc)})", bag
        ) from None
    return reader


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _reason(exc: BaseException) -> str:
    text = " ".join(str(a) for a in exc.args) or type(exc).__name__
    return text if len(text) < 300 else text[:297] + "..."


# --------------------------------------------------------------------------------------------
# Topics


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag: its name, message type (``None`` when it has several) and count."""

    name: str
    msgtype: str | None
    count: int


def _topics(reader: AnyReader) -> list[BagTopic]:
    return [
        BagTopic(name, info.msgtype, int(info.msgcount))
        for name, info in sorted(reader.topics.items())
    ]


def list_topics(bag: str | Path) -> list[BagTopic]:
    """The topics of ``bag`` sorted by name, with message types and counts (for ``--list``)."""
    bag = Path(bag)
    reader = _open_bag(bag)
    try:
        return _topics(reader)
    finally:
        reader.close()


def _connections(
    reader: AnyReader, bag: Path, topic: str, types: Sequence[str], what: str
) -> tuple[list[Any], str]:
    """The connections of ``topic`` and its type, which must be one of ``types``."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        fitting = [t.name for t in _topics(reader) if t.msgtype in types]
        hint = f"{what} topics in the bag: {', '.join(fitting)}" if fitting else f"no {what} topic"
        raise InputError(f"topic {topic!r} not found ({hint})", bag)
    found = {c.msgtype for c in conns}
    if len(found) != 1 or next(iter(found)) not in types:
        raise InputError(
            f"topic {topic!r} holds {', '.join(sorted(found))}, not {' or '.join(types)}", bag
        )
    return conns, next(iter(found))


@dataclass
class RosbagStats:
    """What a :class:`RosbagDrive` read and dropped.

    ``clouds``: messages on the cloud topic; ``scans``: kept as the drive's scans;
    ``before_poses`` / ``after_poses`` / ``in_pose_gaps``: dropped for want of a pose;
    ``duplicate_stamps``: dropped because an earlier cloud had the same µs stamp;
    ``nonfinite_points`` / ``scans_with_nonfinite``: NaN or infinite returns dropped from the
    scans read so far (they grow as :meth:`RosbagDrive.scan` is called).
    """

    clouds: int = 0
    scans: int = 0
    before_poses: int = 0
    after_poses: int = 0
    in_pose_gaps: int = 0
    duplicate_stamps: int = 0
    nonfinite_points: int = 0
    scans_with_nonfinite: int = 0

    def dropped(self) -> str:
        """'12 before the poses, 3 after' style summary of the dropped clouds ('' if none)."""
        parts = [
            (self.before_poses, "before the pose stream"),
            (self.after_poses, "after the pose stream"),
            (self.in_pose_gaps, "in gaps of the pose stream"),
            (self.duplicate_stamps, "with a repeated stamp"),
        ]
        return ", ".join(f"{n} {what}" for n, what in parts if n)


# --------------------------------------------------------------------------------------------
# The drive


_Clouds = TypeVar("_Clouds", bound="RosbagClouds")


class RosbagClouds:
    """The clouds of a bag's PointCloud2 topic, in time order, without poses.

    ``timestamps`` int64 [T] µs (header stamps, sorted, a repeated stamp dropped), ``scan(i)``
    [N, 3] sensor frame, ``frame_id``, ``stats`` (:class:`RosbagStats`); what the replay of a
    bag without poses needs. :class:`RosbagDrive` adds the poses. Arguments as there; holds
    the bag open until :meth:`close` (also a context manager).
    """

    def __init__(
        self,
        bag: str | Path,
        cloud_topic: str,
        *,
        use_log_time: bool = False,
        tf_topics: tuple[str, str] = ("/tf", "/tf_static"),
        name: str | None = None,
    ) -> None:
        self.bag = Path(bag)
        self.cloud_topic = cloud_topic
        self.name = name or (self.bag.stem if self.bag.is_file() else self.bag.name)
        self.use_log_time = use_log_time
        self.tf_topics = tf_topics
        self.stats = RosbagStats()
        self.no_returns = NoReturnCount()
        self._reader: AnyReader | None = _open_bag(self.bag)
        self._stream: Generator[tuple[Any, int, bytes], None, None] | None = None
        self._next = 0
        try:
            self._conns, _ = _connections(
                self._reader, self.bag, cloud_topic, (CLOUD_TYPE,), "PointCloud2"
            )
            self._index_clouds()
        except BaseException:
            self.close()
            raise
        # Stamps rounded to µs must increase strictly: sort, drop repeats (the first kept).
        stamps_us = (self._stamp_ns + 500) // 1000
        order = np.lexsort((np.arange(len(stamps_us)), stamps_us))
        repeat = np.r_[False, np.diff(stamps_us[order]) == 0]
        self.stats.duplicate_stamps = int(repeat.sum())
        self._msg_index = order[~repeat]
        self.timestamps = stamps_us[self._msg_index].astype(np.int64)
        self.stats.scans = len(self._msg_index)

    # -- reading the bag ------------------------------------------------------------------

    def _where(self, what: str) -> str:
        return f"topic {self.cloud_topic!r}: {what}"

    def _messages(
        self, conns: list[Any], start: int | None = None
    ) -> Generator[tuple[Any, int, bytes], None, None]:
        """(connection, bag time, raw) of ``conns``; errors become InputErrors about the bag."""
        assert self._reader is not None
        topic = conns[0].topic
        gen = self._reader.messages(connections=conns, start=start)
        while True:
            try:
                item = next(gen)
            except StopIteration:
                return
            except Exception as exc:
                raise InputError(
                    f"topic {topic!r}: cannot read the bag (truncated or damaged? {_reason(exc)})",
                    self.bag,
                ) from None
            yield item

    def topic_messages(
        self, topic: str, types: Sequence[str], what: str
    ) -> Generator[tuple[int, Any], None, None]:
        """(stamp ns: the header's, else the bag's time; message) of every message on ``topic``
        in bag order. ``InputError`` naming the bag for a missing topic, one of a type not in
        ``types`` (``what`` names them), or a message that does not decode."""
        assert self._reader is not None
        conns, msgtype = _connections(self._reader, self.bag, topic, types, what)
        for _, t, raw in self._messages(conns):
            msg = self._deserialize(raw, msgtype, topic)
            header = getattr(msg, "header", None)
            yield (_stamp_ns(header.stamp) if header is not None else 0) or int(t), msg

    def _deserialize(self, raw: bytes, msgtype: str, topic: str) -> Any:
        assert self._reader is not None
        try:
            return self._reader.deserialize(raw, msgtype)
        except Exception as exc:
            raise InputError(
                f"topic {topic!r}: a message does not decode as {msgtype} ({_reason(exc)})",
                self.bag,
            ) from None

    def _index_clouds(self) -> None:
        """Bag times, stamps and frames of every cloud; the first cloud decoded as a check."""
        assert self._reader is not None
        ros2 = bool(self._reader.is2)
        log_ns: list[int] = []
        stamps: list[int] = []
        frames: set[str] = set()
        for conn, t, raw in self._messages(self._conns):
            try:
                head = header_stamp(raw, ros2)
            except (struct.error, IndexError):
                raise InputError(
                    self._where(f"message {len(log_ns)} is too short for a PointCloud2"), self.bag
                ) from None
            if head is None:
                msg = self._deserialize(raw, conn.msgtype, conn.topic)
                head = (_stamp_ns(msg.header.stamp), msg.header.frame_id)
            log_ns.append(t)
            stamps.append(head[0])
            frames.add(head[1].lstrip("/"))
        if not log_ns:
            raise InputError(self._where("no messages"), self.bag)
        if len(frames) > 1:
            raise InputError(
                self._where(f"clouds in several frames ({', '.join(sorted(frames))})"), self.bag
            )
        self.frame_id = frames.pop()
        self.stats.clouds = len(log_ns)
        self._log_ns = np.asarray(log_ns, dtype=np.int64)
        header = np.asarray(stamps, dtype=np.int64)
        if not self.use_log_time and np.any(header == 0):
            log.warning("%s: clouds with zero header stamps; using the bag's times", self.bag)
            self.use_log_time = True
        self._stamp_ns = self._log_ns if self.use_log_time else header
        self._decode(0)  # a cloud without x/y/z fails here, not after the poses are read
        self._stream = None  # one stream at a time: some storages share a file position

    def _raw_cloud(self, k: int) -> bytes:
        """The raw bytes of message ``k`` of the cloud topic (in bag order)."""
        if self._reader is None:
            self._reader = _open_bag(self.bag)
            self._stream = None
        if self._stream is None or k < self._next or k > self._next + _STREAM_AHEAD:
            if self._stream is not None:
                self._stream.close()
            t = int(self._log_ns[k])
            self._stream = self._messages(self._conns, start=t)
            self._next = int(np.searchsorted(self._log_ns, t, side="left"))
        raw = b""
        while self._next <= k:
            try:
                _, _, raw = next(self._stream)
            except StopIteration:
                raise InputError(
                    self._where(f"message {k} vanished (the bag changed while read?)"), self.bag
                ) from None
            self._next += 1
        return raw

    def _decode(self, k: int) -> np.ndarray:
        raw = self._raw_cloud(k)
        msg = self._deserialize(raw, CLOUD_TYPE, self.cloud_topic)
        try:
            return decode_pointcloud2(msg)
        except CloudError as exc:
            raise InputError(self._where(f"message {k}: {exc}"), self.bag) from None

    # -- the Drive face -------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.timestamps)

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i``: [N, 3] sensor frame, metres (float32 if the cloud is); NaNs and missing
        returns written as points at the origin dropped (counted in ``stats`` and
        ``no_returns``)."""
        pts = self._decode(int(self._msg_index[i]))
        finite = np.isfinite(pts[:, 0])  # column by column: 20x faster than .all(axis=1)
        finite &= np.isfinite(pts[:, 1])
        finite &= np.isfinite(pts[:, 2])
        bad = len(pts) - int(finite.sum())
        if bad:
            self.stats.nonfinite_points += bad
            self.stats.scans_with_nonfinite += 1
            pts = pts[finite]
        pts, dropped = drop_no_returns(pts)
        self.no_returns.add(dropped, self._where(f"scan {i}"))
        return pts

    def close(self) -> None:
        """Close the bag (a later :meth:`scan` opens it again)."""
        self._stream = None
        reader, self._reader = self._reader, None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # closing a reader that failed half-way
                log.debug("closing %s failed", self.bag, exc_info=True)

    def __enter__(self: _Clouds) -> _Clouds:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.bag)!r}, {self.cloud_topic!r}, {len(self)} scans)"


class RosbagDrive(RosbagClouds):
    """A ROS bag's clouds and poses as a drive (see the module docstring).

    - ``bag``: a ROS 1 ``.bag`` file, a ROS 2 bag folder, or a ``.db3`` / ``.mcap`` file.
    - ``cloud_topic``: a ``sensor_msgs/msg/PointCloud2`` topic.
    - exactly one of ``pose_topic`` (Odometry, PoseStamped or PoseWithCovarianceStamped) and
      ``tf_frame`` (the fixed frame of ``/tf`` + ``/tf_static`` that the cloud's frame is
      posed in, e.g. ``odom`` or ``map``).
    - ``origin_ne`` (northing, easting) and ``yaw_deg``: where the fixed frame lies in UTM and
      which way its x axis points (counter-clockwise from east), as for a KITTI sequence.
    - ``max_pose_gap_s``: scans between two pose samples further apart than this are dropped
      (``None``: interpolate across any gap).
    - ``use_log_time``: time scans and poses by when the bag recorded them, not by their header
      stamps (used anyway, with a warning, for a stream whose stamps are all zero).
    - ``tf_topics``: the dynamic and static transform topics.

    Attributes as the ``Drive`` protocol, plus ``stats`` (:class:`RosbagStats`), ``frame_id``
    (the clouds' frame) and ``pose_source`` (a line saying where the poses came from). Holds the
    bag open until :meth:`close` (also a context manager).
    """

    def __init__(
        self,
        bag: str | Path,
        cloud_topic: str,
        *,
        pose_topic: str | None = None,
        tf_frame: str | None = None,
        origin_ne: tuple[float, float] = (0.0, 0.0),
        yaw_deg: float = 0.0,
        max_pose_gap_s: float | None = 2.0,
        use_log_time: bool = False,
        tf_topics: tuple[str, str] = ("/tf", "/tf_static"),
        name: str | None = None,
    ) -> None:
        if (pose_topic is None) == (tf_frame is None):
            raise InputError("give either a pose topic or a /tf fixed frame (not both)", bag)
        if max_pose_gap_s is not None and not max_pose_gap_s > 0:
            raise InputError(f"must be > 0 seconds, got {max_pose_gap_s}", "max_pose_gap_s")
        super().__init__(
            bag, cloud_topic, use_log_time=use_log_time, tf_topics=tf_topics, name=name
        )
        try:
            gap = None if max_pose_gap_s is None else round(max_pose_gap_s * 1e9)
            local = self._poses(pose_topic, tf_frame, gap)
        except BaseException:
            self.close()
            raise
        self.poses = place_in_utm(local, origin_ne, yaw_deg)

    # -- poses ----------------------------------------------------------------------------

    def _read_stream(self, conns: list[Any], msgtype: str) -> tuple[PoseStream, str, str | None]:
        """A pose topic as a stream: (poses of its child frame, parent frame, child frame)."""
        topic = conns[0].topic
        rows, parents, children = [], set(), set()
        for _, t, raw in self._messages(conns):
            msg = self._deserialize(raw, msgtype, topic)
            pose = msg.pose if msgtype == POSE_STAMPED_TYPE else msg.pose.pose
            stamp = _stamp_ns(msg.header.stamp)
            rows.append(
                (
                    t if self.use_log_time or stamp == 0 else stamp,
                    (pose.position.x, pose.position.y, pose.position.z),
                    (
                        pose.orientation.x,
                        pose.orientation.y,
                        pose.orientation.z,
                        pose.orientation.w,
                    ),
                )
            )
            parents.add(msg.header.frame_id.lstrip("/"))
            if msgtype == ODOMETRY_TYPE:
                children.add(msg.child_frame_id.lstrip("/"))
        if not rows:
            raise InputError(f"topic {topic!r}: no messages", self.bag)
        try:
            rotations(np.array([r[2] for r in rows], dtype=np.float64))
        except ValueError as exc:
            raise InputError(f"topic {topic!r}: {exc}", self.bag) from None
        child = children.pop() if len(children) == 1 else None
        parent = parents.pop() if len(parents) == 1 else "?"
        return PoseStream.of(rows), parent, child

    def _poses(self, pose_topic: str | None, tf_frame: str | None, gap: int | None) -> np.ndarray:
        """Local poses (fixed frame <- cloud frame) of the kept scans; drops the others."""
        assert self._reader is not None
        query = self._stamp_ns[self._msg_index]
        if pose_topic is not None:
            conns, msgtype = _connections(self._reader, self.bag, pose_topic, POSE_TYPES, "pose")
            stream, parent, child = self._read_stream(conns, msgtype)
            poses, status = stream.at(query, gap)
            span = (int(stream.times[0]), int(stream.times[-1]))
            source = f"{pose_topic} ({msgtype.rsplit('/', 1)[-1]}, {parent} <- {child or 'pose'})"
            if child is not None and child != self.frame_id:
                tree = self._tf_tree(static_only=True)
                if tree.has_path(self.frame_id, child):
                    poses = poses @ tree.chain(child, self.frame_id, query, gap)[0]
                    source += f" + /tf_static {child} <- {self.frame_id}"
                else:
                    log.warning(
                        "%s: %s poses frame %r, the clouds are in %r and /tf_static does not "
                        "link them: using the poses as the clouds' frame's",
                        self.bag,
                        pose_topic,
                        child,
                        self.frame_id,
                    )
            what = f"pose topic {pose_topic!r}"
        else:
            assert tf_frame is not None
            tree = self._tf_tree(static_only=False)
            fixed = tf_frame.lstrip("/")
            if not tree.has_path(fixed, self.frame_id):
                raise InputError(
                    f"{self.tf_topics[0]}: no chain of transforms from {fixed!r} to the clouds' "
                    f"frame {self.frame_id!r} (frames: {', '.join(tree.frames()) or 'none'})",
                    self.bag,
                )
            poses, status, span = tree.chain(fixed, self.frame_id, query, gap)
            source = f"{self.tf_topics[0]} {fixed} <- {self.frame_id}"
            what = f"{self.tf_topics[0]} ({fixed} <- {self.frame_id})"
        keep = status == POSE_OK
        self.stats.before_poses = int(np.sum(status == POSE_BEFORE))
        self.stats.after_poses = int(np.sum(status == POSE_AFTER))
        self.stats.in_pose_gaps = int(np.sum(status == POSE_GAP))
        if not keep.any():
            raise InputError(
                f"{what} does not overlap the clouds on {self.cloud_topic!r}: poses "
                f"{_span(span)}, clouds {_span((int(query.min()), int(query.max())))}",
                self.bag,
            )
        self._msg_index = self._msg_index[keep]
        self.timestamps = self.timestamps[keep]
        self.stats.scans = len(self._msg_index)
        self.pose_source = source
        dropped = self.stats.dropped()
        if dropped:
            log.warning(
                "%s: %d of %d clouds dropped: %s",
                self.bag,
                self.stats.clouds - self.stats.scans,
                self.stats.clouds,
                dropped,
            )
        return poses[keep]

    def _tf_tree(self, *, static_only: bool) -> TransformTree:
        assert self._reader is not None
        tree = TransformTree()
        dyn, stat = self.tf_topics
        for topic, is_static in ((stat, True), (dyn, False)):
            if static_only and not is_static:
                continue
            conns = [c for c in self._reader.connections if c.topic == topic]
            if not conns:
                if not is_static:
                    raise InputError(f"no {topic} topic (transforms) in the bag", self.bag)
                continue
            conns, _ = _connections(self._reader, self.bag, topic, (TF_TYPE,), "TFMessage")
            for _, t, raw in self._messages(conns):
                msg = self._deserialize(raw, TF_TYPE, topic)
                for tr in msg.transforms:
                    stamp = _stamp_ns(tr.header.stamp)
                    try:
                        tree.add(
                            tr.header.frame_id.lstrip("/"),
                            tr.child_frame_id.lstrip("/"),
                            t if self.use_log_time or stamp == 0 else stamp,
                            tr.transform,
                            static=is_static,
                        )
                    except ValueError as exc:
                        raise InputError(f"{topic}: {exc}", self.bag) from None
        try:
            return tree.finish()
        except ValueError as exc:
            raise InputError(f"{' + '.join(self.tf_topics)}: {exc}", self.bag) from None


def _span(span: tuple[int, int]) -> str:
    return f"{span[0] / 1e9:.3f}..{span[1] / 1e9:.3f} s"
