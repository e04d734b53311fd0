"""The filter G: one raw point cloud (metres) to one benchmark submap (4096 points in [-1, 1]).

The steps, in order, each a public function of this module or of :mod:`~.voxel` (see
docs/PREPROCESS.md for figures on real scans):

1. :func:`crop_mask` / :func:`crop`: optional range (3-D distance from the origin, i.e. the
   sensor) and axis-aligned box.
2. :func:`ground_mask` / :func:`remove_ground`: a RANSAC plane through the lowest point of
   each column (:func:`fit_ground_plane`, :func:`lowest_per_cell`; normal within
   ``max_ground_tilt_deg`` of the z axis) gives the up side and a frame; in
   ``"local"`` mode a height map (:func:`ground_surface`: a low percentile per ``ground_cell``
   cell, the cells joined smoothly to the plane, then a grey-scale closing and opening over
   ``ground_window`` metres) follows slopes and kerbs, and every point less than
   ``ground_threshold`` above that surface (or below it) is ground. ``"plane"`` mode is the
   paper's: points within ``ground_threshold`` of the single plane.
3. :mod:`pnvlad_service.data.voxel`: ``voxel_average`` with the leaf size found by
   ``find_leaf_size`` (a bracketed secant/bisection search until the voxel count is closest to
   the target), then ``resample_to`` duplicates or drops seeded random points to hit the
   target exactly (``adaptive_voxel_downsample`` does both).
4. :func:`normalize`: centre on the centroid, scale to a mean distance of 0.5 from it, drop
   points outside [-1, 1]^3, refill to the target; optional negation afterwards.

Everything is vectorised numpy and deterministic: the same input and seed give the same bytes.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pnvlad_service.data.voxel import (
    adaptive_voxel_downsample,
    column_max,
    column_min,
    resample_to,
    voxel_average,
)
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float, float, float]

_MAX_GRID_CELLS = 4_000_000


class GConfig(BaseModel):
    """Settings of the filter G; defaults follow the PointNetVLAD paper where it gives a value.

    Lengths are metres in the input cloud's frame (before normalisation).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    target_points: int = Field(4096, ge=2, description="Points in the output submap.")
    min_points: int = Field(
        16, ge=1, description="Fewest points left after ground removal; fewer is an error."
    )
    min_range: float | None = Field(
        None, ge=0, description="Drop points closer than this to the origin (m, 3-D distance)."
    )
    max_range: float | None = Field(
        None, gt=0, description="Drop points farther than this from the origin (m, 3-D distance)."
    )
    box: Box | None = Field(
        None, description="Keep only points inside (xmin, ymin, zmin, xmax, ymax, zmax), metres."
    )
    remove_ground: bool = Field(True, description="Remove the ground (the paper does).")
    ground_mode: Literal["local", "plane"] = Field(
        "local",
        description="'local': height above a grid surface that follows slopes and kerbs; "
        "'plane': within the threshold of one RANSAC plane (the paper).",
    )
    ground_threshold: float = Field(
        0.5, gt=0, description="Points less than this above the ground surface are ground (m)."
    )
    ground_cell: float = Field(1.0, gt=0, description="Cell size of the ground height map (m).")
    ground_window: float = Field(
        9.0,
        gt=0,
        description="Objects narrower than this (m) are not taken for ground (the morphological "
        "window of the height map).",
    )
    ground_step: float = Field(
        0.3,
        gt=0,
        description="Largest rise (m) from a height-map cell to its lowest neighbour that still "
        "counts as the same ground (kerbs, slopes up to about 20% with 1 m cells).",
    )
    ground_percentile: float = Field(
        5.0, ge=0, le=100, description="Per-cell percentile of heights taken as the cell's ground."
    )
    max_ground_tilt_deg: float = Field(
        30.0, gt=0, le=90, description="Largest angle between the ground normal and the z axis."
    )
    up: Literal["auto", "z", "-z"] = Field(
        "auto",
        description="Which side of the ground is up: 'auto' (the side under which the columns' "
        "lowest points lie on one plane best; handles z-down frames such as NCLT's), 'z' or '-z'.",
    )
    ransac_iterations: int = Field(200, ge=1, description="RANSAC plane hypotheses.")
    voxel_iterations: int = Field(30, ge=1, description="Most leaf sizes tried.")
    prevoxel: float | None = Field(
        None,
        gt=0,
        description="Average the cropped points in voxels of this size (m) before ground "
        "removal: a dense single scan (120,000 points) then costs G a fraction of the time, "
        "and the output moves by a fraction of the final voxel (about 1 m).",
    )
    normalize: bool = Field(True, description="Centre, scale and clip to [-1, 1].")
    mean_distance: float = Field(
        0.5, gt=0, description="Mean distance from the centroid after scaling (units of [-1,1])."
    )
    negate: bool = Field(False, description="Negate the output coordinates (the MATLAB script).")

    @model_validator(mode="after")
    def _check(self) -> GConfig:
        if self.box is not None and any(
            lo > hi for lo, hi in zip(self.box[:3], self.box[3:], strict=True)
        ):
            raise ValueError("box must be (xmin, ymin, zmin, xmax, ymax, zmax) with min <= max")
        if (
            self.min_range is not None
            and self.max_range is not None
            and self.min_range >= self.max_range
        ):
            raise ValueError("min_range must be smaller than max_range")
        return self

    @classmethod
    def from_file(cls, path: str | Path) -> GConfig:
        """The settings in a YAML or JSON file of ``GConfig`` fields (missing ones default;
        an empty file gives the defaults).

        Raises ``FileNotFoundError`` for a missing file and :class:`InputError` naming the file
        for text that is not YAML/JSON or settings G does not accept.
        """
        import yaml

        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text(encoding="utf-8"))
        except yaml.YAMLError as exc:
            raise InputError(f"not valid YAML/JSON: {exc}", path) from None
        try:
            return cls.model_validate(data or {})
        except ValidationError as exc:
            raise InputError(f"bad filter G settings: {exc}", path) from None


