"""The ground of a cloud, step 2 of the filter G: the ground plane and the height map under the
points, as plain functions of points and lengths (:func:`~.filter_g.ground_mask` runs them
with :class:`~.filter_g.GConfig`'s settings; docs/PREPROCESS.md has the figures).

- :func:`fit_ground_plane`: a RANSAC plane through the lowest point of each column
  (:func:`lowest_per_cell`), its normal within a tilt of the z axis, either side up;
- :func:`ground_surface`: the ground's height under each point from a grid height map (a low
  percentile per cell, the cells joined smoothly to the plane, a grey-scale closing and opening)
  that follows slopes and kerbs;
- :func:`rotation_to_z`, :func:`by_cell_then_height`: the frame and the one sort both use.
"""

from __future__ import annotations

import logging
import math
from typing import Literal

import numpy as np

from pnvlad_service.preprocess.voxel import column_max, column_mean, column_min

log = logging.getLogger(__name__)

#: Most cells a height map may have; a larger cloud gets larger cells (with a warning).
_MAX_GRID_CELLS = 4_000_000


def _fit_plane(
    points: np.ndarray, fallback: np.ndarray, max_tilt_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane (centroid, unit normal) of float64 [M, 3]; ``fallback`` normal if
    the fit tips over beyond ``max_tilt_deg``."""
    mean = column_mean(points)
    normal = np.linalg.svd(points - mean, full_matrices=False)[2][2]
    if abs(normal[2]) < math.cos(math.radians(max_tilt_deg)):
        normal = fallback
    return mean, normal


def by_cell_then_height(cells: np.ndarray, height: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points ordered by grid cell, then by height within a cell (``cells`` int [N] flat
    cell numbers >= 0, ``height`` finite float [N], N >= 1; ties keep their order), and where
    each cell's run starts in that order: ``(order int64 [N], starts int64 [cells present])``.
    The one sort behind the ground plane's candidates and the height map.

    One stable argsort of ``cell * (height range + 1) + height above the lowest``: half the time
    of ``np.lexsort`` on the two keys (11 against 21 ms for a 124,668-point KITTI scan), and the
    same order while the key's rounding (about 3e-8 m at 4 million cells of a 50 m range) stays
    under the smallest height difference within a cell. Past 2**40 for the largest key (a
    rounding of about 2e-4 m) it sorts the two keys exactly with ``np.lexsort``."""
    h0 = height - height.min()
    scale = float(h0.max()) + 1.0
    if float(cells.max()) * scale > 2.0**40:
        order = np.lexsort((height, cells))
    else:
        order = np.argsort(cells * scale + h0, kind="stable")
    sorted_cells = cells[order]
    return order, np.flatnonzero(np.r_[True, sorted_cells[1:] != sorted_cells[:-1]])


def lowest_per_cell(points: np.ndarray, cell: float, sign: float = 1.0) -> np.ndarray:
    """Indices of the lowest point along ``sign`` * z in each ``cell`` x ``cell`` column of x, y
    (``points`` float64 [N, 3]): the candidates for ground, since every wall, pole and car
    stands on it and only its foot is lowest in its column."""
    lo = column_min(points[:, :2])
    ij = np.floor((points[:, :2] - lo) / cell).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order, starts = by_cell_then_height(key, sign * points[:, 2])
    return order[starts]


def _ransac_plane(
    cand: np.ndarray,
    sign: float,
    *,
    threshold: float,
    max_tilt_deg: float,
    iterations: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, float]:
    """The plane (centroid, unit normal with ``sign`` * z > 0) of most inliers among ``cand``
    (float64 [M, 3], centred) whose normal is within ``max_tilt_deg`` of z, refined by least
    squares, and the share of ``cand`` within ``threshold`` of it."""
    m = cand.shape[0]
    idx = rng.integers(0, m, size=(iterations, 3))
    a, b, c = cand[idx[:, 0]], cand[idx[:, 1]], cand[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals[ok] /= norms[ok, None]
    ok &= np.abs(normals[:, 2]) >= math.cos(math.radians(max_tilt_deg))
    fallback = np.array([0.0, 0.0, 1.0])
    if ok.any():
        normals = normals[ok]
        offsets = -np.einsum("ij,ij->i", normals, a[ok])
        # [m, K] distances to each hypothesis; float32 is plenty to count inliers.
        dist = np.abs(cand.astype(np.float32) @ normals.T.astype(np.float32) + offsets)
        best = int(np.argmax(np.count_nonzero(dist < threshold, axis=0)))
        inliers = cand[np.abs(cand @ normals[best] + offsets[best]) < threshold]
        fallback = normals[best]
    else:  # no tilted-enough hypothesis: the lowest tenth of the candidates
        log.warning("no RANSAC ground plane within %.0f deg of z; using z", max_tilt_deg)
        h = sign * cand[:, 2]
        inliers = cand[h <= np.quantile(h, 0.1)]
    if inliers.shape[0] >= 3:
        # Least squares on the inliers, then again on those within half the threshold of that
        # plane (less pull from the feet of walls and cars).
        mean, normal = _fit_plane(inliers, fallback, max_tilt_deg)
        close = inliers[np.abs((inliers - mean) @ normal) < threshold / 2]
        if close.shape[0] >= 3:
            mean, normal = _fit_plane(close, fallback, max_tilt_deg)
    else:
        mean, normal = cand[np.argmin(sign * cand[:, 2])], fallback
    if sign * normal[2] < 0:
        normal = -normal
    share = float(np.mean(np.abs((cand - mean) @ normal) < threshold))
    return mean, normal, share


def fit_ground_plane(
    points: np.ndarray,
    *,
    threshold: float = 0.5,
    max_tilt_deg: float = 30.0,
    up: Literal["auto", "z", "-z"] = "auto",
    iterations: int = 200,
    rng: np.random.Generator | None = None,
    sample: int = 4000,
    cell: float = 2.0,
) -> tuple[np.ndarray, float]:
    """RANSAC plane through the lowest point of each ``cell`` m column (:func:`lowest_per_cell`),
    with the most of them within ``threshold`` m among planes whose normal is within
    ``max_tilt_deg`` of the z axis, refined by least squares on those.

    Fitting the columns' lowest points rather than all points keeps the plane on the ground
    where walls and their horizontal bands of returns at the sensor's height hold more points
    than a rolling road does (an accumulated 20 m window: a plane at the sensor's height wins a
    RANSAC over every point).

    Args:
        points: float64 [N, 3] metres.
        up: which side is up: ``"auto"`` fits the lowest points along z and along -z and takes
            the side whose plane holds the larger share of them (ground lies under everything;
            the highest points of the columns are roofs, crowns and walls' tops); when the two
            are level (an open, flat cloud) the side holding more of the points farther than
            ``threshold`` from the plane.
        rng: the random generator (hypotheses and the subsample of ``sample`` candidates).
        cell: column size, metres; smaller for a cloud spanning less than 32 columns.

    Returns:
        ``(normal, offset)``: unit float64 [3] pointing up and a float such that
        ``points @ normal + offset`` is the signed height above the plane in metres.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    centre = column_mean(points)
    pts = points - centre
    span = float(np.max(column_max(pts[:, :2]) - column_min(pts[:, :2])))
    if span > 0:
        cell = min(cell, span / 32)
    signs = {"auto": (1.0, -1.0), "z": (1.0,), "-z": (-1.0,)}[up]
    fits = []
    for sign in signs:
        cand = pts[lowest_per_cell(pts, cell, sign)] if span > 0 else pts
        if cand.shape[0] > sample:
            cand = cand[np.sort(rng.choice(cand.shape[0], sample, replace=False))]
        fits.append(
            _ransac_plane(
                cand,
                sign,
                threshold=threshold,
                max_tilt_deg=max_tilt_deg,
                iterations=iterations,
                rng=rng,
            )
        )
    mean, normal, _ = max(fits, key=lambda f: f[2])
    # The columns' lowest points sit a little under the ground's mean (each the lowest of its
    # noise): refit on every point near the plane (a random subsample).
    sub = pts if pts.shape[0] <= sample else pts[rng.choice(pts.shape[0], sample, replace=False)]
    close = sub[np.abs((sub - mean) @ normal) < threshold / 2]
    if close.shape[0] >= 3:
        sign = 1.0 if normal[2] > 0 else -1.0
        mean, normal = _fit_plane(close, normal, max_tilt_deg)
        normal = normal if sign * normal[2] > 0 else -normal
    offset = -float(normal @ mean)
    if up == "auto" and abs(fits[0][2] - fits[1][2]) < 0.05:
        height = sub @ normal + offset
        if np.count_nonzero(height < -threshold) > np.count_nonzero(height > threshold):
            normal, offset = -normal, -offset
    return normal, offset - float(normal @ centre)


def rotation_to_z(normal: np.ndarray) -> np.ndarray:
    """Rotation matrix float64 [3, 3] R with R @ normal = (0, 0, 1)."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(normal, z)
    s, c = float(np.linalg.norm(v)), float(normal @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k * ((1.0 - c) / (s * s))


def ground_surface(
    xy: np.ndarray,
    height: np.ndarray,
    *,
    cell: float = 1.0,
    window: float = 9.0,
    percentile: float = 5.0,
    step: float = 0.3,
    seed_band: float = 0.5,
) -> np.ndarray:
    """Height of the ground under each point, from a grid height map.

    1. Each ``cell`` x ``cell`` m cell gets the ``percentile`` of its points' heights.
    2. Connected ground: a cell at most ``step`` m above the lowest of its 8 neighbours is
       smooth; the 8-connected regions of smooth cells that hold a cell within ``seed_band`` m
       of height 0 (the RANSAC plane) are ground. Slopes and kerbs joined to the road stay in;
       tree crowns, roofs and cars, whose cells rise in one jump or float with no ground around
       them, drop out.
    3. Every other cell, empty or not, takes the value of the nearest ground cell (the surface
       carries on flat past the data), padded past the grid's edge.
    4. A grey-scale closing (fills pits: stray low returns) then an opening (cuts bumps still
       left: cars, walls, trunks), both over a square of ``window`` m. Both keep a plane
       exactly, so a uniform slope survives.

    Args:
        xy: float64 [N, 2] metres in a frame whose z is up.
        height: float64 [N] metres, the points' z in that frame (0 = the RANSAC plane).

    Returns:
        float64 [N]: the ground height below each point, metres.
    """
    from scipy import ndimage

    lo = column_min(xy)
    span = column_max(xy) - lo
    cells_needed = float(np.prod(span / cell + 1))
    if cells_needed > _MAX_GRID_CELLS:
        cell = cell * math.sqrt(cells_needed / _MAX_GRID_CELLS) * 1.01
        log.warning("cloud spans %.0f x %.0f m; ground cell enlarged to %.2f m", *span, cell)
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    shape = (int(ij[:, 0].max()) + 1, int(ij[:, 1].max()) + 1)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    order, starts = by_cell_then_height(flat, height)
    counts = np.diff(np.r_[starts, flat.shape[0]])
    pick = starts + np.floor((counts - 1) * (percentile / 100.0)).astype(np.int64)
    grid = np.full(shape, np.inf)
    grid.flat[flat[order[starts]]] = height[order[pick]]
    valid = np.isfinite(grid)

    lowest_near = ndimage.grey_erosion(grid, size=(3, 3), mode="constant", cval=np.inf)
    smooth = valid.copy()
    smooth[valid] = grid[valid] - lowest_near[valid] <= step
    labels, _ = ndimage.label(smooth, structure=np.ones((3, 3), dtype=bool))
    seeds = np.unique(labels[smooth & (np.abs(grid) <= seed_band)])
    ground = smooth & np.isin(labels, seeds[seeds > 0])
    if not ground.any():
        log.warning("no ground cells joined to the RANSAC plane; using the plane")
        return np.zeros_like(height)
    nearest = ndimage.distance_transform_edt(~ground, return_distances=False, return_indices=True)
    grid = grid[tuple(nearest)]
    size = max(1, round(window / cell))
    size += 1 - size % 2  # odd, centred on the cell
    if size > 1:
        pad = 2 * size
        grid = np.pad(grid, pad, mode="edge")
        grid = ndimage.grey_closing(grid, size=(size, size), mode="nearest")
        grid = ndimage.grey_opening(grid, size=(size, size), mode="nearest")
        grid = np.ascontiguousarray(grid[pad:-pad, pad:-pad])
    return grid.flat[flat]
