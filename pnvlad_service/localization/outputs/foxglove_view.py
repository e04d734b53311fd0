"""The live view and its file: a drive's steps as Foxglove's own schemas, through the Foxglove
SDK (extra ``view``), to a WebSocket server the Foxglove app connects to (``--foxglove``)
and/or an MCAP file (``--mcap``). One context, one set of channels: the same calls feed both.

Topics (frame ``map`` unless said; :mod:`.step` for the frames and units):

==========================  ===================  ==============================================
``/tf``                     FrameTransforms      ``utm`` -> ``map`` (the origin, at the start)
                                                 and ``map`` -> ``sensor`` (each pose)
``/pnvlad/map/entries``     PointCloud           the map entries' origins (at the start)
``/pnvlad/map/cloud``       PointCloud           a downsampled cloud of the map (at the start)
``/pnvlad/scan``            PointCloud           the scan, laid at its pose (its ``pose``)
``/pnvlad/pose``            PoseInFrame          the pose
``/pnvlad/pose/covariance`` SceneUpdate          the pose's 1-sigma ellipsoid (x, y, z)
``/pnvlad/truth``           PoseInFrame          the true pose
``/pnvlad/path``            PosesInFrame         the poses so far (every 10th step, the end)
``/pnvlad/truth/path``      PosesInFrame         the true poses so far (the same)
``/pnvlad/state``           JSON                 state, state_code, reason, errors, sigma
``/pnvlad/fix``             LocationFix          latitude, longitude (where the zone is known)
==========================  ===================  ==============================================

Every message is logged at the scan's timestamp. The map and ``utm`` -> ``map`` are logged at
the start; a client that subscribes to them later gets them again at the next step.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.extras import require
from pnvlad_service.localization.outputs.step import (
    PATH_EVERY,
    DriveStep,
    Frames,
    MapView,
    quaternion,
    thinned,
)

log = logging.getLogger(__name__)

#: The most points of a scan sent (a stride thins a larger one).
SCAN_POINTS = 20_000
#: The largest 1-sigma radius drawn (m): an unconstrained direction is drawn this long.
MAX_SIGMA_DRAWN_M = 50.0
#: The latched topics: sent again to a client that subscribes after the start.
LATCHED = ("/tf", "/pnvlad/map/entries", "/pnvlad/map/cloud")

#: ``/pnvlad/state``'s JSON schema (what the Plot panel offers).
STATE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "scan": {"type": "integer"},
        "stamp_ns": {"type": "integer"},
        "state": {"type": ["string", "null"]},
        "state_code": {"type": "integer", "description": "0 searching, 1 tracking, 2 lost"},
        "event": {"type": ["string", "null"]},
        "reason": {"type": ["string", "null"]},
        "how": {"type": ["string", "null"]},
        "verified": {"type": ["boolean", "null"]},
        "pose_error_m": {"type": ["number", "null"]},
        "pose_yaw_error_deg": {"type": ["number", "null"]},
        "sigma_m": {"type": ["number", "null"]},
        "fitness": {"type": ["number", "null"]},
        "confidence": {"type": ["number", "null"]},
    },
}


def parse_host_port(text: str | None, default_port: int = 8765) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT``, ``HOST`` or ``""`` (127.0.0.1:8765); InputError naming
    ``--foxglove`` for anything else."""
    text = (text or "").strip()
    host, _, port = text.rpartition(":") if ":" in text else (text, "", "")
    host = host or "127.0.0.1"
    try:
        number = int(port) if port else default_port
    except ValueError:
        raise InputError(f"{text!r} is not HOST:PORT (e.g. 127.0.0.1:8765)", "--foxglove") from None
    if not 0 <= number <= 65535:
        raise InputError(f"port {number} is not in 0-65535", "--foxglove")
    return host, number


class _Latch:
    """A server listener: a client subscribed to a latched topic (the map is sent again)."""

    def __init__(self) -> None:
        self.wanted = threading.Event()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        if channel.topic in LATCHED:
            self.wanted.set()


