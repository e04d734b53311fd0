"""Drives that test a localiser's honesty: one that leaves the mapped area and comes back, and
one whose recording jumps (a kidnapped robot).

Every run of a ``pnvlad synth`` area drives the same route, so a map of some runs covers the
route of the others. :func:`off_map_drive` rebuilds a run of a preset that drives its route and
then ``out_m`` metres further through the city (streets the route's walk had not driven: off the
map made of the area's runs), turns round and drives back onto the route for ``back_m`` metres.
:class:`Kidnapped` takes any drive and drops the scans of ``gap_s`` seconds from ``at_s`` on:
the robot was carried elsewhere; its odometry (the drive's ``poses``) saw nothing of it, so
after the gap it goes on from where it was before, while the true poses (``true_poses``) jump.
With ``hide_gap`` the clock jumps too: the scans after the gap come right after the one before
it, and only the scans themselves tell that the robot is elsewhere.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.synth.generate import (
    SynthPreset,
    _run_jobs_of_area,
    _world,
)
from pnvlad_service.synth.runs import Route, SimulatedDrive, _resample, make_route

#: Radius of the turn at the far end of an off-map drive, metres.
TURN_RADIUS_M = 4.0
#: Metres over which the turned drive merges back onto the way it came.
MERGE_M = 12.0


def out_and_back(route: Route, end_m: float, back_to_m: float) -> Route:
    """``route`` driven to ``end_m``, turned round (a half circle to the left) and driven back
    along itself to ``back_to_m`` (< ``end_m``): a route that comes back the way it went."""
    if not 0.0 <= back_to_m < end_m - MERGE_M <= route.length:
        raise InputError(
            f"need 0 <= back_to_m < end_m - {MERGE_M:g} <= {route.length:.0f} m, got {back_to_m}, "
            f"{end_m}",
            "route",
        )
    k_end = int(np.searchsorted(route.s, end_m))
    out = route.points[: k_end + 1]
    p_end = out[-1]
    t = out[-1] - out[-4]
    t = t / max(np.linalg.norm(t), 1e-9)
    n = np.array([-t[1], t[0]])  # left
    centre = p_end + TURN_RADIUS_M * n
    a = np.linspace(-np.pi / 2, np.pi / 2, 13)[1:]  # from p_end round to p_end + 2 r n
    rot = np.stack([t, n], 1)  # local (along, left) -> world
    turn = centre + (np.stack([np.cos(a), np.sin(a)], 1) * TURN_RADIUS_M) @ rot.T
    k_merge = int(np.searchsorted(route.s, end_m - MERGE_M))
    k_back = int(np.searchsorted(route.s, back_to_m))
    back = route.points[k_back : k_merge + 1][::-1]
    pts = _resample(np.concatenate([out, turn, back]), 1.0)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    hw = np.interp(s, route.s, route.half_width, right=route.half_width[-1])
    return Route(pts, s, hw)


def off_map_drive(
    spec: SynthPreset, area_index: int, run: int, seed: int, out_m: float, back_m: float
) -> SimulatedDrive:
    """Run ``run`` of area ``area_index`` of ``spec`` (seed ``seed``: the tree's) driving its
    route, ``out_m`` metres beyond its end, and back along it for ``out_m + back_m`` metres (see
    the module doc). Same world, conditions and run seed as the run in the tree (it drives
    either way round as the run does)."""
    if not (out_m > MERGE_M and back_m >= 0):
        raise InputError(f"need out_m > {MERGE_M:g} and back_m >= 0", "out_m")
    area = spec.areas[area_index]
    job = _run_jobs_of_area(Path("."), area_index, area, spec, seed, {})[run]
    world = _world(area, seed, spec.city)
    longer = make_route(world, area.route_m + out_m, seed)
    end = min(area.route_m + out_m, longer.length)
    route = out_and_back(longer, end, max(0.0, area.route_m - back_m))
    return SimulatedDrive(
        world,
        route,
        f"{job['run']}-off-map",
        seed=job["run_seed"],
        start_us=job["start_us"],
        conditions=spec.conditions,
        lidar=spec.run_lidar(area_index, run),
        scan_spacing=spec.scan_spacing,
    )


class Kidnapped:
    """``drive`` (with ``timestamps``, ``poses``, ``scan(i)`` and ``true_poses``) with the
    scans from ``at_s`` to ``at_s + gap_s`` (seconds since its first scan) dropped; its
    ``poses`` (the odometry) go on after the gap from where they were before it; ``true_poses``
    keep the truth; ``hide_gap``: the timestamps after the gap are moved back by it (the scan
    after the gap comes one scan interval after the one before it)."""

    def __init__(self, drive: object, at_s: float, gap_s: float, hide_gap: bool = False) -> None:
        stamps = np.asarray(drive.timestamps, dtype=np.int64)  # type: ignore[attr-defined]
        t = (stamps - stamps[0]) / 1e6
        drop = (t >= at_s) & (t < at_s + gap_s)
        if not drop.any() or drop.all() or not (t >= at_s + gap_s).any():
            raise InputError(
                f"the drive's {t[-1]:.0f} s do not hold a gap at {at_s:g} s of {gap_s:g} s "
                "with scans after it",
                "kidnap",
            )
        self.drive = drive
        self.name = f"{drive.name}-kidnapped"  # type: ignore[attr-defined]
        self.index = np.flatnonzero(~drop)
        before = int(np.flatnonzero(t < at_s)[-1])
        after = int(np.flatnonzero(t >= at_s + gap_s)[0])
        poses = np.asarray(drive.poses, dtype=np.float64).copy()  # type: ignore[attr-defined]
        # The odometry after the gap: the motion since the first scan after it, from the pose
        # of the last scan before it.
        poses[after:] = poses[before] @ np.linalg.inv(poses[after]) @ poses[after:]
        self.poses = poses[self.index]
        self.true_poses = np.asarray(drive.true_poses)[self.index]  # type: ignore[attr-defined]
        stamps = stamps.copy()
        if hide_gap:
            step = int(np.median(np.diff(stamps)))
            stamps[after:] -= stamps[after] - stamps[before] - step
        self.timestamps = stamps[self.index]
        self.gap_index = int(np.searchsorted(self.index, after))  # its first scan after the gap

    def __len__(self) -> int:
        return len(self.index)

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(int(self.index[i]))  # type: ignore[attr-defined]
