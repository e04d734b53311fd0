"""A drive with position fixes only: its poses are the scans' LiDAR odometry laid onto the
fixes.

A receiver that gives positions (metres of noise, no orientation, about one a second) says
where the vehicle was but not which way the sensor faced, and nothing between two fixes.
The LiDAR says both, relative to where it started: KISS-ICP (:class:`.odometry.LidarOdometry`,
extra ``odometry``) registers each scan onto a local map of the ones before. Its poses drift
slowly (a fraction of a percent of the distance, a fraction of a degree a hundred metres);
the fixes do not drift but are metres off. :func:`fit_to_fixes` lays the odometry onto the
fixes by a rigid motion in the plane (a turn about up and a shift, and a height offset)
fitted anew at each scan to the fixes within about ``window_m`` of drive of it (Gaussian
weights over the distance driven, each fix weighted by its ``1/std²``): the odometry's shape
between the fixes, the fixes' place and heading over the window, and the drift absorbed as the
fit moves along.

:class:`FixOdometryDrive` is such a drive (the ``Drive`` protocol); ``pnvlad data prepare
--odometry kiss-icp --fix-topic TOPIC`` prepares a bag as one and keeps the fixes
beside the run (:func:`.fixes.write_run_fixes`), which is how ``pnvlad map align`` knows the
run has fixes only.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from pnvlad_service.data.drive import snap_m
from pnvlad_service.data.sources.fixes import Fixes, check_jumps, linear_at
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

#: The Gaussian window (std, metres of drive) of the fit at each scan.
FIT_WINDOW_M = 50.0
#: The shortest drive whose odometry can be laid onto fixes (metres): under it the heading is
#: the fixes' noise.
MIN_DRIVE_M = 50.0
#: Metres of each scan KISS-ICP keeps: beyond the vehicle's own body and roof, within the
#: sensor's useful range.
ODOMETRY_RANGE_M = (3.0, 100.0)
#: One ground point in this many is kept for KISS-ICP (the ground plane by G's RANSAC): a
#: flat road seen by a spinning sensor is rings at fixed ranges that move with it, and matched
#: point to point they hold the scan where the last one was (on the synthetic city's flat
#: streets KISS-ICP then finds a tenth of the motion); the few kept hold height and tilt.
GROUND_KEEP = 10


def odometry_points(points: np.ndarray) -> np.ndarray:
    """float64 [M, 3]: what KISS-ICP registers of a scan [N, 3+] (sensor frame): its points
    off the ground plane and one ground point in :data:`GROUND_KEEP`."""
    from pnvlad_service.preprocess.filter_g import GConfig, ground_mask

    pts = np.asarray(points, dtype=np.float64)[:, :3]
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 100:
        return pts
    ground, _ = ground_mask(pts, GConfig(ground_mode="plane"))
    return np.concatenate([pts[~ground], pts[np.flatnonzero(ground)[::GROUND_KEEP]]])


def fix_steps(stamps: np.ndarray, fixes: Fixes, span: int = 5) -> np.ndarray:
    """float64 [T]: metres driven before each scan (stamped ``stamps`` int64 [T] µs; the
    first 0) by the fixes' speed, the median over ``span`` consecutive fixes (a fix's metres
    of error change little from one to the next, so their differences give the speed to a
    few percent), linear in time between fixes."""
    t = fixes.stamps.astype(np.float64) / 1e6
    speed = np.linalg.norm(np.diff(fixes.enu[:, :2], axis=0), axis=1) / np.diff(t)
    half = span // 2
    smooth = np.array(
        [np.median(speed[max(0, k - half) : k + half + 1]) for k in range(len(speed))]
    )
    mid = (t[1:] + t[:-1]) / 2
    s = np.asarray(stamps, np.float64) / 1e6
    return np.r_[0.0, np.interp(s[1:], mid, smooth) * np.diff(s)]


def odometry_poses(
    scans: Any, steps_m: np.ndarray | None = None, *, progress: bool = True
) -> np.ndarray:
    """float64 [T, 4, 4]: KISS-ICP's pose of each of ``scans`` (anything with ``len()`` and
    ``scan(i)``, in time order), sensor to the first scan's frame; ``steps_m`` float [T]:
    metres driven before each scan (:func:`fix_steps`), KISS-ICP's start for it
    (:meth:`.odometry.LidarOdometry.update`)."""
    from pnvlad_service.data.sources.odometry import LidarOdometry
    from pnvlad_service.progress import tqdm

    odo = LidarOdometry(max_range=ODOMETRY_RANGE_M[1], min_range=ODOMETRY_RANGE_M[0])
    name = getattr(scans, "name", "drive")
    poses = np.empty((len(scans), 4, 4))
    for i in tqdm(range(len(scans)), desc=f"odometry {name}", unit="scan", disable=not progress):
        step = None if steps_m is None else float(steps_m[i])
        poses[i] = odo.update(odometry_points(scans.scan(i)), step)
    return poses


def _along(points: np.ndarray) -> np.ndarray:
    """float64 [T]: horizontal distance driven along ``points`` [T, 3]."""
    steps = np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def fit_to_fixes(
    stamps: np.ndarray,
    odometry: np.ndarray,
    fixes: Fixes,
    window_m: float = FIT_WINDOW_M,
    name: str = "drive",
) -> np.ndarray:
    """float64 [T, 4, 4]: the ``odometry`` poses [T, 4, 4] (stamped ``stamps`` int64 [T] µs)
    laid onto ``fixes`` (module doc), translations snapped. ``InputError`` naming ``name``
    when fewer than 3 fixes fall within the scans' time or the drive is shorter than
    :data:`MIN_DRIVE_M`."""
    inside = fixes.within(int(stamps[0]), int(stamps[-1]))
    if len(inside) < 3:
        raise InputError(
            f"{len(inside)} position fixes within the scans' time "
            f"({stamps[0]}..{stamps[-1]} µs): the fixes do not overlap the clouds",
            name,
        )
    pos = odometry[:, :3, 3]
    along = _along(pos)
    if along[-1] < MIN_DRIVE_M:
        raise InputError(
            f"the odometry drove {along[-1]:.0f} m: under {MIN_DRIVE_M:g} m the fixes cannot "
            "say which way it faced",
            name,
        )
    o_ref, f_ref = pos[0].copy(), inside.enu[0].copy()  # about the first: sums stay exact
    pos = pos - o_ref
    at_fix = linear_at(stamps, np.c_[pos, along], inside.stamps)  # odometry at each fix: x, y, z, d
    enu = inside.enu - f_ref
    std = np.where(np.isfinite(inside.std_m), inside.std_m, 1.0)
    w = np.exp(-0.5 * ((at_fix[None, :, 3] - along[:, None]) / window_m) ** 2) / std**2
    w /= w.sum(axis=1, keepdims=True)  # [T, F]
    mo, mf = w @ at_fix[:, :2], w @ enu[:, :2]  # weighted means [T, 2]
    # cross terms sum_j w (o - mo)(f - mf)^T, expanded: sum w o f^T - mo mf^T
    s = np.einsum("tf,fa,fb->tab", w, at_fix[:, :2], enu[:, :2])
    s -= mo[:, :, None] * mf[:, None, :]
    theta = np.arctan2(s[:, 0, 1] - s[:, 1, 0], s[:, 0, 0] + s[:, 1, 1])
    c, si = np.cos(theta), np.sin(theta)
    lay = np.zeros((len(stamps), 4, 4))
    lay[:, 0, 0], lay[:, 0, 1], lay[:, 1, 0], lay[:, 1, 1] = c, -si, si, c
    lay[:, 2, 2] = lay[:, 3, 3] = 1.0
    lay[:, 0, 3] = mf[:, 0] - (c * mo[:, 0] - si * mo[:, 1])
    lay[:, 1, 3] = mf[:, 1] - (si * mo[:, 0] + c * mo[:, 1])
    lay[:, 2, 3] = w @ (enu[:, 2] - at_fix[:, 2])
    lay[:, :3, 3] += f_ref - lay[:, :3, :3] @ o_ref  # back from about the first fix
    out = lay @ odometry
    out[:, :3, 3] = snap_m(out[:, :3, 3])
    return out


class FixOdometryDrive:
    """A drive whose poses are its scans' KISS-ICP odometry laid onto position fixes
    (the module doc): the ``Drive`` protocol over ``scans`` (anything with ``name``,
    ``timestamps`` int64 [T] µs, ``len()`` and ``scan(i)``: a bag's clouds, a folder of
    scans, a simulated drive), plus ``fixes`` (those within the scans' time), ``laid_at_fixes``
    float64 [F, 3] (where the poses put the sensor at each fix's time), ``odometry`` [T, 4, 4]
    (KISS-ICP's own poses) and, where ``scans`` has them, its ``true_poses``.

    ``InputError`` naming ``name`` (default the scans' name) when the fixes do not overlap the
    scans or jump against the odometry (:func:`.fixes.check_jumps`)."""

    def __init__(
        self,
        scans: Any,
        fixes: Fixes,
        *,
        name: str | None = None,
        window_m: float = FIT_WINDOW_M,
        odometry: np.ndarray | None = None,
        progress: bool = True,
    ) -> None:
        self.source = scans
        self.name = name or getattr(scans, "name", "drive")
        self.timestamps = np.asarray(scans.timestamps, dtype=np.int64)
        if not math.isfinite(window_m) or window_m <= 0:
            raise InputError(f"must be a positive number of metres, got {window_m}", "window_m")
        if odometry is None:
            steps = fix_steps(self.timestamps, fixes.checked(self.name))
            odometry = odometry_poses(scans, steps, progress=progress)
        self.odometry = odometry
        self.poses = fit_to_fixes(self.timestamps, self.odometry, fixes, window_m, self.name)
        self.fixes = fixes.within(int(self.timestamps[0]), int(self.timestamps[-1]))
        self.laid_at_fixes = linear_at(self.timestamps, self.poses[:, :3, 3], self.fixes.stamps)
        check_jumps(self.fixes, self.laid_at_fixes, self.name)
        if hasattr(scans, "true_poses"):
            self.true_poses = scans.true_poses
        log.info(
            "%s: %d scans laid onto %d fixes (median distance %.2f m)",
            self.name,
            len(self),
            len(self.fixes),
            float(np.median(np.linalg.norm(self.fixes.enu - self.laid_at_fixes, axis=1))),
        )

    pose_source = "KISS-ICP odometry laid onto position fixes"

    def __getattr__(self, name: str) -> Any:
        """What the scans' source says of itself (a bag's ``stats``, ``no_returns``...)."""
        if name == "source":
            raise AttributeError(name)
        return getattr(self.source, name)

    def __len__(self) -> int:
        return len(self.timestamps)

    def scan(self, i: int) -> np.ndarray:
        return self.source.scan(i)

    def close(self) -> None:
        getattr(self.source, "close", lambda: None)()
