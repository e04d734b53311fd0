"""Street geometry the city and its detail share: a road's centreline by travelled distance
(:class:`Street`), the normal towards one side of it, and points covering a rectangle (for the
occupancy checks)."""

from __future__ import annotations

import numpy as np

from pnvlad_service.synth.world import Road


def box_samples(center: np.ndarray, half: np.ndarray, yaw: float, step: float = 0.8) -> np.ndarray:
    """Points covering an oriented rectangle (including its border), float64 [M,2]."""
    u = np.arange(-half[0], half[0] + 1e-9, step)
    v = np.arange(-half[1], half[1] + 1e-9, step)
    u = np.append(u, half[0])
    v = np.append(v, half[1])
    uu, vv = np.meshgrid(u, v)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([center[0] + c * uu - s * vv, center[1] + s * uu + c * vv], -1).reshape(-1, 2)


class Street:
    """One road's centreline by travelled distance: ``at(s)`` gives the point and unit
    tangent ``s`` metres along it (clamped to its segments)."""

    def __init__(self, road: Road) -> None:
        self.road = road
        self.pts = road.points
        self.seg = np.diff(self.pts, axis=0)
        self.seglen = np.linalg.norm(self.seg, axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(self.seglen)])
        self.total = self.cum[-1]
        self.half_width = road.half_width

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        k = int(np.clip(np.searchsorted(self.cum, s) - 1, 0, len(self.seg) - 1))
        t = self.seg[k] / self.seglen[k]
        return self.pts[k] + t * (s - self.cum[k]), t


def normal(t: np.ndarray, side: float) -> np.ndarray:
    """Unit normal of tangent ``t`` towards ``side`` (+1: right of travel, -1: left)."""
    return np.array([t[1], -t[0]]) * side
