"""The filter G: one raw point cloud (metres) to one benchmark submap (4096 points in [-1, 1]).

The steps, in order, each a public function of this module, of :mod:`~.ground` or of
:mod:`~.voxel` (see docs/PREPROCESS.md for figures on real scans):

1. :func:`crop_mask` / :func:`crop`: optional range (3-D distance from the origin, i.e. the
   sensor) and axis-aligned box.
2. :func:`ground_mask` / :func:`remove_ground`: a RANSAC plane through the lowest point of
   each column (:func:`~.ground.fit_ground_plane`, :func:`~.ground.lowest_per_cell`; normal
   within ``max_ground_tilt_deg`` of the z axis) gives the up side and a frame; in ``"local"``
   mode a height map (:func:`~.ground.ground_surface`: a low percentile per ``ground_cell``
   cell, the cells joined smoothly to the plane, then a grey-scale closing and opening over
   ``ground_window`` metres) follows slopes and kerbs, and every point less than
   ``ground_threshold`` above that surface (or below it) is ground. ``"plane"`` mode is the
   paper's: points within ``ground_threshold`` of the single plane.
3. :mod:`pnvlad_service.preprocess.voxel`: ``voxel_average`` with the leaf size found by
   ``find_leaf_size`` (a bracketed secant/bisection search until the voxel count is closest to
   the target), then ``resample_to`` duplicates or drops seeded random points to hit the
   target exactly (``adaptive_voxel_downsample`` does both).
4. :func:`normalize`: centre on the centroid, scale to a mean distance of 0.5 from it, drop
   points outside [-1, 1]^3, refill to the target; optional negation afterwards.

Everything is vectorised numpy and deterministic: the same input and seed give the same bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from pnvlad_service.errors import InputError
from pnvlad_service.preprocess.ground import fit_ground_plane, ground_surface, rotation_to_z
from pnvlad_service.preprocess.voxel import (
    adaptive_voxel_downsample,
    column_mean,
    resample_to,
    voxel_average,
)

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float, float, float]


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
    centre = column_mean(points)
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
