"""Metric submap pairs with a known relative transform, made by the synthetic city: two runs
that pass the same place, each accumulated from the *true* poses around its own position and
run through the filter G without normalisation (metres, a local frame like the database's).

Used by tests/localization/test_registration.py and benchmarks/registration.py; the truth
comes from the simulator's true poses, independently of any registration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pnvlad_service.data.accumulate import accumulate
from pnvlad_service.preprocess.filter_g import GConfig, apply_g
from pnvlad_service.synth.generate import get_preset, simulated_drive
from pnvlad_service.synth.runs import SimulatedDrive

WINDOW_M = 20.0  # road accumulated per submap, as data/prepare.py's default
BOX_M = 50.0  # square crop about the submap's centre


@dataclass(frozen=True)
class Pair:
    """``source`` [N, 3] and ``target`` [M, 3] metres; ``truth`` float64 4x4 source -> target."""

    source: np.ndarray
    target: np.ndarray
    truth: np.ndarray
    name: str


def true_poses(drive: SimulatedDrive) -> np.ndarray:
    """float64 [T, 4, 4] sensor -> local world, without the run's GNSS error."""
    n = len(drive)
    c, s = np.cos(drive.true_yaw), np.sin(drive.true_yaw)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, :2, 3] = drive.true_xy
    poses[:, 2, 3] = drive.true_z
    return poses


def submap(drive: SimulatedDrive, i: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(points [4096, 3] metres about the true position of scan ``i``, UTM-aligned axes; that
    centre [3] in the local world frame)."""
    poses = true_poses(drive)
    steps = np.linalg.norm(np.diff(drive.true_xy, axis=0), axis=1)
    travelled = np.concatenate([[0.0], np.cumsum(steps)])
    near = np.flatnonzero(np.abs(travelled - travelled[i]) <= WINDOW_M / 2)
    scans = {int(j): drive.scan(int(j)).astype(np.float64) for j in near}
    centre = poses[i, :3, 3].copy()
    pts = accumulate(poses, scans, near, centre, box_m=BOX_M)
    return apply_g(pts, GConfig(normalize=False), seed=seed).points, centre


def yaw_matrix(yaw: float, t: np.ndarray | None = None) -> np.ndarray:
    """float64 4x4: rotation ``yaw`` radians about z, then translation ``t`` [3]."""
    m = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    if t is not None:
        m[:3, 3] = t
    return m


def drives(seed: int = 7, runs: int = 3) -> list[SimulatedDrive]:
    spec = get_preset("tiny")
    return [simulated_drive(spec, 0, r, seed) for r in range(runs)]


def nearest_pass(a: SimulatedDrive, b: SimulatedDrive, i: int, offset_m: float) -> int:
    """The scan of run ``b`` whose true position is nearest to ``offset_m`` metres from run
    ``a``'s scan ``i`` (b drives the same road, so the offset is along it)."""
    dist = np.linalg.norm(b.true_xy - a.true_xy[i], axis=1)
    near = np.flatnonzero(dist <= abs(offset_m) + 6.0)
    return int(near[np.argmin(np.abs(dist[near] - abs(offset_m)))])


def submap_pair(
    a: SimulatedDrive, b: SimulatedDrive, i: int, offset_m: float, query_yaw: float
) -> Pair:
    """Target: run ``a``'s submap at scan ``i``. Source: run ``b``'s submap about
    ``offset_m`` metres along the road from it, seen in a frame turned by ``query_yaw``
    (radians) - what a query in any heading looks like. ``truth`` maps source points onto
    the target's."""
    j = nearest_pass(a, b, i, offset_m)
    target, c_t = submap(a, i)
    source_world, c_s = submap(b, j)
    turn = yaw_matrix(query_yaw)
    source = source_world @ turn[:3, :3]  # the query's frame: world axes turned by query_yaw
    truth = turn.copy()
    truth[:3, 3] = c_s - c_t
    name = f"{a.name}[{i}] <- {b.name}[{j}] yaw {np.degrees(query_yaw):.0f}"
    return Pair(source, target, truth, name)


def scan_pair(a: SimulatedDrive, b: SimulatedDrive, i: int, offset_m: float) -> Pair:
    """Target: run ``a``'s submap at scan ``i``; source: one raw scan of run ``b`` near it,
    through G, in its sensor frame (the heading of that run)."""
    j = nearest_pass(a, b, i, offset_m)
    target, c_t = submap(a, i)
    source = apply_g(b.scan(j).astype(np.float64), GConfig(normalize=False)).points
    pose = true_poses(b)[j]
    truth = pose.copy()
    truth[:3, 3] = pose[:3, 3] - c_t
    return Pair(source, target, truth, f"{a.name}[{i}] <- scan {b.name}[{j}]")