#: How far from the sensor a single scan is kept (metres): the crop of keyframe maps and of
#: single-scan queries, so that a query meets a map entry of its own kind.
SCAN_MAX_RANGE_M = 50.0
#: The voxel a single scan is averaged in before G's ground removal (metres): a 120,000-point
#: scan goes on with about a quarter of its points (``GConfig.prevoxel``).
SCAN_PREVOXEL_M = 0.2


def scan_config(base: GConfig | None = None, max_range: float = SCAN_MAX_RANGE_M) -> GConfig:
    """G for one scan in its sensor frame (keyframes, single-scan queries): ``base`` (default:
    the default settings) with points farther than ``max_range`` metres from the sensor dropped
    and the rest averaged in :data:`SCAN_PREVOXEL_M` voxels (unless ``base`` sets its own)."""
    base = base or GConfig()
    prevoxel = SCAN_PREVOXEL_M if base.prevoxel is None else base.prevoxel
    return GConfig.model_validate(
        {**base.model_dump(), "max_range": float(max_range), "prevoxel": prevoxel}
    )


@dataclass(frozen=True)
class GResult:
    """Output of :func:`apply_g`: the submap and what each step left.

    ``points``: float64 [target_points, 3]; ``leaf_size``: metres (0 when the cloud was smaller
    than the target and only refilled); ``up``: unit normal of the ground plane, float64 [3],
    pointing up (``None`` when ground removal is off).

    ``centre`` (float64 [3], input frame and units) and ``scale`` (input units per output unit,
    negative when ``negate`` flipped the cloud) map the output back to where it came from:
    ``input ≈ centre + scale * points`` (exactly, up to the voxel averaging and the crop to
    [-1, 1]); without ``normalize`` they are 0 and 1 (or -1).
    """

    points: np.ndarray
    n_input: int
    n_cropped: int
    n_nonground: int
    n_voxels: int
    leaf_size: float
    up: np.ndarray | None
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0


def _col_mean(a: np.ndarray) -> np.ndarray:
    """Column means of [N, K] (column by column: see :func:`~.voxel.column_min`)."""
    return np.array([a[:, k].mean() for k in range(a.shape[1])])


MAX_COORDINATE = 1e8
"""Largest absolute coordinate (metres) G accepts: ten times any UTM northing."""


