"""A vectorised ray-cast spinning LiDAR (Velodyne HDL-64E-like by default).

One scan is ``beams × columns`` rays from one origin. A point is where the first surface along
its ray is (real occlusion), found analytically for boxes, vertical cylinders, ellipsoids and a
height-field ground. No per-ray Python loop: each primitive within range is paired with the
azimuth columns and the beams its bounding volume can cover, and all pairs are intersected in
one numpy pass, then reduced to the nearest hit per ray with ``np.minimum.at``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pnvlad_service.synth.sensors import LidarConfig
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CAR,
    KIND_GRASS,
    Boxes,
    Cylinders,
    Ellipsoids,
    Ground,
    Scene,
)

__all__ = [
    "LidarConfig",
    "RayBundle",
    "cast_scan",
    "nearest_hits",
    "on_roof",
    "ray_bundle",
    "real_returns",
]


@dataclass
class RayBundle:
    """Unit ray directions in the sensor frame, float64 [beams, columns, 3]; elevation
    float64 [beams] (radians, descending), azimuth float64 [columns] (radians, from +x);
    ``roof``: which rays (bool [beams * columns], flat) meet the vehicle's own roof, None
    where the sensor does not see it."""

    dirs: np.ndarray
    elevation: np.ndarray
    azimuth: np.ndarray
    roof: np.ndarray | None = None


def ray_bundle(cfg: LidarConfig) -> RayBundle:
    """The sensor's rays, beam-major, and those its vehicle's roof hides (once a sensor: they
    are the same rays every scan)."""
    el = np.deg2rad(cfg.elevations())
    az = np.arange(cfg.columns) * (2 * np.pi / cfg.columns)
    ce = np.cos(el)[:, None]
    d = np.stack(
        [
            ce * np.cos(az)[None],
            ce * np.sin(az)[None],
            np.broadcast_to(np.sin(el)[:, None], (cfg.beams, cfg.columns)),
        ],
        -1,
    )
    roof = on_roof(cfg, d.reshape(-1, 3)) if cfg.ego_roof_drop > 0 else None
    return RayBundle(d, el, az, roof)


def _pairs(
    center: np.ndarray,
    radius: np.ndarray,
    zlo: np.ndarray,
    zhi: np.ndarray,
    origin: np.ndarray,
    yaw: float,
    rays: RayBundle,
    max_range: float,
    tilt: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (primitive, ray) pairs: primitive index int64 [M], flat ray index int64 [M].

    ``center`` [P,2], ``radius`` [P] is each primitive's bounding circle, ``zlo``/``zhi`` [P]
    its vertical extent; only rays whose azimuth and elevation can reach it are kept.

    ``tilt`` (float64 [3, 3]): how the sensor leans, its orientation in the frame of its
    heading ``yaw`` (None: level). A beam at azimuth a then looks higher in the world by about
    ``tilt[2, 0] cos a + tilt[2, 1] sin a`` radians, and its azimuth moves by at most the lean
    times the tangent of its elevation: the windows shift by the first and widen by the rest.
    """
    ncol = len(rays.azimuth)
    nbeam = len(rays.elevation)
    rel = center - origin[:2]
    dist = np.hypot(rel[:, 0], rel[:, 1])
    keep = dist - radius < max_range
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rel, dist, radius, zlo, zhi = rel[idx], dist[idx], radius[idx], zlo[idx], zhi[idx]
    dcol = 2 * np.pi / ncol
    theta = np.arctan2(rel[:, 1], rel[:, 0]) - yaw
    inside = dist <= radius * 1.0001
    half = np.where(inside, np.pi, np.arcsin(np.clip(radius / np.maximum(dist, 1e-9), 0, 1)))
    # Beam range from the elevation span of the bounding cylinder.
    near = np.maximum(dist - radius, 0.05)
    far = dist + radius
    e_hi = np.maximum(np.arctan2(zhi - origin[2], near), np.arctan2(zhi - origin[2], far))
    e_lo = np.minimum(np.arctan2(zlo - origin[2], near), np.arctan2(zlo - origin[2], far))
    e_hi = np.where(inside, np.pi / 2, e_hi)
    e_lo = np.where(inside & (zlo < origin[2]), -np.pi / 2, e_lo)
    margin = 1e-3
    if tilt is not None:
        lean = float(np.hypot(tilt[2, 0], tilt[2, 1]))
        steep = np.minimum(np.maximum(np.abs(e_lo), np.abs(e_hi)), np.abs(rays.elevation).max())
        half = half + lean * np.tan(steep) + abs(float(tilt[1, 0])) + lean**2
        low, high = _rise_span(tilt[2, 0], tilt[2, 1], theta, half)
        e_hi, e_lo = e_hi - low, e_lo - high
        margin = margin + lean * (1.0 - np.cos(steep)) + lean**2
    c0 = np.floor((theta - half) / dcol).astype(np.int64) - 1
    c1 = np.ceil((theta + half) / dcol).astype(np.int64) + 1
    ncols = np.minimum(c1 - c0 + 1, ncol)
    el = rays.elevation  # descending
    b0 = np.searchsorted(-el, -e_hi - margin, side="left")
    b1 = np.searchsorted(-el, -e_lo + margin, side="right")
    nb = np.clip(b1 - b0, 0, nbeam)
    ncols = np.where(nb > 0, ncols, 0)
    # Expand primitives → (primitive, column) → (primitive, column, beam).
    p1 = np.repeat(np.arange(len(idx)), ncols)
    start = np.repeat(np.cumsum(ncols) - ncols, ncols)
    col = (np.repeat(c0, ncols) + (np.arange(len(p1)) - start)) % ncol
    nbr = nb[p1]
    p2 = np.repeat(p1, nbr)
    start2 = np.repeat(np.cumsum(nbr) - nbr, nbr)
    beam = b0[p2] + (np.arange(len(p2)) - start2)
    ray = beam * ncol + np.repeat(col, nbr)
    return idx[p2], ray


