"""Streets whose small pieces differ as real ones do (:class:`StreetVariety`).

The first city builds each district from 3-4 building templates (±5 %), one setback per street
side, buildings nearly touching, flat roofs and trees of one size range on a regular spacing:
at the PointNetVLAD paper's submap size (20 m of trajectory, 30-40 m of street) one piece of
street looks much like the next. This pass, run on the placed city before the street detail,
varies what 30-40 m of street holds
(:class:`~pnvlad_service.synth.world.StreetVariety`):

- **building heights**: each building's height above the ground times a factor drawn
  log-uniformly from ``height_scale``, half of it shared by its neighbourhood (a smooth random
  field over 80-250 m: quarters of low and of tall buildings) and half its own;
- **roofs**: on ``roofs`` of the buildings a pitched roof (stepped boxes narrowing to the
  ridge), a set-back top storey, or chimneys and roof plant (boxes of the fronts' kind, so
  that no front is laid on them);
- **setbacks**: each building moved back from its street by up to ``setback_jitter_m``;
- **gaps**: ``narrow_share`` of the buildings cut shorter along the street (passages, alleys),
  ``vacant_lots`` of them taken away and the lot left open: a pocket park of trees, or a yard
  or car park behind a low wall with a shed;
- **trees**: every tree scaled by a factor drawn log-uniformly from ``tree_scale`` (young
  trees and old giants; half the factor shared by the neighbourhood, as a street's trees are of
  one planting), crowns from slender to broad, and on ``avenues`` of the street sides a row of
  trees 7-11 m apart.

Everything is drawn from a random stream of its own: the city without variety is built as
before, and the street detail (hedges, lawns, fronts) placed after it follows the varied
buildings and fills the open lots.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pnvlad_service.synth.streets import Street, box_samples, normal
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CROWN,
    KIND_FACADE,
    KIND_FURNITURE,
    KIND_TRUNK,
    KIND_WALL,
    Road,
    StreetVariety,
)

#: Lowest building (m above the ground) a height factor may leave.
MIN_BUILDING_M = 3.5


def _field(rng: np.random.Generator, k: int = 4) -> Any:
    """A smooth random field over the plane in [-1, 1] (waves 80-250 m long)."""
    lam = rng.uniform(80.0, 250.0, k)
    ang = rng.uniform(0, 2 * np.pi, k)
    kv = (2 * np.pi / lam)[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    ph = rng.uniform(0, 2 * np.pi, k)

    def f(xy: np.ndarray) -> np.ndarray:
        return np.sin(np.atleast_2d(xy) @ kv.T + ph).sum(1) / np.sqrt(k / 2) / 1.5

    return f


def _log_factor(
    rng: np.random.Generator, scale: tuple[float, float], shared: np.ndarray
) -> np.ndarray:
    """Factors in ``scale``, log-uniform: half from ``shared`` (in [-1, 1]), half own."""
    lo, hi = np.log(scale[0]), np.log(max(scale[1], scale[0]))
    u = 0.5 * (np.clip(shared, -1, 1) + 1) * 0.5 + 0.5 * rng.random(len(shared))
    return np.exp(lo + u * (hi - lo))


def vary_city(placer: Any, roads: list[Road], v: StreetVariety, rng: np.random.Generator) -> None:
    """Apply ``v`` to the city ``placer`` has placed (its builder's lists, its occupancy)."""
    _avenues(placer, roads, v.avenues, rng)
    _trees(placer, v.tree_scale, rng)
    _buildings(placer, v, rng)


def _avenues(placer: Any, roads: list[Road], share: float, rng: np.random.Generator) -> None:
    """Rows of trees 7-11 m apart on ``share`` of the street sides, where the pavement is free."""
    for road in roads:
        street = Street(road)
        for side in (1.0, -1.0):
            if rng.random() >= share:
                continue
            step = rng.uniform(7.0, 11.0)
            back = street.half_width + rng.uniform(1.0, 2.2)
            for s0 in np.arange(rng.uniform(2, 8), street.total - 2, step):
                p, t = street.at(s0)
                if placer.near_junction(p, street.half_width + 8.0):
                    continue
                c = p + normal(t, side) * back
                pad = box_samples(c, np.array([0.4, 0.4]), 0.0, 0.4)
                if placer.clear_of_roads(c[None], 0.5) and placer.occ.free(pad):
                    placer.b.tree(rng, placer.ground, c[0], c[1], placer.style.crown_radius)


def _trees(placer: Any, scale: tuple[float, float], rng: np.random.Generator) -> None:
    """Every tree (a trunk and its crown, placed as a pair) scaled about its foot, its crown
    made slender or broad."""
    cyl, ell = placer.b.cyl, placer.b.ell
    trunks = [i for i, c in enumerate(cyl) if int(c[5]) == KIND_TRUNK]
    crowns = {(e[0], e[1]): i for i, e in enumerate(ell) if int(e[6]) == KIND_CROWN}
    if not trunks:
        return
    xy = np.array([[cyl[i][0], cyl[i][1]] for i in trunks])
    f = _log_factor(rng, scale, _field(rng)(xy))
    shape = rng.uniform(0.75, 1.45, len(trunks))  # crown height over width
    for i, fi, sh in zip(trunks, f, shape, strict=True):
        cx, cy, r, z0, z1, kind = cyl[i]
        foot = z0 + 0.3
        j = crowns.get((cx, cy))
        cyl[i] = (cx, cy, r * np.sqrt(fi), z0, foot + (z1 - foot) * fi, kind)
        if j is None:
            continue
        ex, ey, ez, rx, rz, dens, ekind = ell[j]
        rx2 = rx * fi / np.sqrt(sh)
        rz2 = rz * fi * np.sqrt(sh)
        ell[j] = (ex, ey, foot + (ez - foot) * fi + (rz2 - rz * fi) * 0.9, rx2, rz2, dens, ekind)


def _buildings(placer: Any, v: StreetVariety, rng: np.random.Generator) -> None:
    """Heights, setbacks, gaps, open lots and roofs of the buildings placed so far."""
    boxes = placer.b.boxes
    idx = [i for i, b in enumerate(boxes) if int(b[7]) == KIND_BUILDING]
    if not idx:
        return
    xy = np.array([[boxes[i][0], boxes[i][1]] for i in idx])
    height = _log_factor(rng, v.height_scale, _field(rng)(xy))
    gone: list[int] = []
    for i, h in zip(idx, height, strict=True):
        cx, cy, hx, hy, z0, z1, yaw, kind = boxes[i]
        c = np.array([cx, cy])
        ex, ey = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        _, k = placer.tree.query(c)
        face = 1.0 if float((placer.tree.data[k] - c) @ ey) > 0 else -1.0
        ground = placer._z(c)
        draw = rng.random(4)
        if draw[0] < v.vacant_lots:
            gone.append(i)
            _open_lot(placer, c, hx, hy, yaw, face, rng)
            continue
        if draw[1] < v.narrow_share:  # cut from one end: a passage beside it
            cut = hx * rng.uniform(0.2, 0.5)
            c = c + ex * cut * (1 if draw[2] < 0.5 else -1)
            hx -= cut
        c = c - ey * face * rng.uniform(0.0, v.setback_jitter_m)
        top = ground + max((z1 - ground) * h, MIN_BUILDING_M)
        boxes[i] = (c[0], c[1], hx, hy, z0, top, yaw, kind)
        if draw[3] < v.roofs:
            _roof(placer, c, hx, hy, top, yaw, face, rng)
    for i in sorted(gone, reverse=True):
        del boxes[i]


def _open_lot(
    placer: Any,
    c: np.ndarray,
    hx: float,
    hy: float,
    yaw: float,
    face: float,
    rng: np.random.Generator,
) -> None:
    """The land of a building taken away: freed for lawns and shrubs, then a pocket park (a few
    trees) or a yard behind a low wall with a shed."""
    ex, ey = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    r, col, ok = placer.occ.cells(box_samples(c, np.array([hx, hy]), yaw, step=1.0))
    placer.occ.grid[r[ok], col[ok]] = False
    if rng.random() < 0.5:
        for _ in range(int(rng.integers(1, 5))):
            q = c + ex * rng.uniform(-hx, hx) * 0.8 + ey * rng.uniform(-hy, hy) * 0.8
            placer.b.tree(rng, placer.ground, q[0], q[1], placer.style.crown_radius)
        return
    front = c + ey * face * hy
    z = placer._z(front)
    placer.b.box(front[0], front[1], hx, 0.15, z - 0.2, z + rng.uniform(0.8, 1.8), yaw, KIND_WALL)
    if rng.random() < 0.6:
        s = c - ey * face * hy * 0.5 + ex * rng.uniform(-0.5, 0.5) * hx
        zs = placer._z(s)
        w, d = rng.uniform(2.0, 5.0), rng.uniform(2.0, 4.0)
        top = zs + rng.uniform(2.4, 3.6)
        placer.b.box(s[0], s[1], w / 2, d / 2, zs - 0.3, top, yaw, KIND_FACADE)


def _roof(
    placer: Any,
    c: np.ndarray,
    hx: float,
    hy: float,
    top: float,
    yaw: float,
    face: float,
    rng: np.random.Generator,
) -> None:
    """A pitched roof (3-4 steps narrowing to a ridge along the street), a set-back top storey,
    or chimneys and plant."""
    ex, ey = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    kind = rng.random()
    if kind < 0.45:
        steps = int(rng.integers(3, 5))
        rise = hy * np.tan(np.radians(rng.uniform(25.0, 45.0))) / steps
        rise = min(rise, 2.0)
        for k in range(steps):
            w = hy * (1.0 - (k + 1) / (steps + 1))
            z = top + k * rise
            placer.b.box(c[0], c[1], hx, w, z, z + rise, yaw, KIND_FACADE)
    elif kind < 0.75:
        sx, sy = hx * rng.uniform(0.5, 0.9), hy * rng.uniform(0.45, 0.75)
        q = c - ey * face * (hy - sy) + ex * rng.uniform(-1, 1) * (hx - sx)
        placer.b.box(q[0], q[1], sx, sy, top, top + rng.uniform(2.8, 3.4), yaw, KIND_FACADE)
    else:
        for _ in range(int(rng.integers(1, 4))):
            q = c + ex * rng.uniform(-0.8, 0.8) * hx + ey * rng.uniform(-0.8, 0.8) * hy
            a, b = rng.uniform(0.3, 1.5, 2)
            placer.b.box(q[0], q[1], a, b, top, top + rng.uniform(1.0, 3.0), yaw, KIND_FURNITURE)
