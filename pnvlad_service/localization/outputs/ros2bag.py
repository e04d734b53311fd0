"""A drive's poses as a ROS 2 bag (MCAP storage, the ``rosbags`` writer, extra ``rosbag``) that
``ros2 bag play`` feeds to a ROS 2 stack (frames and units: :mod:`.step`):

=====================  ===========================================  =========================
``/pnvlad/pose``       geometry_msgs/msg/PoseWithCovarianceStamped  the pose and its
                                                                    covariance (nav2 / AMCL's
                                                                    ``/initialpose`` type)
``/pnvlad/path``       nav_msgs/msg/Path                            the poses so far (every
                                                                    10th scan, the end)
``/pnvlad/truth``      geometry_msgs/msg/PoseStamped                the true pose
``/pnvlad/fix``        sensor_msgs/msg/NavSatFix                    latitude, longitude
                                                                    (zone known)
``/pnvlad/state``      std_msgs/msg/String                          the state as JSON
``/tf``                tf2_msgs/msg/TFMessage                       ``map`` -> ``sensor``
``/tf_static``         tf2_msgs/msg/TFMessage                       ``utm`` -> ``map``
=====================  ===========================================  =========================

A pose without a covariance (a fix found by search, a pose carried on by the odometry)
carries a diagonal of :data:`~.step.UNKNOWN_VARIANCE`: nothing measured its spread. The bag
is written under a temporary name and renamed when it is closed.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.outputs.step import (
    PATH_EVERY,
    DriveStep,
    Frames,
    MapView,
    quaternion,
    thinned,
)


class Ros2Bag:
    """The ROS 2 bag of a drive at ``path`` (a folder that must not exist)."""

    def __init__(self, path: str | Path) -> None:
        from pnvlad_service.data.sources.rosbag_write import BagWriter

        self.path = Path(path)
        self.name = f"--ros2-bag {self.path}"
        if self.path.suffix == ".bag":
            raise InputError("a ROS 2 bag is a folder; .bag names a ROS 1 bag's file (readers "
                             "tell them by it): name it without .bag", self.path)  # fmt: skip
        if self.path.exists():
            raise InputError("already exists (a bag is never overwritten)", self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # Written inside a hidden folder beside it, under its own name (the bag's file is named
        # for its folder), and moved out when closed.
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._partial = self._tmp / self.path.name
        self.bag = BagWriter(self._partial, ros=2, storage="mcap")
        self.bag.__enter__()
        self.types = self.bag.types
        self.frames = Frames((0.0, 0.0))
        self.path_poses: list[Any] = []
        self._static = False
        self._steps = self._path_at = self._last_ns = 0

    def start(self, frames: Frames, view: MapView | None) -> None:
        self.frames = frames

    def _header(self, ns: int, frame: str) -> Any:
        t = self.types
        stamp = t["builtin_interfaces/msg/Time"](sec=int(ns // 1_000_000_000),
                                                 nanosec=int(ns % 1_000_000_000))  # fmt: skip
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def _pose(self, matrix: np.ndarray) -> Any:
        t = self.types
        x, y, z, w = quaternion(matrix[:3, :3])
        p = matrix[:3, 3]
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
            orientation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        )

    def _transform(self, ns: int, parent: str, child: str, matrix: np.ndarray) -> Any:
        t = self.types
        x, y, z, w = quaternion(matrix[:3, :3])
        p = matrix[:3, 3]
        return t["geometry_msgs/msg/TransformStamped"](
            header=self._header(ns, parent), child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(p[0]), y=float(p[1]),
                                                           z=float(p[2])),
                rotation=t["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
            ),
        )  # fmt: skip

    def step(self, step: DriveStep) -> None:
        t, ns, write = self.types, step.stamp_ns, self.bag.write
        tf_type = t["tf2_msgs/msg/TFMessage"]
        if not self._static:
            origin = np.eye(4)
            origin[0, 3], origin[1, 3] = self.frames.origin
            write("/tf_static", tf_type(transforms=[self._transform(ns, "utm", "map", origin)]),
                  ns)  # fmt: skip
            self._static = True
        if step.pose is not None:
            pose = self.frames.to_map(step.pose)
            msg = self._pose(pose)
            cov = step.covariance_or_unknown().reshape(-1).astype(np.float64)
            write("/pnvlad/pose", t["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=self._header(ns, "map"),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=msg, covariance=cov),
            ), ns)  # fmt: skip
            self.path_poses.append(t["geometry_msgs/msg/PoseStamped"](
                header=self._header(ns, "map"), pose=msg))  # fmt: skip
            write("/tf", tf_type(transforms=[self._transform(ns, "map", "sensor", pose)]), ns)
            if step.latlon is not None:
                write("/pnvlad/fix", self._fix(step, ns), ns)
        if step.truth is not None:
            write("/pnvlad/truth", t["geometry_msgs/msg/PoseStamped"](
                header=self._header(ns, "map"), pose=self._pose(self.frames.to_map(step.truth)),
            ), ns)  # fmt: skip
        write("/pnvlad/state", t["std_msgs/msg/String"](data=json.dumps(step.figures())), ns)
        self._steps, self._last_ns = self._steps + 1, ns
        if self.path_poses and (self._steps % PATH_EVERY == 1 or PATH_EVERY == 1):
            self._write_path(ns)

    def _write_path(self, ns: int) -> None:
        """The poses so far (:data:`~.step.PATH_EVERY`, :func:`~.step.thinned`)."""
        t = self.types
        path = t["nav_msgs/msg/Path"](header=self._header(ns, "map"),
                                      poses=thinned(self.path_poses))  # fmt: skip
        self.bag.write("/pnvlad/path", path, ns)
        self._path_at = self._steps

    def _fix(self, step: DriveStep, ns: int) -> Any:
        t = self.types
        fix = t["sensor_msgs/msg/NavSatFix"]
        status = t["sensor_msgs/msg/NavSatStatus"]
        assert step.latlon is not None and step.pose is not None
        cov = step.covariance_or_unknown()[:3, :3].reshape(-1).astype(np.float64)
        known = step.covariance is not None
        return fix(
            header=self._header(ns, "sensor"),
            status=status(status=status.STATUS_FIX, service=0),
            latitude=float(step.latlon[0]), longitude=float(step.latlon[1]),
            altitude=float(step.pose[2, 3]), position_covariance=cov,
            position_covariance_type=(fix.COVARIANCE_TYPE_KNOWN if known
                                      else fix.COVARIANCE_TYPE_UNKNOWN),
        )  # fmt: skip

    def abort(self) -> None:
        try:
            self.bag.__exit__(None, None, None)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def close(self) -> list[Path]:
        if self.path_poses and self._path_at != self._steps:
            self._write_path(self._last_ns)  # the whole drive's
        self.bag.__exit__(None, None, None)
        os.replace(self._partial, self.path)
        self._tmp.rmdir()
        return [self.path]
