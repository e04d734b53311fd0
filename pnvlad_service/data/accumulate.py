"""Scans laid into one cloud: how a submap is accumulated, offline from a whole drive or online
from the last stretch of a drive.

``pnvlad data prepare`` and ``pnvlad synth`` cut submaps with :func:`accumulate` (through
:mod:`.prepare`, which reads each scan once through a :class:`ScanCache`); a robot with poses
(a bag's pose topic, /tf, or LiDAR odometry, :mod:`.sources.odometry`) asks with the last
``window_m`` of its drive, gathered scan by scan by a :class:`WindowAccumulator` through the
very same steps: each scan's finite points within range (:func:`sensor_points`), scans spaced
along the trajectory (:func:`spaced_scans`), each cut to a seeded subset (:func:`scan_subset`),
moved into one local frame (:func:`accumulate`). Poses are float64 [4, 4] sensor-to-world,
world x = easting, y = northing, z = up (or any odometry frame: only relative poses matter to
the cloud).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from pnvlad_service.data.cuts import check_box_m
from pnvlad_service.data.drive import Drive, snap_m
from pnvlad_service.errors import InputError


def travelled_distance(poses: np.ndarray) -> np.ndarray:
    """Cumulative horizontal distance along the trajectory: float64 [T] metres, starting at 0.

    ``poses``: float64 [T, 4, 4] sensor-to-world; only x (easting) and y (northing) count.
    """
    xy = np.asarray(poses, dtype=np.float64)[:, :2, 3]
    steps = np.hypot(np.diff(xy[:, 0]), np.diff(xy[:, 1]))
    return np.concatenate([[0.0], np.cumsum(steps)])


def spaced_scans(travelled: np.ndarray, min_spacing_m: float) -> np.ndarray:
    """bool [T]: scans at least ``min_spacing_m`` of travel after the previous one kept.

    Scan 0 is always kept; with ``min_spacing_m`` = 0 every scan is. The choice depends on the
    whole drive, not on a window, so every window uses the same scans (each read once).
    """
    d = np.asarray(travelled, dtype=np.float64)
    keep = np.zeros(len(d), dtype=bool)
    last = -math.inf
    for i, value in enumerate(d.tolist()):
        if value - last >= min_spacing_m:
            keep[i] = True
            last = value
    return keep


def used_scans(travelled: np.ndarray, min_spacing_m: float, scan_step: int = 1) -> np.ndarray:
    """bool [T]: the scans a prepare call accumulates: :func:`spaced_scans`, of which only every
    ``scan_step``-th scan of the drive."""
    use = spaced_scans(travelled, min_spacing_m)
    use[np.arange(len(use)) % scan_step != 0] = False
    return use


def accumulate(
    poses: np.ndarray,
    scans: dict[int, np.ndarray] | Sequence[np.ndarray],
    indices: Sequence[int],
    centre: np.ndarray,
    box_m: float | None = None,
) -> np.ndarray:
    """Scans moved into a local world frame centred on ``centre``: float64 [M, 3] metres.

    ``poses``: float64 [T, 4, 4] sensor-to-world; ``scans[i]``: [N_i, 3] sensor frame;
    ``centre``: float64 [3] world position (UTM). The result has UTM axes (x east, y north,
    z up) and origin ``centre``; translations are snapped and subtracted in float64 before the
    points are added, so large UTM coordinates lose no precision. ``box_m`` keeps only points
    with |x| and |y| <= box_m / 2: a square centred on ``centre``, axis-aligned in the map's
    frame (UTM), not turned to the heading, so that every run through a place keeps the same
    ground whatever its direction, lane or heading noise (docs/PREPARE.md).
    """
    c = snap_m(centre)
    parts = []
    for i in indices:
        pts = scans[i]
        if len(pts) == 0:
            continue
        r = poses[i, :3, :3]
        offset = snap_m(poses[i, :3, 3]) - c
        parts.append(pts @ r.T + offset)
    out = np.concatenate(parts) if parts else np.empty((0, 3))
    if box_m is not None:
        half = box_m / 2.0
        out = out[(np.abs(out[:, 0]) <= half) & (np.abs(out[:, 1]) <= half)]
    return out


def scan_subset(points: np.ndarray, max_points: int | None, seed: Sequence[int]) -> np.ndarray:
    """At most ``max_points`` rows of ``points``, a random subset in file order seeded by
    ``seed`` (prepare seeds it with its seed and the scan index: the same whichever window
    asks); ``points`` itself when it is small enough or ``max_points`` is None."""
    if max_points is None or len(points) <= max_points:
        return points
    rng = np.random.default_rng(list(seed))
    return points[np.sort(rng.choice(len(points), max_points, replace=False))]


def sensor_points(points: np.ndarray, max_range_m: float | None) -> np.ndarray:
    """A scan's x, y, z as float64 [N, 3] (sensor frame, metres, C order): rows with a NaN or
    infinite coordinate dropped, and points farther than ``max_range_m`` from the sensor."""
    pts = np.asarray(points)[:, :3]
    finite = np.isfinite(pts)
    if not finite.all():
        pts = pts[finite.all(axis=1)]
    if max_range_m is not None:
        sq = np.einsum("ij,ij->i", pts, pts, dtype=np.float64)
        pts = pts[sq <= max_range_m**2]
    return np.ascontiguousarray(pts, dtype=np.float64)


class ScanCache:
    """Scans of the sliding window, in the sensor frame, read once each.

    Holds float64 [N, 3] arrays keyed by scan index, whole (keyframes and raw scans take them
    so); :meth:`get` gives the seeded ``max_points_per_scan`` subset that windows accumulate.
    :meth:`evict_before` drops the scans that the windows have passed, so memory is bounded by
    one window, not the drive.
    """

    def __init__(
        self,
        drive: Drive,
        *,
        seed: int,
        max_points_per_scan: int | None,
        max_range_m: float | None,
    ) -> None:
        self.drive = drive
        self.seed = seed
        self.max_points = max_points_per_scan
        self.max_range = max_range_m
        self.scans: dict[int, np.ndarray] = {}
        self.reads = 0

    def full(self, i: int) -> np.ndarray:
        """Scan ``i`` whole (finite points within ``max_range_m``)."""
        if i not in self.scans:
            self.scans[i] = self._load(i)
        return self.scans[i]

    def get(self, i: int) -> np.ndarray:
        """Scan ``i`` as windows accumulate it: at most ``max_points_per_scan`` points, a
        subset seeded by the scan index (the same whichever window asks)."""
        return scan_subset(self.full(i), self.max_points, (self.seed, i))

    def _load(self, i: int) -> np.ndarray:
        name = getattr(self.drive, "name", "drive")
        pts = np.asarray(self.drive.scan(i))
        self.reads += 1
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise InputError(f"scan {i}: expected points [N, 3], got shape {pts.shape}", name)
        return sensor_points(pts, self.max_range)

    def evict_before(self, first: int) -> None:
        for i in [i for i in self.scans if i < first]:
            del self.scans[i]


@dataclass
class _Held:
    """One scan a :class:`WindowAccumulator` holds: travelled distance, pose, points, and
    whether it was kept for its spacing (``spaced``) or only as the newest scan."""

    distance: float
    pose: np.ndarray
    points: np.ndarray
    spaced: bool = True


@dataclass
class WindowAccumulator:
    """The last ``window_m`` metres of a drive, scan by scan, as one cloud.

    :meth:`add` each scan (sensor frame, metres) with its pose; :meth:`cloud` gives the scans of
    the last ``window_m`` of travel laid together as ``pnvlad data prepare`` lays a submap's
    (:func:`accumulate`), about the newest scan: in the world's axes (``frame="enu"``: with
    poses in UTM, the axes of the map's submaps) or in the newest scan's own axes
    (``frame="sensor"``: for odometry, whose frame is nobody's map). A scan less than
    ``min_spacing_m`` from the last one kept for its spacing is held only as the newest, until
    the next scan replaces it (as :func:`spaced_scans` keeps scans offline: a robot creeping or
    standing still holds its spaced scans and its newest); each keeps at most
    ``max_points_per_scan`` points within ``max_range_m`` (prepare's options, default none);
    ``box_m``: the cloud cut to the square of that side about the newest scan, in the world's
    axes as the map's submaps were cut (:func:`accumulate`; default none).
    """

    window_m: float = 20.0
    min_spacing_m: float = 0.05
    max_points_per_scan: int | None = None
    max_range_m: float | None = None
    frame: Literal["enu", "sensor"] = "sensor"
    seed: int = 0
    box_m: float | None = None
    _held: deque[_Held] = field(default_factory=deque, init=False, repr=False)
    _count: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_m) and self.window_m > 0):
            raise InputError(
                f"must be a positive number of metres, got {self.window_m}", "window_m"
            )
        if not (math.isfinite(self.min_spacing_m) and self.min_spacing_m >= 0):
            raise InputError(f"must be >= 0 metres, got {self.min_spacing_m}", "min_spacing_m")
        if self.max_points_per_scan is not None and self.max_points_per_scan < 1:
            raise InputError(f"must be >= 1, got {self.max_points_per_scan}", "max_points_per_scan")
        if self.max_range_m is not None and not self.max_range_m > 0:
            raise InputError(f"must be > 0 metres, got {self.max_range_m}", "max_range_m")
        if self.frame not in ("enu", "sensor"):
            raise InputError(f"must be enu or sensor, got {self.frame!r}", "frame")
        self.box_m = check_box_m(self.box_m)

    @classmethod
    def for_map(
        cls,
        map_record: Any,
        window_m: float = 20.0,
        frame: Literal["enu", "sensor"] = "sensor",
        seed: int = 0,
    ) -> WindowAccumulator:
        """An accumulator that lays scans as the map's windows were laid: ``map_record`` a
        bundle manifest's ``map`` entry (its JSON, as ``GET /info`` gives it under
        ``manifest``, or an ``index.manifest.MapRecord``) whose ``accumulation`` holds the map's
        ``max_points_per_scan``, ``max_range_m``, ``min_scan_spacing_m`` and ``box_m``; without
        one the scans are kept whole and the cloud uncut. Keeping the map's points a scan
        matters: windows of whole scans found their place at 51.7 % recall@1 where the map's
        own submaps found it at 93 % (docs/SCANS.md)."""
        acc = getattr(map_record, "accumulation", None)
        if acc is None and isinstance(map_record, dict):
            acc = map_record.get("accumulation")
        return cls.laid_as(acc, window_m, frame, seed)

    @classmethod
    def laid_as(
        cls,
        accumulation: Any,
        window_m: float = 20.0,
        frame: Literal["enu", "sensor"] = "sensor",
        seed: int = 0,
    ) -> WindowAccumulator:
        """An accumulator that lays scans by ``accumulation`` (a map's, or a prepare record's:
        ``data.run_folder.recorded_accumulation``): its ``max_points_per_scan``,
        ``max_range_m``, ``min_scan_spacing_m`` and ``box_m``; ``None`` keeps the scans whole
        and the cloud uncut."""
        acc = dict(accumulation or {})
        return cls(
            window_m=window_m,
            min_spacing_m=float(acc.get("min_scan_spacing_m", 0.05)),
            max_points_per_scan=acc.get("max_points_per_scan"),
            max_range_m=acc.get("max_range_m"),
            frame=frame,
            seed=seed,
            box_m=acc.get("box_m"),
        )

    def add(self, points: np.ndarray, pose: np.ndarray) -> None:
        """Take one scan float [N, 3+] (sensor frame, metres) at ``pose`` float64 [4, 4]."""
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.isfinite(pose).all():
            raise InputError(f"a pose must be a finite [4, 4] matrix, got {pose.shape}", "pose")
        pts = np.asarray(points)
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise InputError(f"expected points [N, 3+], got {pts.shape}", "points")
        pts = sensor_points(pts, self.max_range_m)
        pts = scan_subset(pts, self.max_points_per_scan, (self.seed, self._count))
        self._count += 1
        distance, spaced = 0.0, True
        if self._held and not self._held[-1].spaced:
            self._held.pop()  # the newest-only scan gives way to the next
        if self._held:
            last = self._held[-1]  # the last scan kept for its spacing
            step = float(np.hypot(*(pose[:2, 3] - last.pose[:2, 3])))
            distance = last.distance + step
            spaced = step >= self.min_spacing_m
        self._held.append(_Held(distance, pose, pts, spaced))
        while self._held[-1].distance - self._held[0].distance > self.window_m:
            self._held.popleft()

    def clear(self) -> None:
        """Forget every scan (after a gap in the poses, say)."""
        self._held.clear()

    @property
    def span_m(self) -> float:
        """Metres of travel between the oldest and the newest scan held."""
        return self._held[-1].distance - self._held[0].distance if self._held else 0.0

    @property
    def scans(self) -> int:
        return len(self._held)

    @property
    def newest_pose(self) -> np.ndarray:
        if not self._held:
            raise InputError("no scan added yet", "window")
        return self._held[-1].pose

    def cloud(self) -> np.ndarray:
        """float64 [M, 3]: the held scans laid into the newest scan's frame (see the class)."""
        if not self._held:
            raise InputError("no scan added yet", "window")
        poses = np.stack([h.pose for h in self._held])
        newest = poses[-1]
        local = accumulate(
            poses, [h.points for h in self._held], range(len(self._held)), newest[:3, 3], self.box_m
        )
        if self.frame == "sensor":
            local = local @ newest[:3, :3]  # rows: R^T p, the newest scan's axes
        return local
