"""What a drive step is, once, for every output: :class:`DriveStep` (one scan's state, pose,
covariance, truth and cloud), :class:`MapView` (the map drawn under it) and :class:`Frames`
(the ``map`` frame and its origin in UTM, the zone).

Frames and units (docs/TRACKING.md, "Frames and units"), the same in every output:

- ``utm``: UTM east, north, up (metres) of the map's zone; the drive's poses and the CSV's
  ``pose_northing`` / ``pose_easting`` are in it.
- ``map``: ``utm`` shifted by :attr:`Frames.origin` (east, north; no rotation, no height
  shift), so that the numbers a viewer draws stay small (a float32 renderer loses centimetres
  at 5,000 km). The live view, the MCAP, the ROS 2 bag and the TUM / KITTI files are in it;
  the transform ``utm`` -> ``map`` is in each of them (a frame transform, the file's header).
- ``sensor``: the LiDAR's own frame (x forward, y left, z up); a pose is ``sensor`` -> ``map``.
- Times: the scan's timestamp, UTC, nanoseconds in the MCAP, the bag and the live view,
  seconds in TUM files, microseconds in the CSV's ``timestamp``.
- Angles: roll, pitch, yaw as ROS's fixed axes (``R = Rz(yaw) Ry(pitch) Rx(roll)``), yaw
  counter-clockwise from east; degrees in the CSV, radians in the covariance.
- Covariance: float64 [6, 6], ROS's ``PoseWithCovariance`` order (x, y, z, rotation about x,
  y, z), metres and radians, ``map`` axes (UTM's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: The covariance's axes, in order (ROS's PoseWithCovariance).
AXES = ("x", "y", "z", "roll", "pitch", "yaw")
#: The variance given to a direction nothing constrains (the pose has no covariance): m^2 or
#: rad^2, as the registration's own covariance gives an unconstrained direction.
UNKNOWN_VARIANCE = 1e6
#: The origin of the ``map`` frame is the map's south-west corner rounded down to this (m).
ORIGIN_GRID_M = 1000.0
#: A path (the poses so far) is sent on the first step, every this many steps and at the end:
#: sent each step, a long drive's paths would grow its files with the square of its length.
PATH_EVERY = 10
#: ... of at most this many poses (a longer one thinned evenly, its last pose kept).
PATH_POSES = 2000
#: The states a drive step can be in, and the number each is plotted as.
STATE_CODES = {"searching": 0, "tracking": 1, "lost": 2}


@dataclass(frozen=True)
class Frames:
    """The ``map`` frame: ``origin`` (east, north) in UTM metres, and ``utm_zone`` (``""``:
    unknown, latitude/longitude are left out)."""

    origin: tuple[float, float]
    utm_zone: str = ""

    @classmethod
    def around(cls, east: np.ndarray, north: np.ndarray, utm_zone: str = "") -> Frames:
        """The frame whose origin is the south-west corner of these positions, rounded down
        to :data:`ORIGIN_GRID_M`."""
        e, n = np.asarray(east, dtype=np.float64), np.asarray(north, dtype=np.float64)
        ok = np.isfinite(e) & np.isfinite(n)
        if not ok.any():
            return cls((0.0, 0.0), utm_zone)
        grid = ORIGIN_GRID_M
        return cls((math.floor(e[ok].min() / grid) * grid, math.floor(n[ok].min() / grid) * grid),
                   utm_zone)  # fmt: skip

    def to_map(self, pose: np.ndarray) -> np.ndarray:
        """``pose`` (-> UTM, float64 [4, 4]) as a pose -> ``map``."""
        out = np.array(pose, dtype=np.float64)
        out[0, 3] -= self.origin[0]
        out[1, 3] -= self.origin[1]
        return out

    def points_to_map(self, points: np.ndarray) -> np.ndarray:
        """UTM points float [N, 3] in the ``map`` frame (float64)."""
        return np.asarray(points, dtype=np.float64) - [self.origin[0], self.origin[1], 0.0]


@dataclass(frozen=True, eq=False)
class DriveStep:
    """One scan of a drive as every output says it.

    ``scan``: its index in the drive; ``stamp_ns``: its timestamp (UTC, ns); ``state``
    (``searching``, ``tracking``, ``lost``; ``None`` for a scan asked alone), ``event``,
    ``reason``, ``how`` (``fix``, ``registered``, ``predicted``) and ``verified``; ``pose``:
    float64 [4, 4] sensor -> UTM, or ``None``; ``covariance``: float64 [6, 6] of the pose
    (module doc), ``None`` when the answer gave none; ``truth``: float64 [4, 4] sensor -> UTM
    or ``None``; ``points``: the scan float32 [N, 3] in the sensor frame (``None`` when not
    kept); the figures ``pose_error_m``, ``pose_yaw_error_deg``, ``sigma_m``, ``fitness``,
    ``confidence``; ``latlon``: the pose's WGS 84 latitude and longitude (degrees) where the
    zone is known."""

    scan: int
    stamp_ns: int
    state: str | None = None
    event: str | None = None
    reason: str | None = None
    how: str | None = None
    verified: bool | None = None
    pose: np.ndarray | None = None
    covariance: np.ndarray | None = None
    truth: np.ndarray | None = None
    points: np.ndarray | None = field(default=None, repr=False)
    pose_error_m: float | None = None
    pose_yaw_error_deg: float | None = None
    sigma_m: float | None = None
    fitness: float | None = None
    confidence: float | None = None
    latlon: tuple[float, float] | None = None

    def covariance_or_unknown(self) -> np.ndarray:
        """The covariance, or a diagonal of :data:`UNKNOWN_VARIANCE` when there is none (what a
        message that must carry one says of a pose nothing measured the spread of)."""
        if self.covariance is not None:
            return np.asarray(self.covariance, dtype=np.float64)
        return np.eye(6) * UNKNOWN_VARIANCE

    def figures(self) -> dict[str, object]:
        """The step's state and figures as plain values (the live view's ``/pnvlad/state``)."""
        return {
            "scan": self.scan,
            "stamp_ns": self.stamp_ns,
            "state": self.state,
            "state_code": STATE_CODES.get(self.state or "", -1),
            "event": self.event,
            "reason": self.reason,
            "how": self.how,
            "verified": self.verified,
            "pose_error_m": self.pose_error_m,
            "pose_yaw_error_deg": self.pose_yaw_error_deg,
            "sigma_m": self.sigma_m,
            "fitness": self.fitness,
            "confidence": self.confidence,
        }


@dataclass(frozen=True, eq=False)
class MapView:
    """The map under a drive: ``entries`` float64 [M, 3] (east, north, height of each entry's
    origin, UTM metres), ``cloud`` float64 [K, 3] (a downsampled cloud of its submaps or
    keyframes laid together, UTM metres; may be empty) and its ``utm_zone`` (``""``:
    unknown)."""

    entries: np.ndarray
    cloud: np.ndarray
    utm_zone: str = ""

    def frames(self) -> Frames:
        """The ``map`` frame of this map (:meth:`Frames.around` its entries)."""
        return Frames.around(self.entries[:, 0], self.entries[:, 1], self.utm_zone)


def thinned(items: list, most: int = PATH_POSES) -> list:
    """``items`` when at most ``most`` of them, else every k-th (k the smallest that gives at
    most ``most``) and the last."""
    if len(items) <= most:
        return list(items)
    k = -(-len(items) // (most - 1))
    out = list(items[::k])
    if out[-1] is not items[-1]:
        out.append(items[-1])
    return out


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w), unit, w >= 0, of a rotation matrix float [3, 3] (Shepperd's method)."""
    m = np.asarray(rotation, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    v = np.asarray(q)
    v = v / np.linalg.norm(v)
    if v[3] < 0:
        v = -v
    return float(v[0]), float(v[1]), float(v[2]), float(v[3])


def roll_pitch_yaw(rotation: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (ROS's fixed
    axes; yaw counter-clockwise from east)."""
    m = np.asarray(rotation, dtype=np.float64)
    pitch = math.asin(max(-1.0, min(1.0, -m[2, 0])))
    roll = math.atan2(m[2, 1], m[2, 2])
    yaw = math.atan2(m[1, 0], m[0, 0])
    return roll, pitch, yaw


def upper_triangle(covariance: np.ndarray) -> tuple[float, ...]:
    """The 21 values of a symmetric [6, 6] on and above its diagonal, row by row."""
    c = np.asarray(covariance, dtype=np.float64)
    return tuple(float(c[i, j]) for i in range(6) for j in range(i, 6))


def from_upper_triangle(values: tuple[float, ...] | list[float]) -> np.ndarray:
    """The symmetric [6, 6] of :func:`upper_triangle`'s 21 values."""
    if len(values) != 21:
        raise ValueError(f"a 6 x 6 covariance has 21 values on and above its diagonal, "
                         f"got {len(values)}")  # fmt: skip
    out = np.zeros((6, 6))
    k = 0
    for i in range(6):
        for j in range(i, 6):
            out[i, j] = out[j, i] = values[k]
            k += 1
    return out


#: The CSV's covariance columns, in :func:`upper_triangle`'s order: ``cov_x_x``, ``cov_x_y``,
#: ..., ``cov_yaw_yaw``.
COVARIANCE_COLUMNS = tuple(f"cov_{AXES[i]}_{AXES[j]}" for i in range(6) for j in range(i, 6))
