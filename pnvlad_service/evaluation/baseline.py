"""A training-free global descriptor, the yardstick a learned encoder must beat.

In the manner of Scan Context (Kim & Kim, IROS 2018): the submap is cut into a polar grid around
its centre, ``RINGS`` rings by ``SECTORS`` sectors, and each bin holds the height of its highest
point (plus one, so an empty bin, 0, differs from a bin at the bottom of the cube). The grid,
flattened and L2-normalised, is the descriptor, compared by Euclidean distance (FAISS
``IndexFlatL2``), exactly as learned descriptors are.

Benchmark submaps are cut in the UTM frame (north up), so every run sees a place in the same
orientation and no search over sector shifts is needed. Input: normalised submaps, float
[B, N, 3] in [-1, 1]; output float32 [B, RINGS * SECTORS], unit rows.
"""

from __future__ import annotations

import numpy as np

NAME = "scan-context"
RINGS = 20
SECTORS = 60
MAX_RADIUS = 1.0
DIM = RINGS * SECTORS


def describe(points: np.ndarray) -> np.ndarray:
    """Descriptors float32 [B, DIM] (unit L2 norm) of submaps ``points`` float [B, N, 3] or
    [N, 3] (normalised benchmark frame). An all-empty grid gives a zero row."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim == 2:
        pts = pts[None]
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise ValueError(f"expected points [B, N, 3], got {pts.shape}")
    b = pts.shape[0]
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    r = np.hypot(x, y)
    ring = np.minimum((r / MAX_RADIUS * RINGS).astype(np.int64), RINGS - 1)
    theta = np.arctan2(y, x)  # (-pi, pi]
    sector = np.minimum(((theta + np.pi) / (2 * np.pi) * SECTORS).astype(np.int64), SECTORS - 1)
    keep = r <= MAX_RADIUS
    cell = (np.arange(b)[:, None] * DIM + ring * SECTORS + sector)[keep]
    grid = np.zeros(b * DIM)
    np.maximum.at(grid, cell, z[keep] + 1.0)
    grid = grid.reshape(b, DIM)
    norm = np.linalg.norm(grid, axis=1, keepdims=True)
    return (grid / np.where(norm > 0, norm, 1.0)).astype(np.float32)