def _as_points(points: np.ndarray, source: str = "points") -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"expected points of shape [N, 3], got {tuple(points.shape)}", source)
    if not np.issubdtype(points.dtype, np.number):
        raise InputError(f"points must be numeric, got dtype {points.dtype}", source)
    points = np.ascontiguousarray(points, dtype=np.float64)
    if not np.isfinite(points).all():
        raise InputError("points contain NaN or infinite coordinates", source)
    if points.size and np.abs(points).max() > MAX_COORDINATE:
        # Far beyond any UTM coordinate; squaring such values overflows in the plane fit.
        raise InputError(
            f"coordinates beyond {MAX_COORDINATE:g} m (largest {np.abs(points).max():.3g}); "
            "expected metres in a sensor or UTM frame",
            source,
        )
    return points


# --- 1. crop -------------------------------------------------------------------------------


def crop_mask(
    points: np.ndarray,
    *,
    min_range: float | None = None,
    max_range: float | None = None,
    box: Box | None = None,
) -> np.ndarray:
    """Boolean [N] mask of the points kept by the crop.

    ``points`` float [N, 3] metres; ranges are 3-D distances from the origin (the sensor for a
    single scan), inclusive bounds; ``box`` is (xmin, ymin, zmin, xmax, ymax, zmax), inclusive.
    """
    keep = np.ones(points.shape[0], dtype=bool)
    if min_range is not None or max_range is not None:
        r2 = np.einsum("ij,ij->i", points, points)
        if min_range is not None:
            keep &= r2 >= min_range * min_range
        if max_range is not None:
            keep &= r2 <= max_range * max_range
    if box is not None:
        lo = np.asarray(box[:3], dtype=np.float64)
        hi = np.asarray(box[3:], dtype=np.float64)
        for k in range(3):
            keep &= (points[:, k] >= lo[k]) & (points[:, k] <= hi[k])
    return keep


def crop(
    points: np.ndarray,
    *,
    min_range: float | None = None,
    max_range: float | None = None,
    box: Box | None = None,
) -> np.ndarray:
    """The points [M, 3] inside the range and box limits (see :func:`crop_mask`)."""
    return points[crop_mask(points, min_range=min_range, max_range=max_range, box=box)]


# --- 2. ground -------------------------------------------------------------------------------