def _rise_span(
    a: float, b: float, theta: np.ndarray, half: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Least and most of ``a cos x + b sin x`` for x within ``half`` of ``theta``: how much
    lower and higher a leaning sensor's beams look over a primitive's azimuth span."""
    amp, peak = float(np.hypot(a, b)), float(np.arctan2(b, a))
    ends = amp * np.cos(np.stack([theta - half, theta + half]) - peak)
    to_peak = np.abs(np.mod(theta - peak + np.pi, 2 * np.pi) - np.pi)  # 0..pi
    high = np.where(to_peak <= half, amp, ends.max(0))
    low = np.where(np.pi - to_peak <= half, -amp, ends.min(0))
    return low, high


def _hit_boxes(
    b: Boxes, prim: np.ndarray, o: np.ndarray, d: np.ndarray, faces: bool = False
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Entry distance of rays ``d`` [M,3] from ``o`` into boxes ``prim`` [M] (inf if none);
    with ``faces`` (a real sensor's failures need them) also the cosine of the incidence on the
    face entered and where on a side face it is entered: metres along the face (from the box's
    corner), nan on the top or bottom; else None for both."""
    c, s = np.cos(b.yaw[prim]), np.sin(b.yaw[prim])
    rx = o[0] - b.center[prim, 0]
    ry = o[1] - b.center[prim, 1]
    ox = c * rx + s * ry
    oy = -s * rx + c * ry
    dx = c * d[:, 0] + s * d[:, 1]
    dy = -s * d[:, 0] + c * d[:, 1]
    hx, hy = b.half[prim, 0], b.half[prim, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        ix, iy, iz = 1.0 / dx, 1.0 / dy, 1.0 / d[:, 2]
        tx1, tx2 = (-hx - ox) * ix, (hx - ox) * ix
        ty1, ty2 = (-hy - oy) * iy, (hy - oy) * iy
        tz1, tz2 = (b.z[prim, 0] - o[2]) * iz, (b.z[prim, 1] - o[2]) * iz
        enter = np.stack([np.minimum(tx1, tx2), np.minimum(ty1, ty2), np.minimum(tz1, tz2)])
        tn = enter.max(0)
        tf = np.minimum(
            np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2)), np.maximum(tz1, tz2)
        )
    hit = (tn <= tf) & (tn > 0)
    if not faces:
        return np.where(hit, tn, np.inf), None, None
    face = enter.argmax(0)
    cos = np.abs(np.choose(face, [dx, dy, d[:, 2]]))
    with np.errstate(invalid="ignore"):  # misses: inf times a zero direction
        along = np.where(
            face == 0, oy + tn * dy + hy, np.where(face == 1, ox + tn * dx + hx, np.nan)
        )
    return np.where(hit, tn, np.inf), cos, along


