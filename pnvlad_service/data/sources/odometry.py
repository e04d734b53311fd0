"""LiDAR odometry: the poses of a drive estimated from its scans alone (KISS-ICP).

A robot without a pose stream can still ask with more than its newest scan: KISS-ICP (Vizzo
et al., RA-L 2023; PyPI ``kiss-icp``, extra ``odometry``) registers each scan to a local map of
the ones before, and :class:`~..accumulate.WindowAccumulator` lays the last stretch together
with those poses. The poses are in the odometry's own frame (the first scan's), so accumulated
clouds are asked about in the newest scan's axes; their drift over a window is what
``benchmarks/odometry_drift.py`` measures.
"""

from __future__ import annotations

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.extras import require


class LidarOdometry:
    """Scan-to-map odometry: :meth:`update` takes each scan in time order and returns its pose
    float64 [4, 4] (sensor to the odometry frame, the first scan's). ``max_range``: metres kept
    of each scan; ``voxel_size``: the local map's voxel (default ``max_range`` / 100, KISS-ICP's
    own default); ``deskew`` off: scans come without per-point times."""

    def __init__(
        self, max_range: float = 100.0, min_range: float = 0.0, voxel_size: float | None = None
    ) -> None:
        require("kiss_icp", "kiss-icp", "odometry", "LiDAR odometry (accumulated queries)")
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP

        if not max_range > min_range >= 0:
            raise InputError(
                f"need 0 <= min_range < max_range, got {min_range}, {max_range}", "range"
            )
        config = KISSConfig()
        config.data.max_range = float(max_range)
        config.data.min_range = float(min_range)
        config.data.deskew = False
        config.mapping.voxel_size = float(voxel_size or max_range / 100.0)
        self._icp = KissICP(config)
        self.frames = 0

    def update(self, points: np.ndarray, step_m: float | None = None) -> np.ndarray:
        """The pose of one scan float [N, 3+] (sensor frame, metres), given the ones before.

        ``step_m``: how far the sensor moved since the last scan, from elsewhere (the speed
        of position fixes): KISS-ICP's start for this scan moves that far, along its last
        step's direction (forward, x, when that step was too short to have one), instead of
        repeating its last step. A street whose walls run along it leaves the motion along
        it unseen by the scans, where KISS-ICP alone keeps whatever it started from."""
        pts = np.asarray(points)[:, :3]
        pts = np.ascontiguousarray(pts[np.isfinite(pts).all(axis=1)], dtype=np.float64)
        if len(pts) < 100:
            raise InputError(f"a scan of {len(pts)} points is too few for odometry", "points")
        if step_m is not None and self.frames > 0:
            delta = np.array(self._icp.last_delta, dtype=np.float64)
            move = delta[:3, 3]
            norm = float(np.linalg.norm(move))
            way = move / norm if norm > 0.2 * step_m and norm > 1e-6 else np.array([1.0, 0, 0])
            delta[:3, 3] = way * step_m
            self._icp.last_delta = delta
        self._icp.register_frame(pts, np.zeros(0))
        self.frames += 1
        return np.array(self._icp.last_pose, dtype=np.float64)
