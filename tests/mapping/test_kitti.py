"""Real scans: KITTI 00's revisit (frames 52 and 4501, two sessions of one street) found and
accepted as a closure, its relative pose within 0.3 m and 0.5 degrees of KITTI's; frames 94 and
95 as an odometry step. Each scan is made a node as ``pnvlad data prepare`` makes a keyframe
(laid by its pose into UTM axes, through the keyframes' G); session B's recorded pose is put
off by a GNSS-like error, so the closure is measured, not read back from the poses."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tests.kitti00 import velodyne_pose


def _yaw(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


def kitti_run(folder: Path, name: str, frames: list[int], error: np.ndarray | None = None):
    """A run of KITTI 00 ``frames``: each scan laid (rotated into world axes, z up: the
    velodyne frame of frame 0) by its pose, or by its pose put off by ``error`` (world ->
    world), through the keyframes' G; the laid frames' true poses beside."""
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.mapping.nodes import RunNodes
    from pnvlad_service.preprocess.filter_g import apply_g, scan_config

    world = np.linalg.inv(velodyne_pose(folder, 0))
    laid, truth, clouds = [], [], []
    for i in frames:
        true = world @ velodyne_pose(folder, i)
        recorded = true if error is None else error @ true
        scan = read_points(folder / f"kitti00_{i:06d}.bin", "kitti")
        local = scan @ recorded[:3, :3].T
        g = apply_g(local, scan_config(), seed=i)
        clouds.append(g.centre + g.scale * g.points)
        pose = np.eye(4)
        pose[:3, 3] = recorded[:3, 3]
        laid.append(pose)
        frame_truth = np.eye(4)  # the laid frame's true pose: points laid by R_rec sit at true
        frame_truth[:3, :3] = true[:3, :3] @ recorded[:3, :3].T
        frame_truth[:3, 3] = true[:3, 3]
        truth.append(frame_truth)
    stamps = np.array(frames, dtype=np.int64) * 100_000
    return RunNodes(name, stamps, np.stack(laid), np.stack(truth), clouds=clouds)


def _off(measured: np.ndarray, true: np.ndarray) -> tuple[float, float]:
    d = np.linalg.inv(true) @ measured
    angle = math.degrees(math.acos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(d[:3, 3])), angle


def test_the_revisit_is_found_and_accepted_as_a_closure(real_scans: Path) -> None:
    from pnvlad_service.mapping.candidates import (
        CandidateConfig,
        merged,
        nearby_candidates,
        query_nodes,
    )
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, closure_edges
    from pnvlad_service.mapping.nodes import MapNodes

    error = _yaw(1.2)
    error[:3, 3] = [1.6, -1.1, 0.0]  # session B's fixes 1.9 m and 1.2 degrees off
    nodes = MapNodes([kitti_run(real_scans, "a", [52]), kitti_run(real_scans, "b", [4501], error)])
    config = CandidateConfig(every=1)
    groups = merged(nearby_candidates(nodes, query_nodes(nodes, 1), config), per_group=4)
    assert (1, [0]) in groups  # found: 4501's candidates hold 52
    edges = EdgeConfig()
    found = [e for e in closure_edges(nodes, Clouds(nodes, edges), groups, edges) if e.source == 1]
    assert len(found) == 1 and found[0].accepted, found
    truth = nodes.truth
    expected = np.linalg.inv(truth[0]) @ truth[1]  # KITTI's relative pose of the laid frames
    metres, degrees = _off(found[0].transform, expected)
    assert metres <= 0.3 and degrees <= 0.5, (metres, degrees)


def test_consecutive_frames_make_an_odometry_step(real_scans: Path) -> None:
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, odometry_edges
    from pnvlad_service.mapping.nodes import MapNodes

    nodes = MapNodes([kitti_run(real_scans, "a", [94, 95])])
    edges = EdgeConfig()
    (step,) = odometry_edges(nodes, Clouds.for_odometry(nodes, edges), edges)
    assert step.accepted, step.reason
    truth = nodes.truth
    metres, degrees = _off(step.transform, np.linalg.inv(truth[0]) @ truth[1])
    assert metres <= 0.1 and degrees <= 0.2, (metres, degrees)  # G took the ground: z is loose
    assert step.covariance is not None and np.all(np.linalg.eigvalsh(step.covariance) > 0)
