"""A stand-in drive and service for the drive localiser's tests (test_tracking.py,
test_follow.py, test_follow_report.py): a street with a turn, the robot's odometry in a frame of
its own, a service whose typed replies are set scan by scan, and the rows of the drive
followed."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.runner import run_drive
from pnvlad_service.localization.drive.service import Place, Reply
from pnvlad_service.localization.drive.tracking import DriveScan
from pnvlad_service.localization.verify.prior import MapPositions, Prior

ORIGIN = np.array([620000.0, 5735000.0, 40.0])
STEP_M = 2.5  # metres between scans
DT_US = 250_000  # 0.25 s between scans (10 m/s)


def pose(x: float, y: float, yaw_deg: float, z: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = [x, y, z]
    return out


def truth(i: int) -> np.ndarray:
    """The drive: east along a street, then a 90-degree left turn over 10 scans, then north."""
    if i <= 20:
        return pose(ORIGIN[0] + STEP_M * i, ORIGIN[1], 0.0, ORIGIN[2])
    k = min(i - 20, 10)
    x = ORIGIN[0] + STEP_M * 20 + 5.0 * math.sin(math.radians(9 * k))
    y = ORIGIN[1] + 5.0 * (1 - math.cos(math.radians(9 * k))) + STEP_M * max(0, i - 30)
    return pose(x, y, 9.0 * k, ORIGIN[2])


def odometry(i: int) -> np.ndarray:
    """The robot's odometry: the truth in a frame of its own (turned and shifted)."""
    return pose(3.0, -7.0, 30.0) @ np.linalg.inv(truth(0)) @ truth(i)


def cloud(i: int) -> np.ndarray:
    """A stand-in scan that names its index (the service reads it back)."""
    return np.full((5, 3), float(i))


def answer(p: np.ndarray | None, mode: str, reason: str | None = None, **prior: Any) -> Reply:
    top = Place(f"city/run/{mode}", 0, "run", "keyframe", 0.0, 0.0, None)
    return Reply(mode=mode, verified=p is not None, pose=p, top=top,
                 confidence=0.5 if p is not None else 0.0, reason=reason,
                 timings_ms={"total": 1.0}, **prior)  # fmt: skip


class Service:
    """Search answers: the truth on ``right`` scans, a place 300 m away (and a different one
    each time) on ``wrong`` scans, nothing verified else. Prior answers: the truth when the
    prior is within ``reach`` metres of it and the scan is not ``off_map``; else not verified.
    A look-alike place (``alias``, a rigid transform [4, 4] of the world): search answers there
    (the truth moved by it, so they agree with the odometry) on ``alias_search`` scans, and
    priors within ``reach`` of it verified there on ``alias_holds`` scans. Records every call."""

    def __init__(
        self,
        right: set[int] = frozenset(),
        wrong: set[int] = frozenset(),
        off_map: set[int] = frozenset(),
        reach: float = 4.0,
        refuse: set[int] = frozenset(),
        scan_truth: Any = truth,
        alias: np.ndarray | None = None,
        alias_search: set[int] = frozenset(),
        alias_holds: set[int] = frozenset(),
    ) -> None:
        self.right, self.wrong, self.off_map = set(right), set(wrong), set(off_map)
        self.reach, self.refuse, self.truth = reach, set(refuse), scan_truth
        self.alias, self.alias_search, self.alias_holds = alias, set(alias_search), set(alias_holds)
        self.calls: list[tuple[int, Prior | None]] = []

    def __call__(self, points: np.ndarray, prior: Prior | None = None, kind: str = "scan") -> Reply:
        i = int(points[0, 0])
        self.calls.append((i, prior))
        if i in self.refuse:
            raise InputError("filter G: too few points", "points")
        true = self.truth(i)
        there = None if self.alias is None else self.alias @ true
        if prior is None:
            if there is not None and i in self.alias_search:
                return answer(there, "search")
            if i in self.right:
                return answer(true, "search")
            if i in self.wrong:
                return answer(pose(ORIGIN[0] + 300.0 + 37.0 * i, ORIGIN[1] - 90.0, 120.0), "search")
            return answer(None, "search", "confidence 0.02 < 0.09")
        near_there = there is not None and (
            math.hypot(prior.easting - there[0, 3], prior.northing - there[1, 3]) <= self.reach
        )
        if near_there and i in self.alias_holds:
            return answer(there, "prior", fitness=0.6, sigma_m=0.1)
        off = math.hypot(prior.easting - true[0, 3], prior.northing - true[1, 3])
        if i in self.off_map:
            return answer(None, "prior", "no map within 20 m of the prior", fitness=0.0)
        if off > self.reach:
            return answer(None, "prior", "fitness 0.12 < 0.5", fitness=0.12)
        return answer(true, "prior", fitness=0.8, sigma_m=0.1)


def scans(n: int, start: int = 0, odo: bool = True) -> list[DriveScan]:
    return [
        DriveScan(i, 1_000_000_000 + DT_US * i, cloud(i), odometry(i) if odo else None)
        for i in range(start, start + n)
    ]


N = 44


class StandInDrive:
    """``N`` scans: ``poses`` the odometry (in its own frame), the points name the scan."""

    name = "stand-in"

    def __init__(self, n: int = N) -> None:
        self.timestamps = np.array([1_000_000_000 + DT_US * i for i in range(n)], dtype=np.int64)
        self.poses = np.stack([odometry(i) for i in range(n)])

    def scan(self, i: int) -> np.ndarray:
        return cloud(i)


def true_poses(n: int = N) -> np.ndarray:
    return np.stack([truth(i) for i in range(n)])


def map_without(hole: range, n: int = N) -> MapPositions:
    """A map of an entry at every scan's true place but those of ``hole``, and a far one."""
    keep = [i for i in range(n) if i not in hole]
    ne = np.array([[truth(i)[1, 3], truth(i)[0, 3]] for i in keep] + [[0.0, 0.0]])
    return MapPositions(ne[:, 0], ne[:, 1], np.array(["city/a"] * len(ne)))


def followed(**kw) -> tuple[list, Service]:
    svc = Service(right={2, 3, 30, 31}, off_map=set(range(18, 27)))
    rows = run_drive(StandInDrive(), svc, "tracked", truth=true_poses(), progress=False,
                     positions=map_without(range(18, 27)), **kw)  # fmt: skip
    return rows, svc
