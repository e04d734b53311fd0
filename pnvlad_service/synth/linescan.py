"""A ray-cast 2D line scanner (push-broom): one line of a SICK LMS-151-like scanner at a time.

A line is the fan of rays of :class:`~pnvlad_service.synth.sensors.PushbroomConfig` in the
scanner's plane, cast from the scanner's place on the moving vehicle. The surfaces and the real
sensor's failures are the spinning LiDAR's (:func:`~pnvlad_service.synth.lidar.nearest_hits`,
:func:`~pnvlad_service.synth.lidar.real_returns`); only the choice of the rays each primitive
can meet differs: a primitive is paired with a line when the scan plane cuts its bounding
cylinder, and then with the rays of the angular window its bounding sphere covers in that
plane. Rays that meet the vehicle's own body (:attr:`PushbroomConfig.body`) return nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pnvlad_service.synth.lidar import PairFn, RayBundle, nearest_hits, real_returns
from pnvlad_service.synth.sensors import PushbroomConfig
from pnvlad_service.synth.world import Ground, Scene

__all__ = ["LineFan", "body_mask", "cast_line", "line_fan", "scene_near"]


@dataclass
class LineFan:
    """A line scanner's rays in the vehicle frame (x forward, y left, z up): ``dirs`` float64
    [R, 3] unit, ``angles`` float64 [R] radians in the scan plane (ascending, evenly spaced),
    ``origin`` float64 [3] the scanner above the road, ``axes`` float64 [3, 3] its axes
    (columns x, y, z: z is the scan plane's normal), ``bundle`` the same rays as the failure
    model takes them, its ``roof`` the rays the vehicle's body blocks."""

    dirs: np.ndarray
    angles: np.ndarray
    origin: np.ndarray
    axes: np.ndarray
    bundle: RayBundle


def body_mask(cfg: PushbroomConfig, dirs: np.ndarray) -> np.ndarray:
    """bool [R]: which rays ``dirs`` [R, 3] (vehicle frame) from the scanner meet one of the
    vehicle's body boxes (the slab test of a ray against an axis-aligned box)."""
    o = cfg.origin()
    hit = np.zeros(len(dirs), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / dirs
        for box in cfg.body:
            lo, hi = np.array(box[0::2]), np.array(box[1::2])
            t1, t2 = (lo - o) * inv, (hi - o) * inv
            near = np.nanmax(np.minimum(t1, t2), axis=1)
            far = np.nanmin(np.maximum(t1, t2), axis=1)
            hit |= (near <= far) & (far > 0)
    return hit


def line_fan(cfg: PushbroomConfig) -> LineFan:
    """The scanner's rays, once a sensor: the same every line."""
    axes = cfg.axes()
    a = cfg.angles()
    dirs = np.cos(a)[:, None] * axes[:, 0] + np.sin(a)[:, None] * axes[:, 1]
    bundle = RayBundle(dirs[None], np.zeros(1), a, body_mask(cfg, dirs))
    return LineFan(dirs, a, cfg.origin(), axes, bundle)


def scene_near(scene: Scene, xy: np.ndarray, radius: float) -> Scene:
    """The primitives of ``scene`` whose bounding circle comes within ``radius`` metres of
    ``xy`` [2] (a stretch of street: the lines cast there meet nothing else)."""
    b, c, e = scene.boxes, scene.cylinders, scene.ellipsoids
    rb = np.hypot(b.half[:, 0], b.half[:, 1])
    keep_b = np.linalg.norm(b.center - xy, axis=1) - rb < radius
    keep_c = np.linalg.norm(c.center - xy, axis=1) - c.radius < radius
    keep_e = np.linalg.norm(e.center[:, :2] - xy, axis=1) - e.radii[:, 0] < radius
    return Scene(b.take(keep_b), c.take(keep_c), e.take(keep_e))


def _windows(
    theta: np.ndarray, half: np.ndarray, a0: float, step: float, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """First and last ray (int64 [3P] each, last < first: none) of the angular windows
    ``theta`` +- ``half`` [P], also shifted by a turn each way (a window across the fan's
    back)."""
    lo, hi = [], []
    for shift in (0.0, 2 * np.pi, -2 * np.pi):
        lo.append(np.ceil((theta + shift - half - a0) / step).astype(np.int64) - 1)
        hi.append(np.floor((theta + shift + half - a0) / step).astype(np.int64) + 1)
    first = np.clip(np.concatenate(lo), 0, n)
    last = np.clip(np.concatenate(hi), -1, n - 1)
    return first, last


def _fan_pairs(o: np.ndarray, plane: np.ndarray, fan: LineFan, max_range: float) -> PairFn:
    """The pair function of one line (``nearest_hits``'s ``pairs``): from the line's origin
    ``o`` [3] and its scan plane's axes in the world ``plane`` [3, 3] (columns x, y, normal)."""
    e1, e2, nrm = plane[:, 0], plane[:, 1], plane[:, 2]
    a0 = float(fan.angles[0])
    step = float(fan.angles[1] - fan.angles[0]) if len(fan.angles) > 1 else 1.0
    n = len(fan.angles)
    flat_n = float(np.hypot(nrm[0], nrm[1]))

    def pairs(
        center: np.ndarray, radius: np.ndarray, zlo: np.ndarray, zhi: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        hz = (zhi - zlo) / 2
        rel = np.concatenate([center - o[:2], ((zlo + zhi) / 2 - o[2])[:, None]], axis=1)
        cut = np.abs(rel @ nrm) <= radius * flat_n + hz * abs(nrm[2]) + 1e-6
        cut &= np.hypot(rel[:, 0], rel[:, 1]) - radius < max_range
        idx = np.flatnonzero(cut)
        if len(idx) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        u, v = rel[idx] @ e1, rel[idx] @ e2
        dist = np.hypot(u, v)
        rho = np.hypot(radius[idx], hz[idx])
        inside = dist <= rho
        half = np.where(inside, np.pi, np.arcsin(np.clip(rho / np.maximum(dist, 1e-9), 0, 1)))
        first, last = _windows(np.arctan2(v, u), half, a0, step, n)
        prim = np.tile(idx, 3)
        count = np.maximum(last - first + 1, 0)
        # a primitive about the scanner: every ray, once (its first window)
        whole = np.tile(inside, 3)
        once = np.arange(len(prim)) < len(idx)
        count = np.where(whole, np.where(once, n, 0), count)
        first = np.where(whole, 0, first)
        p = np.repeat(prim, count)
        start = np.repeat(np.cumsum(count) - count, count)
        ray = np.repeat(first, count) + (np.arange(len(p)) - start)
        return p, ray

    return pairs


def cast_line(
    scene: Scene,
    ground: Ground,
    position: np.ndarray,
    attitude: np.ndarray,
    cfg: PushbroomConfig,
    rng: np.random.Generator,
    fan: LineFan | None = None,
) -> np.ndarray:
    """One line from the scanner at ``position`` (local metres, float64 [3]) on a vehicle whose
    axes in the world are ``attitude`` (float64 [3, 3], columns x forward, y left, z up).

    Returns the returns in the vehicle's axes about the scanner (x forward, y left, z up, the
    scanner at the origin), float32 [N, 3] metres: range noise, dropouts, glass, paint and
    foliage as the spinning sensors have them, the rays the body blocks and those without a
    return in range removed.
    """
    fan = fan or line_fan(cfg)
    att = np.asarray(attitude, dtype=np.float64)
    o = np.asarray(position, dtype=np.float64)
    world = fan.dirs @ att.T
    pairs = _fan_pairs(o, att @ fan.axes, fan, cfg.max_range)
    depth, hits = nearest_hits(scene, ground, o, world, pairs, cfg, rng)
    ok = np.isfinite(depth) & (depth <= cfg.max_range) & (depth >= cfg.min_range)
    pts, _ = real_returns(cfg, rng, fan.bundle, fan.dirs, world, depth, ok, hits, (0.0, 0.0))
    return pts