class FoxgloveView:
    """The live view (``serve``: ``(host, port)``) and/or the MCAP file (``mcap``) of a drive.

    Opening fails at once (a port in use, an MCAP that cannot be created): RuntimeError or
    OSError with one line. The MCAP is written under a temporary name and renamed at
    :meth:`close`; ``port``: the server's port (0 asks the system for a free one)."""

    def __init__(self, serve: tuple[str, int] | None = None, mcap: str | Path | None = None):
        fg = require("foxglove", "foxglove-sdk", "view", "the live view (--foxglove, --mcap)")
        self.fg = fg
        self.context = fg.Context()
        self.server: Any = None
        self.writer: Any = None
        self.mcap = None if mcap is None else Path(mcap)
        parts = []
        if serve is not None:
            parts.append(f"--foxglove {serve[0]}:{serve[1]}")
        if self.mcap is not None:
            parts.append(f"--mcap {self.mcap}")
        self.name = " ".join(parts) or "foxglove"
        self.latch = _Latch()
        self._channels()
        if self.mcap is not None:
            self._partial = self.mcap.with_name(f".{self.mcap.name}.partial")
            try:
                self.mcap.parent.mkdir(parents=True, exist_ok=True)
                self.writer = fg.open_mcap(self._partial, allow_overwrite=True,
                                           context=self.context)  # fmt: skip
            except (OSError, RuntimeError) as exc:
                raise OSError(f"--mcap {self.mcap}: {exc}") from None
        if serve is not None:
            try:
                self.server = fg.start_server(
                    name="pnvlad", host=serve[0], port=serve[1], context=self.context,
                    server_listener=self.latch,
                )  # fmt: skip
            except RuntimeError as exc:
                self.abort()
                raise RuntimeError(f"--foxglove {serve[0]}:{serve[1]}: {exc}") from None
            log.info("the live view: ws://%s:%d (Foxglove: Open connection, Foxglove WebSocket)",
                     serve[0], self.server.port)  # fmt: skip
        self.frames = Frames((0.0, 0.0))
        self.view: MapView | None = None
        self.path: list[Any] = []
        self.truth_path: list[Any] = []
        self._last_ns = 0
        self._started = False
        self._steps = self._paths_at = 0

    @property
    def port(self) -> int | None:
        """The server's port (``None`` without a server)."""
        return None if self.server is None else int(self.server.port)

    def _channels(self) -> None:
        from foxglove import Channel
        from foxglove import channels as ch

        c = self.context
        self.tf = ch.FrameTransformsChannel("/tf", context=c)
        self.entries = ch.PointCloudChannel("/pnvlad/map/entries", context=c)
        self.cloud = ch.PointCloudChannel("/pnvlad/map/cloud", context=c)
        self.scan = ch.PointCloudChannel("/pnvlad/scan", context=c)
        self.pose = ch.PoseInFrameChannel("/pnvlad/pose", context=c)
        self.ellipse = ch.SceneUpdateChannel("/pnvlad/pose/covariance", context=c)
        self.truth = ch.PoseInFrameChannel("/pnvlad/truth", context=c)
        self.poses = ch.PosesInFrameChannel("/pnvlad/path", context=c)
        self.truths = ch.PosesInFrameChannel("/pnvlad/truth/path", context=c)
        self.state = Channel("/pnvlad/state", schema=STATE_SCHEMA, context=c)
        self.fix = ch.LocationFixChannel("/pnvlad/fix", context=c)

    # -- messages ------------------------------------------------------------------------------

    def _stamp(self, ns: int) -> Any:
        return self.fg.messages.Timestamp(int(ns // 1_000_000_000), int(ns % 1_000_000_000))

    def _pose(self, matrix: np.ndarray) -> Any:
        m = self.fg.messages
        x, y, z, w = quaternion(matrix[:3, :3])
        t = matrix[:3, 3]
        return m.Pose(position=m.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                      orientation=m.Quaternion(x=x, y=y, z=z, w=w))  # fmt: skip

    def _cloud(self, points: np.ndarray, ns: int, pose: np.ndarray | None = None) -> Any:
        m = self.fg.messages
        f32 = m.PackedElementFieldNumericType.Float32
        fields = [m.PackedElementField(name=n, offset=4 * k, type=f32)
                  for k, n in enumerate("xyz")]  # fmt: skip
        data = np.ascontiguousarray(points, dtype=np.float32).tobytes()
        return m.PointCloud(timestamp=self._stamp(ns), frame_id="map",
                            pose=self._pose(np.eye(4) if pose is None else pose),
                            point_stride=12, fields=fields, data=data)  # fmt: skip

    def _transform(self, matrix: np.ndarray, ns: int, parent: str, child: str) -> Any:
        m = self.fg.messages
        x, y, z, w = quaternion(matrix[:3, :3])
        t = matrix[:3, 3]
        return m.FrameTransform(
            timestamp=self._stamp(ns), parent_frame_id=parent, child_frame_id=child,
            translation=m.Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])),
            rotation=m.Quaternion(x=x, y=y, z=z, w=w),
        )  # fmt: skip

    def _origin_tf(self, ns: int) -> Any:
        origin = np.eye(4)
        origin[0, 3], origin[1, 3] = self.frames.origin
        return self._transform(origin, ns, "utm", "map")

    def _log_map(self, ns: int) -> None:
        m = self.fg.messages
        self.tf.log(m.FrameTransforms(transforms=[self._origin_tf(ns)]), log_time=ns)
        if self.view is None:
            return
        if len(self.view.entries):
            pts = self.frames.points_to_map(self.view.entries)
            self.entries.log(self._cloud(pts, ns), log_time=ns)
        if len(self.view.cloud):
            self.cloud.log(self._cloud(self.frames.points_to_map(self.view.cloud), ns),
                           log_time=ns)  # fmt: skip

    def _ellipse(self, cov: np.ndarray, pose: np.ndarray, ns: int) -> Any:
        m = self.fg.messages
        w, v = np.linalg.eigh(np.asarray(cov, dtype=np.float64)[:3, :3])
        if np.linalg.det(v) < 0:
            v[:, 0] = -v[:, 0]
        sigma = np.minimum(np.sqrt(np.maximum(w, 0.0)), MAX_SIGMA_DRAWN_M)
        axes = np.eye(4)
        axes[:3, :3], axes[:3, 3] = v, pose[:3, 3]
        sphere = m.SpherePrimitive(
            pose=self._pose(axes),
            size=m.Vector3(x=2 * float(sigma[0]), y=2 * float(sigma[1]), z=2 * float(sigma[2])),
            color=m.Color(r=1.0, g=0.6, b=0.0, a=0.35),
        )
        entity = m.SceneEntity(timestamp=self._stamp(ns), frame_id="map", id="covariance",
                               spheres=[sphere])  # fmt: skip
        return m.SceneUpdate(entities=[entity])

    # -- the sink ------------------------------------------------------------------------------

    def start(self, frames: Frames, view: MapView | None) -> None:
        self.frames, self.view = frames, view
        self._started = False

    def step(self, step: DriveStep) -> None:
        m, ns = self.fg.messages, step.stamp_ns
        if not self._started or self.latch.wanted.is_set():
            self.latch.wanted.clear()
            self._log_map(ns)
            self._started = True
        self._last_ns = ns
        stamp = self._stamp(ns)
        pose = None if step.pose is None else self.frames.to_map(step.pose)
        if pose is not None:
            p = self._pose(pose)
            self.pose.log(m.PoseInFrame(timestamp=stamp, frame_id="map", pose=p), log_time=ns)
            self.path.append(p)
            tf = self._transform(pose, ns, "map", "sensor")
            self.tf.log(m.FrameTransforms(transforms=[tf]), log_time=ns)
            if step.covariance is not None:
                self.ellipse.log(self._ellipse(step.covariance, pose, ns), log_time=ns)
            if step.points is not None and len(step.points):
                pts = step.points[:: max(1, -(-len(step.points) // SCAN_POINTS))]
                self.scan.log(self._cloud(pts, ns, pose), log_time=ns)
        if step.truth is not None:
            g = self._pose(self.frames.to_map(step.truth))
            self.truth.log(m.PoseInFrame(timestamp=stamp, frame_id="map", pose=g), log_time=ns)
            self.truth_path.append(g)
        self._steps += 1
        if self._steps % PATH_EVERY == 1 or PATH_EVERY == 1:
            self._log_paths(ns)
        self.state.log(step.figures(), log_time=ns)
        if step.latlon is not None and step.pose is not None:
            cov = step.covariance_or_unknown()[:3, :3].reshape(-1)
            known = m.LocationFixPositionCovarianceType
            kind = known.Known if step.covariance is not None else known.Unknown
            self.fix.log(m.LocationFix(
                timestamp=stamp, frame_id="sensor", latitude=step.latlon[0],
                longitude=step.latlon[1], altitude=float(step.pose[2, 3]),
                position_covariance=[float(v) for v in cov], position_covariance_type=kind,
            ), log_time=ns)  # fmt: skip

    def _log_paths(self, ns: int) -> None:
        """The paths so far (:data:`~.step.PATH_EVERY`, :func:`~.step.thinned`)."""
        m, stamp = self.fg.messages, self._stamp(ns)
        self.poses.log(m.PosesInFrame(timestamp=stamp, frame_id="map", poses=thinned(self.path)),
                       log_time=ns)  # fmt: skip
        if self.truth_path:
            truth = m.PosesInFrame(timestamp=stamp, frame_id="map", poses=thinned(self.truth_path))
            self.truths.log(truth, log_time=ns)
        self._paths_at = self._steps

    def abort(self) -> None:
        """Stop the server and drop the MCAP (a failed view leaves no file)."""
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.writer is not None:
            self.writer.close()
            self.writer = None
            self._partial.unlink(missing_ok=True)

    def close(self) -> list[Path]:
        if self._started and self._paths_at != self._steps:
            self._log_paths(self._last_ns)  # the whole drive's
        if self.server is not None:
            self.server.stop()
            self.server = None
        if self.writer is None:
            return []
        self.writer.close()
        self.writer = None
        assert self.mcap is not None
        os.replace(self._partial, self.mcap)
        return [self.mcap]
