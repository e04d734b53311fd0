"""A vectorised ray-cast spinning LiDAR (Velodyne HDL-64E-like by default).

One scan is ``beams × columns`` rays from one origin. A point is where the first surface along
its ray is (real occlusion), found analytically for boxes, vertical cylinders, ellipsoids and a
height-field ground. No per-ray Python loop: each primitive within range is paired with the
azimuth columns and the beams its bounding volume can cover, and all pairs are intersected in
one numpy pass, then reduced to the nearest hit per ray with ``np.minimum.at``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, Field

from pnvlad_service.synth.world import Boxes, Cylinders, Ellipsoids, Ground, Scene


class LidarConfig(BaseModel):
    """The spinning sensor. Defaults: a Velodyne HDL-64E (64 beams from +2° to -24.8°, one
    turn every 0.1 s, about 100 m range, 2 cm range noise, a few % dropouts)."""

    beams: int = Field(64, ge=1, description="laser channels")
    elevation_max_deg: float = Field(2.0, description="top beam elevation, degrees")
    elevation_min_deg: float = Field(-24.8, description="bottom beam elevation, degrees")
    columns: int = Field(1800, ge=8, description="azimuth steps per turn (0.2°)")
    max_range: float = Field(100.0, gt=0, description="metres")
    min_range: float = Field(2.5, ge=0, description="metres; closer returns are dropped")
    range_noise: float = Field(0.02, ge=0, description="range noise std, metres")
    dropout: float = Field(0.05, ge=0, lt=1, description="share of returns lost")
    mount_height: float = Field(1.9, description="sensor height above the ground, metres")


@dataclass
class RayBundle:
    """Unit ray directions in the sensor frame, float64 [beams, columns, 3]; elevation
    float64 [beams] (radians, descending), azimuth float64 [columns] (radians, from +x)."""

    dirs: np.ndarray
    elevation: np.ndarray
    azimuth: np.ndarray


def ray_bundle(cfg: LidarConfig) -> RayBundle:
    """The sensor's rays, beam-major."""
    el = np.deg2rad(np.linspace(cfg.elevation_max_deg, cfg.elevation_min_deg, cfg.beams))
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
    return RayBundle(d, el, az)


