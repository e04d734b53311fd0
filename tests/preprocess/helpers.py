"""An estimate of a scan's road surface that does not use the filter G."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def road_surface(points: np.ndarray, cell: float = 2.0) -> Callable[[np.ndarray], np.ndarray]:
    """An estimate of the road surface independent of the filter G (the G tests and
    ``benchmarks/bench_preprocess.py --ground`` measure G against it).

    Per 2 m cell (with 3 or more points) the 5th percentile of z; a least-squares plane through
    those cell values 3-20 m from the sensor, refitted five times without cells more than
    0.3 m off it. Returns f(points) -> surface z under each point: the cell's value where it
    is within 0.75 m of the plane (the cell looks like ground), else the plane.
    """
    keys = np.floor(points[:, :2] / cell).astype(np.int64)
    low: dict[tuple[int, int], float] = {}
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    for k, (i, j) in enumerate(uniq.tolist()):
        zs = points[order[bounds[k] : bounds[k + 1]], 2]
        if len(zs) >= 3:
            low[(i, j)] = float(np.percentile(zs, 5))
    centres = np.array([((i + 0.5) * cell, (j + 0.5) * cell, z) for (i, j), z in low.items()])
    r = np.hypot(centres[:, 0], centres[:, 1])
    near = centres[(r > 3) & (r < 20)]
    a = np.c_[near[:, :2], np.ones(len(near))]
    keep = np.ones(len(near), bool)
    for _ in range(5):
        coef = np.linalg.lstsq(a[keep], near[keep, 2], rcond=None)[0]
        keep = np.abs(a @ coef - near[:, 2]) < 0.3

    def surface(q: np.ndarray) -> np.ndarray:
        plane = q[:, 0] * coef[0] + q[:, 1] * coef[1] + coef[2]
        cells = np.floor(q[:, :2] / cell).astype(np.int64).tolist()
        local = np.array([low.get((i, j), np.nan) for i, j in cells])
        use = np.isfinite(local) & (np.abs(local - plane) < 0.75)
        return np.where(use, local, plane)

    return surface
