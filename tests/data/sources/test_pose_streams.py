"""data.sources.pose_streams: interpolation against a hand-worked case."""

from __future__ import annotations

import math

import numpy as np

from pnvlad_service.data.drive import yaw_matrix
from pnvlad_service.data.sources.pose_streams import (
    POSE_AFTER,
    POSE_BEFORE,
    POSE_GAP,
    POSE_OK,
    interpolate_poses,
)


def yaw_pose(yaw_deg: float, xyz: tuple[float, float, float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = yaw_matrix(math.radians(yaw_deg))
    m[:3, 3] = xyz
    return m


def test_interpolation_against_a_hand_worked_case() -> None:
    # t = 0 s: at the origin facing east; t = 1 s: at (10, 2, 0.4) facing north.
    q = np.array([[0.0, 0.0, 0.0, 1.0], [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]])
    p = np.array([[0.0, 0.0, 0.0], [10.0, 2.0, 0.4]])
    t = np.array([0, 1_000_000_000], dtype=np.int64)
    query = np.array([250_000_000, 0, 1_000_000_000, -1, 1_000_000_001], dtype=np.int64)
    poses, status = interpolate_poses(t, p, q, query)
    assert status.tolist() == [POSE_OK, POSE_OK, POSE_OK, POSE_BEFORE, POSE_AFTER]
    # A quarter of the way: a quarter of the translation, a quarter of the 90-degree turn.
    np.testing.assert_allclose(poses[0], yaw_pose(22.5, (2.5, 0.5, 0.1)), atol=1e-12)
    np.testing.assert_array_equal(poses[1], np.eye(4))  # at a sample: that sample, exactly
    np.testing.assert_allclose(poses[2], yaw_pose(90.0, (10.0, 2.0, 0.4)), atol=1e-15)
    np.testing.assert_array_equal(poses[3:], np.stack([np.eye(4)] * 2))
    # Slerp, not a linear blend of matrices: the rotation stays a rotation at every fraction.
    fine = np.linspace(0, 1_000_000_000, 11).astype(np.int64)
    poses, _ = interpolate_poses(t, p, q, fine)
    yaws = np.degrees(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    np.testing.assert_allclose(yaws, np.linspace(0.0, 90.0, 11), atol=1e-9)
    # A gap longer than allowed.
    _, status = interpolate_poses(t, p, q, query, max_gap_ns=500_000_000)
    assert status.tolist() == [POSE_GAP, POSE_OK, POSE_OK, POSE_BEFORE, POSE_AFTER]