def _hit_cylinders(
    cy: Cylinders, prim: np.ndarray, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the side of vertical cylinders (inf if missed) and the incidence cosine
    (a few products of what the distance needs anyway)."""
    rx = o[0] - cy.center[prim, 0]
    ry = o[1] - cy.center[prim, 1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    bb = d[:, 0] * rx + d[:, 1] * ry
    cc = rx * rx + ry * ry - cy.radius[prim] ** 2
    disc = bb * bb - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-bb - np.sqrt(disc)) / a
        # the radial normal at the hit: (o + t d - c) / r, horizontal
        cos = np.abs((rx + t * d[:, 0]) * d[:, 0] + (ry + t * d[:, 1]) * d[:, 1])
        cos = cos / cy.radius[prim]
    z = o[2] + t * d[:, 2]
    hit = (disc > 0) & (t > 0) & (z >= cy.z[prim, 0]) & (z <= cy.z[prim, 1])
    return np.where(hit, t, np.inf), np.nan_to_num(cos, nan=1.0)


def _hit_ellipsoids(
    e: Ellipsoids,
    prim: np.ndarray,
    o: np.ndarray,
    d: np.ndarray,
    rng: np.random.Generator,
    depth_m: float = 0.0,
) -> np.ndarray:
    """Distance to ellipsoids; a hit survives with the crown's density (foliage gaps). With
    ``depth_m`` > 0 the ray returns from inside the crown, an exponential depth of that mean
    past its surface (at most its far side): leaves scattered through the crown's volume."""
    r = e.radii[prim]
    oc = (o[None, :] - e.center[prim]) / r
    dd = d / r
    a = (dd * dd).sum(1)
    bb = (oc * dd).sum(1)
    cc = (oc * oc).sum(1) - 1.0
    disc = bb * bb - a * cc
    with np.errstate(invalid="ignore"):
        root = np.sqrt(disc)
        t = (-bb - root) / a
    hit = (disc > 0) & (t > 0) & (rng.random(len(prim)) < e.density[prim])
    if depth_m > 0:
        chord = np.where(hit, 2.0 * root / a, 0.0)
        t = t + np.minimum(rng.exponential(depth_m, len(prim)), chord)
    return np.where(hit, t, np.inf)


def _into_grass(
    t: np.ndarray,
    grass: np.ndarray,
    z: np.ndarray,
    dz: np.ndarray,
    depth_m: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Box hits ``t`` with those on grass (``grass``) moved into the blades: an exponential
    depth of mean ``depth_m`` past the top, at most the ray's way through the layer (its
    thickness over the ray's slope, the ground beneath stops the rest)."""
    chord = np.where(grass, (z[:, 1] - z[:, 0]) / np.maximum(np.abs(dz), 0.05), 0.0)
    step = np.minimum(rng.exponential(depth_m, len(t)), chord)
    return np.where(grass & np.isfinite(t), t + step, t)


def _hit_ground(
    g: Ground, o: np.ndarray, d: np.ndarray, max_range: float, iters: int = 4
) -> np.ndarray:
    """Distance to the height field along rays ``d`` [M,3] (Newton on o_z + t d_z = h)."""
    h0 = float(g.height(o[0], o[1]))
    down = d[:, 2] < -1e-3
    t = np.full(len(d), np.inf)
    if not down.any():
        return t
    dd = d[down]
    tt = (o[2] - h0) / -dd[:, 2]
    tt = np.minimum(tt, 2 * max_range)
    for _ in range(iters):
        x = o[0] + tt * dd[:, 0]
        y = o[1] + tt * dd[:, 1]
        h, gx, gy = g.height_and_grad(x, y)
        f = o[2] + tt * dd[:, 2] - h
        fp = dd[:, 2] - gx * dd[:, 0] - gy * dd[:, 1]
        tt = tt - f / np.where(np.abs(fp) < 1e-6, -1e-6, fp)
    ok = (tt > 0) & (tt <= max_range)
    t[np.flatnonzero(down)[ok]] = tt[ok]
    return t


#: What a return hit, for the sensor's failures: the ground, a building's side, a vehicle,
#: foliage, anything else.
MAT_GROUND, MAT_FACADE, MAT_VEHICLE, MAT_FOLIAGE, MAT_OTHER = 0, 1, 2, 3, 4
#: Facade windows: a bay every WINDOW_BAY_M along a building's side, a floor every
#: WINDOW_FLOOR_M, the glass the middle WINDOW_SHARE of each (none below WINDOW_SILL_M).
WINDOW_BAY_M, WINDOW_FLOOR_M, WINDOW_SHARE, WINDOW_SILL_M = 3.0, 3.3, 0.6, 1.0


def _windows(along: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Whether points on a facade (metres along it, above its foot) fall on a window's glass."""
    lo = (1.0 - WINDOW_SHARE) / 2
    u = np.mod(along, WINDOW_BAY_M) / WINDOW_BAY_M
    v = np.mod(height, WINDOW_FLOOR_M) / WINDOW_FLOOR_M
    return (u > lo) & (u < 1 - lo) & (v > lo) & (v < 1 - lo) & (height > WINDOW_SILL_M)


def _winners(depth: np.ndarray, ray: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Which candidate hits (ray, t) are their ray's nearest surface."""
    return np.isfinite(t) & (t == depth[ray])


def _world_rays(
    flat: np.ndarray, yaw: float, attitude: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The rays ``flat`` [N, 3] turned into the world by the heading ``yaw`` (a level sensor) or
    by ``attitude``, and the sensor's lean in the frame of its heading (None when level)."""
    c, s = np.cos(yaw), np.sin(yaw)
    if attitude is None:
        world = np.empty_like(flat)
        world[:, 0] = c * flat[:, 0] - s * flat[:, 1]
        world[:, 1] = s * flat[:, 0] + c * flat[:, 1]
        world[:, 2] = flat[:, 2]
        return world, None
    attitude = np.asarray(attitude, dtype=np.float64)
    # by columns: a BLAS product of this shape would take every core for nothing
    world = flat[:, :1] * attitude[:, 0] + flat[:, 1:2] * attitude[:, 1]
    world += flat[:, 2:] * attitude[:, 2]
    return world, np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ attitude


#: Candidate (primitive, ray) pairs of one primitive kind: from its bounding cylinders (centres
#: [P, 2], radii [P], bottom and top z [P]) to primitive and flat ray indices, int64 [M] each.
PairFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _box_hits(
    bx: Boxes,
    o: np.ndarray,
    world: np.ndarray,
    pairs: PairFn,
    cfg: Any,
    rng: np.random.Generator,
    depth: np.ndarray,
    hits: list,
) -> None:
    """The boxes' nearest hits into ``depth`` (in place) and, for a real sensor, what each hit
    is made of into ``hits``: vehicles, grass, facades and their glass, anything else."""
    real = cfg.realistic
    rad = np.hypot(bx.half[:, 0], bx.half[:, 1])
    prim, ray = pairs(bx.center, rad, bx.z[:, 0], bx.z[:, 1])
    if not len(prim):
        return
    t, cos, along = _hit_boxes(bx, prim, o, world[ray], faces=real)
    kind = bx.kind[prim]
    grass = kind == KIND_GRASS
    if cfg.foliage_depth > 0 and grass.any():
        t = _into_grass(t, grass, bx.z[prim], world[ray, 2], cfg.foliage_depth, rng)
    np.minimum.at(depth, ray, t)
    if real:
        mat = np.where(kind == KIND_CAR, MAT_VEHICLE, MAT_OTHER)
        mat = np.where(grass, MAT_FOLIAGE, mat)
        facade = (kind == KIND_BUILDING) & np.isfinite(along)
        mat = np.where(facade, MAT_FACADE, mat)
        height = o[2] + np.where(np.isfinite(t), t, 0.0) * world[ray, 2] - bx.z[prim, 0]
        glass = facade & _windows(np.nan_to_num(along), height)
        glass &= cfg.glass_loss > 0
        hits.append((mat, ray, t, cos, glass))


def nearest_hits(
    scene: Scene,
    ground: Ground,
    o: np.ndarray,
    world: np.ndarray,
    pairs: PairFn,
    cfg: Any,
    rng: np.random.Generator,
) -> tuple[np.ndarray, list]:
    """Each ray's nearest surface from ``o`` (float64 [3]) along ``world`` (float64 [N, 3],
    unit): its distance float64 [N] (inf: none in range) and, for a real sensor
    (``cfg.realistic``), what each primitive kind's candidate hits are made of, for
    :func:`real_returns`. ``pairs`` picks the rays each primitive can meet (a spinning
    sensor's azimuth and elevation windows, a line scanner's fan)."""
    depth = _hit_ground(ground, o, world, cfg.max_range)
    real = cfg.realistic
    hits: list = []  # (material, ray, t, cos, glass) of each primitive kind, for the failures
    if len(scene.boxes):
        _box_hits(scene.boxes, o, world, pairs, cfg, rng, depth, hits)
    cy = scene.cylinders
    if len(cy):
        prim, ray = pairs(cy.center, cy.radius, cy.z[:, 0], cy.z[:, 1])
        if len(prim):
            t, cos = _hit_cylinders(cy, prim, o, world[ray])
            np.minimum.at(depth, ray, t)
            if real:
                hits.append((np.full(len(t), MAT_OTHER), ray, t, cos, np.zeros(len(t), bool)))
    el = scene.ellipsoids
    if len(el):
        zc, rz = el.center[:, 2], el.radii[:, 2]
        prim, ray = pairs(el.center[:, :2], el.radii[:, 0], zc - rz, zc + rz)
        if len(prim):
            t = _hit_ellipsoids(el, prim, o, world[ray], rng, cfg.foliage_depth)
            np.minimum.at(depth, ray, t)
            if real:
                ones = np.ones(len(t))
                hits.append((np.full(len(t), MAT_FOLIAGE), ray, t, ones, np.zeros(len(t), bool)))
    return depth, hits


def cast_scan(
    scene: Scene,
    ground: Ground,
    position: np.ndarray,
    yaw: float,
    cfg: LidarConfig,
    rng: np.random.Generator,
    rays: RayBundle | None = None,
    motion: tuple[float, float] = (0.0, 0.0),
    rings: bool = False,
    attitude: np.ndarray | None = None,
) -> Any:
    """Simulate one full turn of the sensor at ``position`` (local metres, float64 [3]) with
    heading ``yaw`` (radians from east, sensor level), the vehicle moving at ``motion`` =
    (forward speed m/s, yaw rate rad/s) at that moment (used when ``cfg.deskewed`` is False).
    ``attitude``: the sensor's full orientation instead (float64 [3, 3], sensor axes in the
    world, columns x forward, y left, z up), for a vehicle pitched and rolled by the slope it
    stands on; ``yaw`` is then its heading.

    Returns the points in the *sensor* frame (x forward, y left, z up), float32 [N,3], metres,
    with range noise and dropouts applied and rays without a return in range removed; with
    ``rings`` also each point's beam, int64 [N] (0: the top one).
    """
    rays = rays or ray_bundle(cfg)
    flat = rays.dirs.reshape(-1, 3)
    world, tilt = _world_rays(flat, yaw, attitude)
    o = np.asarray(position, dtype=np.float64)

    def pairs(
        center: np.ndarray, radius: np.ndarray, zlo: np.ndarray, zhi: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        return _pairs(center, radius, zlo, zhi, o, yaw, rays, cfg.max_range, tilt)

    depth, hits = nearest_hits(scene, ground, o, world, pairs, cfg, rng)
    real = cfg.realistic

    ok = np.isfinite(depth) & (depth <= cfg.max_range) & (depth >= cfg.min_range)
    if not real:  # the perfect sensor, as trees made before the failures cast it
        if cfg.dropout > 0:
            ok &= rng.random(len(depth)) >= cfg.dropout
        idx = np.flatnonzero(ok)
        r = depth[idx] + rng.normal(0.0, cfg.range_noise, len(idx))
        pts = (flat[idx] * r[:, None]).astype(np.float32)
    else:
        pts, idx = real_returns(cfg, rng, rays, flat, world, depth, ok, hits, motion)
    return (pts, idx // len(rays.azimuth)) if rings else pts


def on_roof(cfg: LidarConfig, dirs: np.ndarray) -> np.ndarray:
    """Which sensor-frame rays ``dirs`` [N, 3] meet the vehicle's own roof, ``ego_roof_drop``
    below the sensor inside the outline through ``ego_roof`` (ahead, behind, to each side):
    two half ellipses, the front one and the rear one."""
    ahead, behind, side = cfg.ego_roof
    down = dirs[:, 2] < -1e-6
    t = cfg.ego_roof_drop / np.where(down, -dirs[:, 2], 1.0)
    x, y = t * dirs[:, 0], t * dirs[:, 1]
    reach = np.where(x >= 0, x / ahead, x / behind) ** 2 + (y / side) ** 2
    return down & (reach < 1.0)


def real_returns(
    cfg: Any,
    rng: np.random.Generator,
    rays: RayBundle,
    flat: np.ndarray,
    world: np.ndarray,
    depth: np.ndarray,
    ok: np.ndarray,
    hits: list,
    motion: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """The returns of a real sensor from the nearest hits: dropouts by range, incidence and
    material, glass and recessed windows, range noise growing with range, the sweep's motion;
    float32 [N, 3] and the flat ray index of each."""
    if rays.roof is not None:
        ok &= ~rays.roof
    cos = np.abs(world[:, 2])  # the ground's: its normal is about vertical
    mat = np.full(len(depth), MAT_GROUND, np.int8)
    glass = np.zeros(len(depth), bool)
    for m, ray, t, c, g in hits:
        win = _winners(depth, ray, t)
        mat[ray[win]] = m[win]
        cos[ray[win]] = c[win]
        glass[ray[win]] = g[win]
    u = rng.random(len(depth))
    frac = np.clip(depth / cfg.max_range, 0.0, 1.0)
    lost = (
        cfg.dropout
        + cfg.dropout_far * np.where(np.isfinite(frac), frac, 1.0) ** 2
        + cfg.dropout_grazing * (1.0 - np.clip(cos, 0.0, 1.0)) ** 2
        + cfg.dark_loss * (mat == MAT_VEHICLE)
    )
    ok &= u >= lost
    # Glass: most rays pass through (lost); the rest return from frames and blinds behind it.
    ok &= ~(glass & (rng.random(len(depth)) < cfg.glass_loss))
    depth = np.where(glass, depth + rng.uniform(0.1, 0.6, len(depth)), depth)
    idx = np.flatnonzero(ok)
    std = cfg.range_noise + cfg.range_noise_per_100m * depth[idx] / 100.0
    r = depth[idx] + rng.normal(0.0, 1.0, len(idx)) * std
    pts = flat[idx] * r[:, None]
    speed, yaw_rate = motion
    if not cfg.deskewed and (speed or yaw_rate):
        # Each column fires at its time in the sweep (clockwise from the rear); the sensor has
        # moved speed*tau forward and turned yaw_rate*tau since the sweep's middle.
        ncol = len(rays.azimuth)
        col = idx % ncol
        az = rays.azimuth[col]
        tau = (np.mod(np.pi - az, 2 * np.pi) / (2 * np.pi) - 0.5) / cfg.rotation_hz
        x = pts[:, 0] - speed * tau
        y = pts[:, 1]
        a = -yaw_rate * tau
        ca, sa = np.cos(a), np.sin(a)
        pts = np.stack([ca * x - sa * y, sa * x + ca * y, pts[:, 2]], 1)
    return pts.astype(np.float32), idx