def _fit_plane(
    points: np.ndarray, fallback: np.ndarray, max_tilt_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane (centroid, unit normal) of float64 [M, 3]; ``fallback`` normal if
    the fit tips over beyond ``max_tilt_deg``."""
    mean = _col_mean(points)
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
    centre = _col_mean(points)
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


def ground_mask(
    points: np.ndarray,
    config: GConfig | None = None,
    *,
    rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Boolean [N] mask of the ground points and the up normal float64 [3].

    ``points`` float64 [N, 3] metres. See :class:`GConfig` for ``ground_mode``,
    ``ground_threshold``, ``ground_cell``, ``ground_window``; in ``"local"`` mode points
    below the local surface (stray returns under the road) count as ground too.
    """
    cfg = config or GConfig()
    rng = np.random.default_rng(0) if rng is None else rng
    normal, offset = fit_ground_plane(
        points,
        threshold=cfg.ground_threshold,
        max_tilt_deg=cfg.max_ground_tilt_deg,
        up=cfg.up,
        iterations=cfg.ransac_iterations,
        rng=rng,
    )
    if cfg.ground_mode == "plane":
        return np.abs(points @ normal + offset) < cfg.ground_threshold, normal
    rot = rotation_to_z(normal)  # rows: two horizontal axes, then the normal
    xy = np.stack([points @ rot[0], points @ rot[1]], axis=1)
    height = points @ normal + offset
    surface = ground_surface(
        xy,
        height,
        cell=cfg.ground_cell,
        window=cfg.ground_window,
        percentile=cfg.ground_percentile,
        step=cfg.ground_step,
        seed_band=cfg.ground_threshold,
    )
    return height - surface < cfg.ground_threshold, normal


def remove_ground(
    points: np.ndarray, config: GConfig | None = None, *, rng: np.random.Generator | None = None
) -> np.ndarray:
    """The non-ground points float64 [M, 3] (see :func:`ground_mask`)."""
    return points[~ground_mask(points, config, rng=rng)[0]]


# --- 4. normalisation ------------------------------------------------------------------------


def normalization(points: np.ndarray, mean_distance: float = 0.5) -> tuple[np.ndarray, float]:
    """What :func:`normalize` does to ``points``: its centre (the centroid, float64 [3]) and
    scale (input units per output unit, so that the mean distance from the centre becomes
    ``mean_distance``). ``InputError`` when all points coincide."""
    centre, spread = _centre_spread(points)
    return centre, spread / mean_distance


def _centre_spread(points: np.ndarray) -> tuple[np.ndarray, float]:
    centre = _col_mean(points)
    centred = points - centre
    spread = float(np.sqrt(np.einsum("ij,ij->i", centred, centred)).mean())
    if spread <= 0.0:
        raise InputError("all points coincide; the cloud cannot be normalised", "points")
    return centre, spread


def normalize(
    points: np.ndarray,
    target: int | None = None,
    *,
    rng: np.random.Generator,
    mean_distance: float = 0.5,
) -> np.ndarray:
    """Centre on the centroid, scale so the mean distance from it is ``mean_distance``, drop
    points with any coordinate outside [-1, 1], refill (seeded duplicates) to ``target`` points
    (default: the input count). ``points`` float64 [M, 3]; returns float64 [target, 3].
    """
    target = points.shape[0] if target is None else target
    centre, spread = _centre_spread(points)
    scaled = (points - centre) * (mean_distance / spread)
    a = np.abs(scaled)
    inside = scaled[(a[:, 0] <= 1.0) & (a[:, 1] <= 1.0) & (a[:, 2] <= 1.0)]
    return resample_to(inside, target, rng=rng)


# --- the filter ------------------------------------------------------------------------------


def apply_g(points: np.ndarray, config: GConfig | None = None, *, seed: int = 0) -> GResult:
    """Run the filter G and report what each step left (see :class:`GResult`).

    ``points`` float [N, 3] metres (any frame; z or -z up). Raises InputError for a bad shape,
    NaN/inf, or fewer than ``config.min_points`` points left after cropping and ground removal.
    """
    cfg = config or GConfig()
    rng = np.random.default_rng(seed)
    pts = _as_points(points)
    n_input = pts.shape[0]
    if cfg.min_range is not None or cfg.max_range is not None or cfg.box is not None:
        pts = crop(pts, min_range=cfg.min_range, max_range=cfg.max_range, box=cfg.box)
    n_cropped = pts.shape[0]
    if cfg.prevoxel is not None and n_cropped > cfg.target_points:
        pts = voxel_average(pts, cfg.prevoxel)
    if n_cropped < cfg.min_points:
        raise InputError(
            f"{n_cropped} points left after cropping {n_input}; at least {cfg.min_points} needed",
            "points",
        )
    up = None
    if cfg.remove_ground:
        ground, up = ground_mask(pts, cfg, rng=rng)
        pts = pts[~ground]
    n_nonground = pts.shape[0]
    if n_nonground < cfg.min_points:
        raise InputError(
            f"{n_nonground} points left after ground removal (of {n_cropped}); at least "
            f"{cfg.min_points} needed",
            "points",
        )
    if n_nonground < cfg.target_points:
        log.info("%d points < %d: refilled with duplicates", n_nonground, cfg.target_points)
    out, leaf, n_voxels = adaptive_voxel_downsample(
        pts, cfg.target_points, rng=rng, iterations=cfg.voxel_iterations
    )
    centre, scale = np.zeros(3), 1.0
    if cfg.normalize:
        centre, scale = normalization(out, cfg.mean_distance)
        out = normalize(out, cfg.target_points, rng=rng, mean_distance=cfg.mean_distance)
    if cfg.negate:
        out = -out
        scale = -scale
    return GResult(
        points=np.ascontiguousarray(out, dtype=np.float64),
        n_input=n_input,
        n_cropped=n_cropped,
        n_nonground=n_nonground,
        n_voxels=n_voxels,
        leaf_size=leaf,
        up=up,
        centre=centre,
        scale=scale,
    )


def filter_g(points: np.ndarray, config: GConfig | None = None, *, seed: int = 0) -> np.ndarray:
    """The filter G: float [N, 3] metres -> float64 [config.target_points, 3].

    With ``normalize`` (default) the result is centred, of mean distance 0.5 and inside
    [-1, 1]; without, it is the ground-free, voxel-averaged cloud in the input frame and units.
    Same input and seed give identical bytes.
    """
    return apply_g(points, config, seed=seed).points