def _pairs(
    center: np.ndarray,
    radius: np.ndarray,
    zlo: np.ndarray,
    zhi: np.ndarray,
    origin: np.ndarray,
    yaw: float,
    rays: RayBundle,
    max_range: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (primitive, ray) pairs: primitive index int64 [M], flat ray index int64 [M].

    ``center`` [P,2], ``radius`` [P] is each primitive's bounding circle, ``zlo``/``zhi`` [P]
    its vertical extent; only rays whose azimuth and elevation can reach it are kept.
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
    c0 = np.floor((theta - half) / dcol).astype(np.int64) - 1
    c1 = np.ceil((theta + half) / dcol).astype(np.int64) + 1
    ncols = np.minimum(c1 - c0 + 1, ncol)
    # Beam range from the elevation span of the bounding cylinder.
    near = np.maximum(dist - radius, 0.05)
    far = dist + radius
    e_hi = np.maximum(np.arctan2(zhi - origin[2], near), np.arctan2(zhi - origin[2], far))
    e_lo = np.minimum(np.arctan2(zlo - origin[2], near), np.arctan2(zlo - origin[2], far))
    e_hi = np.where(inside, np.pi / 2, e_hi)
    e_lo = np.where(inside & (zlo < origin[2]), -np.pi / 2, e_lo)
    el = rays.elevation  # descending
    b0 = np.searchsorted(-el, -e_hi - 1e-3, side="left")
    b1 = np.searchsorted(-el, -e_lo + 1e-3, side="right")
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


def _hit_boxes(b: Boxes, prim: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Entry distance of rays ``d`` [M,3] from ``o`` into boxes ``prim`` [M]; inf if none."""
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
        tn = np.maximum(
            np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2)), np.minimum(tz1, tz2)
        )
        tf = np.minimum(
            np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2)), np.maximum(tz1, tz2)
        )
    hit = (tn <= tf) & (tn > 0)
    return np.where(hit, tn, np.inf)


def _hit_cylinders(cy: Cylinders, prim: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Distance to the side of vertical cylinders; inf if missed."""
    rx = o[0] - cy.center[prim, 0]
    ry = o[1] - cy.center[prim, 1]
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    bb = d[:, 0] * rx + d[:, 1] * ry
    cc = rx * rx + ry * ry - cy.radius[prim] ** 2
    disc = bb * bb - a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-bb - np.sqrt(disc)) / a
    z = o[2] + t * d[:, 2]
    hit = (disc > 0) & (t > 0) & (z >= cy.z[prim, 0]) & (z <= cy.z[prim, 1])
    return np.where(hit, t, np.inf)


def _hit_ellipsoids(
    e: Ellipsoids, prim: np.ndarray, o: np.ndarray, d: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Distance to ellipsoids; a hit survives with the crown's density (foliage gaps)."""
    r = e.radii[prim]
    oc = (o[None, :] - e.center[prim]) / r
    dd = d / r
    a = (dd * dd).sum(1)
    bb = (oc * dd).sum(1)
    cc = (oc * oc).sum(1) - 1.0
    disc = bb * bb - a * cc
    with np.errstate(invalid="ignore"):
        t = (-bb - np.sqrt(disc)) / a
    hit = (disc > 0) & (t > 0) & (rng.random(len(prim)) < e.density[prim])
    return np.where(hit, t, np.inf)


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


def cast_scan(
    scene: Scene,
    ground: Ground,
    position: np.ndarray,
    yaw: float,
    cfg: LidarConfig,
    rng: np.random.Generator,
    rays: RayBundle | None = None,
) -> np.ndarray:
    """Simulate one full turn of the sensor at ``position`` (local metres, float64 [3]) with
    heading ``yaw`` (radians from east, sensor level).

    Returns the points in the *sensor* frame (x forward, y left, z up), float32 [N,3], metres,
    with range noise and dropouts applied and rays without a return in range removed.
    """
    rays = rays or ray_bundle(cfg)
    c, s = np.cos(yaw), np.sin(yaw)
    flat = rays.dirs.reshape(-1, 3)
    world = np.empty_like(flat)
    world[:, 0] = c * flat[:, 0] - s * flat[:, 1]
    world[:, 1] = s * flat[:, 0] + c * flat[:, 1]
    world[:, 2] = flat[:, 2]
    o = np.asarray(position, dtype=np.float64)
    depth = _hit_ground(ground, o, world, cfg.max_range)

    bx = scene.boxes
    if len(bx):
        rad = np.hypot(bx.half[:, 0], bx.half[:, 1])
        prim, ray = _pairs(bx.center, rad, bx.z[:, 0], bx.z[:, 1], o, yaw, rays, cfg.max_range)
        if len(prim):
            np.minimum.at(depth, ray, _hit_boxes(bx, prim, o, world[ray]))
    cy = scene.cylinders
    if len(cy):
        prim, ray = _pairs(
            cy.center, cy.radius, cy.z[:, 0], cy.z[:, 1], o, yaw, rays, cfg.max_range
        )
        if len(prim):
            np.minimum.at(depth, ray, _hit_cylinders(cy, prim, o, world[ray]))
    el = scene.ellipsoids
    if len(el):
        zc, rz = el.center[:, 2], el.radii[:, 2]
        prim, ray = _pairs(
            el.center[:, :2], el.radii[:, 0], zc - rz, zc + rz, o, yaw, rays, cfg.max_range
        )
        if len(prim):
            np.minimum.at(depth, ray, _hit_ellipsoids(el, prim, o, world[ray], rng))

    ok = np.isfinite(depth) & (depth <= cfg.max_range) & (depth >= cfg.min_range)
    if cfg.dropout > 0:
        ok &= rng.random(len(depth)) >= cfg.dropout
    idx = np.flatnonzero(ok)
    r = depth[idx] + rng.normal(0.0, cfg.range_noise, len(idx))
    return (flat[idx] * r[:, None]).astype(np.float32)
