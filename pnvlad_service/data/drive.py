"""The face every drive shows: the :class:`Drive` protocol, the check :func:`prepare_drive
<pnvlad_service.data.prepare.prepare_drive>` runs on one, and the pose conventions drives share.

A *drive* is anything with ``name``, ``timestamps``, ``poses``, ``len()`` and ``scan(i)``; the
recorded ones are in :mod:`pnvlad_service.data.sources` (KITTI, CSV, ROS bags), the synthetic
city's is :class:`pnvlad_service.synth.runs.SimulatedDrive`. What consumes a drive (cutting,
accumulating, the true poses) imports this module, never a source.

Conventions (docs/ARCHITECTURE.md): world frame x = easting, y = northing, z = up, UTM metres;
timestamps are integer microseconds. Translations are snapped to a 2**-26 m (15 nm) grid
(:func:`snap_m`) so that adding a UTM origin and subtracting a submap centre are exact in
float64.
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

from pnvlad_service.errors import InputError

#: Grid (metres) that translations are snapped to: 2**-26 m, about 15 nanometres. Any UTM
#: coordinate (< 2**24 m) on this grid has at most 50 significant bits, so sums and differences
#: of such coordinates are exact in float64.
SNAP_M = 2.0**-26


@runtime_checkable
class Drive(Protocol):
    """A recorded (or simulated) drive: LiDAR scans with their poses, in time order.

    - ``name``: a short name for messages (e.g. the sequence folder).
    - ``timestamps``: int64 [T], microseconds, strictly increasing (they name the submap files).
    - ``poses``: float64 [T, 4, 4], sensor-to-world transforms; world x = easting,
      y = northing, z = up, UTM metres.
    - ``len(drive)``: T.
    - ``scan(i)``: the points of scan ``i``, [N, 3] float32 or float64, sensor frame, metres.
    """

    name: str
    timestamps: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int: ...

    def scan(self, i: int) -> np.ndarray: ...


def snap_m(values: np.ndarray | float) -> np.ndarray:
    """Round metres (float64, any shape) to the :data:`SNAP_M` grid (exact for |x| < 2**26 m)."""
    return np.round(np.asarray(values, dtype=np.float64) / SNAP_M) * SNAP_M


def yaw_matrix(yaw_rad: float) -> np.ndarray:
    """float64 [3, 3] rotation about z (up) by ``yaw_rad``, counter-clockwise seen from above."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def place_in_utm(
    local: np.ndarray, origin_ne: tuple[float, float] = (0.0, 0.0), yaw_deg: float = 0.0
) -> np.ndarray:
    """Poses float64 [T, 4, 4] of a local metric frame (z up) placed in UTM: the frame turned by
    ``yaw_deg`` counter-clockwise from east, its translations snapped to :data:`SNAP_M`, then its
    origin put at ``origin_ne`` = (northing, easting), height 0. Snapping before the origin is
    added keeps the result minus the origin independent of the origin's magnitude."""
    place = np.eye(4)
    place[:3, :3] = yaw_matrix(math.radians(yaw_deg))
    world = place @ local
    origin = snap_m(np.array([origin_ne[1], origin_ne[0], 0.0]))
    world[:, :3, 3] = snap_m(world[:, :3, 3]) + origin
    return world


def check_drive(drive: Drive) -> tuple[np.ndarray, np.ndarray]:
    """Validate a drive's arrays: (timestamps int64 [T], poses float64 [T, 4, 4])."""
    name = getattr(drive, "name", "drive")
    stamps = np.asarray(drive.timestamps)
    poses = np.asarray(drive.poses, dtype=np.float64)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise InputError(f"timestamps must be int64 [T], got {stamps.dtype} {stamps.shape}", name)
    stamps = stamps.astype(np.int64)
    t_count = len(drive)
    if len(stamps) != t_count or poses.shape != (t_count, 4, 4):
        raise InputError(
            f"{t_count} scans but {len(stamps)} timestamps and poses of shape {poses.shape}", name
        )
    if t_count == 0:
        raise InputError("the drive has no scans", name)
    if np.any(np.diff(stamps) <= 0):
        i = int(np.nonzero(np.diff(stamps) <= 0)[0][0]) + 1
        raise InputError(f"timestamps must increase strictly (scan {i}: {stamps[i]})", name)
    if not np.all(np.isfinite(poses)):
        raise InputError("a pose holds NaN or infinite values", name)
    return stamps, poses
