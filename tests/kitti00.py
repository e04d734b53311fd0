"""KITTI odometry sequence 00's recorded poses, for the tests that check real scans against
them (frames 94/95 and 52/4501 of the real scans folder; see its README.md).

Computed here with numpy alone, as the data README states it: the velodyne pose of frame ``i``
is ``P_i = C_i · Tr`` (``C_i``: line ``i`` of ``kitti00_poses.txt``, camera 0's pose; ``Tr``:
sequence 00's velodyne-to-camera calibration), and ``inv(P_i) · P_j`` takes points of scan ``j``
into scan ``i``'s frame. Nothing here calls pnvlad_service, so the tests can hold its pose
conversions and registration to it.

The real scans ``kitti00_000000.bin`` and ``kitti00_000005.bin`` are NOT frames 0 and 5 of
sequence 00 and have no pose here (nor in ``kitti00_poses_0-5.txt``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Sequence 00's ``Tr`` (velodyne -> camera 0), as its calib.txt and the data README give it.
TR = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0.0, 0.0, 0.0, 1.0],
    ]
)

#: The ``Tr:`` line of a KITTI calib.txt holding :data:`TR` (12 numbers, row-major 3x4).
TR_LINE = "Tr: " + " ".join(f"{v:.12e}" for v in TR[:3].ravel())

POSES = "kitti00_poses.txt"


def pose_line(folder: Path, i: int) -> str:
    """Line ``i`` of ``kitti00_poses.txt`` (frame ``i``: 12 numbers, camera 0's 3x4 pose)."""
    lines = (folder / POSES).read_text().splitlines()
    assert len(lines) == 4541, f"{POSES}: {len(lines)} lines, sequence 00 has 4,541 frames"
    return lines[i]


def camera_pose(folder: Path, i: int) -> np.ndarray:
    """``C_i``: float64 [4, 4], camera 0 of frame ``i`` -> camera 0 of frame 0 (KITTI axes)."""
    c = np.eye(4)
    c[:3, :4] = np.array(pose_line(folder, i).split(), dtype=np.float64).reshape(3, 4)
    return c


def velodyne_pose(folder: Path, i: int) -> np.ndarray:
    """``P_i = C_i · Tr``: float64 [4, 4], the pose of scan ``i`` (velodyne frame) in the
    sequence's frame (camera 0 of frame 0)."""
    return camera_pose(folder, i) @ TR


def relative_pose(folder: Path, i: int, j: int) -> np.ndarray:
    """``inv(P_i) · P_j``: float64 [4, 4], points of scan ``j`` -> scan ``i``'s frame (the
    transform that registering scan ``j`` onto scan ``i`` should find)."""
    return np.linalg.inv(velodyne_pose(folder, i)) @ velodyne_pose(folder, j)
