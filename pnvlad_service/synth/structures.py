"""Ground cover and built structure the first benchmarks' city lacked
(:class:`~pnvlad_service.synth.world.CityDetail`): grass verges by the kerb and lawns on the free
land near the streets, bridges over the streets, and building fronts with piers, recesses and
balconies.

Placed after the rest of the detail, from the same stream of its own (so that a tree made
without these is built again the same). Grass is thin boxes over the ground (``KIND_GRASS``)
that a real sensor's rays reach into; the rest are boxes of their own kinds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pnvlad_service.synth.streets import Street, box_samples, normal
from pnvlad_service.synth.world import (
    KIND_BRIDGE,
    KIND_BUILDING,
    KIND_FACADE,
    KIND_GRASS,
    CityDetail,
    Road,
)

#: Grass pieces: metres along a verge, the side of a lawn tile, how far lawns reach from a street.
VERGE_PIECE_M, LAWN_TILE_M, LAWN_REACH_M = 3.0, 5.0, 22.0
#: Storey height (m) for balconies, and the most balcony floors a front gets.
STOREY_M, MAX_BALCONY_FLOORS = 3.2, 7


def place_structures(
    placer: Any, roads: list[Road], detail: CityDetail, rng: np.random.Generator
) -> None:
    """Add ``detail``'s ground cover and structures through ``placer`` (the city's ``_Placer``):
    verges along every road side, then lawns, bridges and building fronts, in that order."""
    for i, road in enumerate(roads):
        street = Street(road)
        for side in (1.0, -1.0):
            if detail.grass_verges > 0:
                _verges(placer, street, i, side, detail.grass_verges, rng)
            if detail.lawns > 0:
                _lawns(placer, street, side, detail.lawns, rng)
    if detail.bridges_per_km > 0:
        for road in roads:
            _bridges(placer, Street(road), detail.bridges_per_km, rng)
    if detail.facade_bays > 0 or detail.balconies > 0:
        _fronts(placer, detail, rng)


def _grass(placer: Any, c: np.ndarray, half: np.ndarray, yaw: float, tall: float) -> None:
    """A grass box over the ground of an oriented rectangle: from under its lowest corner to
    ``tall`` over its highest."""
    corners = box_samples(c, half, yaw, step=float(half.max()))
    h = placer.ground.height(corners[:, 0], corners[:, 1])
    placer.b.box(c[0], c[1], half[0], half[1], h.min() - 0.05, h.max() + tall, yaw, KIND_GRASS)


def _verges(
    placer: Any, street: Street, road: int, side: float, share: float, rng: np.random.Generator
) -> None:
    """Grass between the kerb and the footway on ``share`` of the 12 m stretches."""
    hw = street.half_width
    for s0 in np.arange(rng.uniform(0, 4), street.total - VERGE_PIECE_M, 12.0):
        if rng.random() >= share:
            continue
        width, tall = rng.uniform(1.2, 2.0), rng.uniform(0.08, 0.2)
        for s in np.arange(s0, min(s0 + 12.0, street.total) - VERGE_PIECE_M / 2, VERGE_PIECE_M):
            p, t = street.at(s + VERGE_PIECE_M / 2)
            c = p + normal(t, side) * (hw + 0.3 + width / 2)
            half = np.array([VERGE_PIECE_M / 2, width / 2])
            yaw = float(np.arctan2(t[1], t[0]))
            if placer.near_junction(p, hw + 8.0) or not placer.clear_of_roads(
                box_samples(c, half, yaw, 1.0), 0.2, own=road
            ):
                continue
            _grass(placer, c, half, yaw, tall)


def _lawns(
    placer: Any, street: Street, side: float, share: float, rng: np.random.Generator
) -> None:
    """Lawn tiles on ``share`` of the free land within ``LAWN_REACH_M`` of the street."""
    hw, half = street.half_width, np.full(2, LAWN_TILE_M / 2)
    offsets = np.arange(hw + 3.5 + LAWN_TILE_M / 2, LAWN_REACH_M, LAWN_TILE_M)
    for s in np.arange(LAWN_TILE_M / 2, street.total, LAWN_TILE_M):
        p, t = street.at(s)
        yaw = float(np.arctan2(t[1], t[0]))
        for off in offsets:
            if rng.random() >= share:
                continue
            c = p + normal(t, side) * off
            tile = box_samples(c, half, yaw, 1.25)
            if placer.occ.free(tile) and placer.clear_of_roads(tile, 2.0):
                _grass(placer, c, half, yaw, rng.uniform(0.05, 0.15))


def _bridges(placer: Any, street: Street, per_km: float, rng: np.random.Generator) -> None:
    """Bridges across the street: a deck 5-6.5 m over the road on two piers beside it, where
    the piers' land is free and no junction is near."""
    hw = street.half_width
    for s in rng.uniform(
        30.0, max(street.total - 30.0, 30.0), rng.poisson(per_km * street.total / 1e3)
    ):
        p, t = street.at(s)
        n = normal(t, 1.0)
        along = float(np.arctan2(n[1], n[0]))  # the deck spans the street
        deck_w, clear = rng.uniform(3.0, 6.0), rng.uniform(5.0, 6.5)
        thick, reach = rng.uniform(0.9, 1.4), hw + rng.uniform(6.0, 9.0)
        piers = [p + n * k * (hw + 3.5) for k in (1.0, -1.0)]
        pier_half = np.array([0.45, deck_w * 0.8])
        if placer.near_junction(p, hw + 25.0) or not all(
            placer.occ.free(box_samples(q, pier_half, along, 0.5)) for q in piers
        ):
            continue
        z = placer._z(p)
        placer.b.box(p[0], p[1], reach, deck_w, z + clear, z + clear + thick, along, KIND_BRIDGE)
        for q in piers:
            placer.occ.mark(box_samples(q, pier_half, along, 0.5))
            zq = placer._z(q)
            placer.b.box(q[0], q[1], *pier_half, zq - 0.5, z + clear, along, KIND_BRIDGE)


def _fronts(placer: Any, detail: CityDetail, rng: np.random.Generator) -> None:
    """Piers (the front between them recessed) and balconies on the street face of a share
    of the buildings placed so far."""
    buildings = [b for b in placer.b.boxes if int(b[7]) == KIND_BUILDING]
    for cx, cy, hx, hy, z0, z1, yaw, _ in buildings:
        bays = rng.random() < detail.facade_bays
        balconies = rng.random() < detail.balconies
        if not (bays or balconies):
            continue
        c = np.array([cx, cy])
        ex, ey = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
        _, k = placer.tree.query(c)
        face = 1.0 if float((placer.tree.data[k] - c) @ ey) > 0 else -1.0
        bay = rng.uniform(3.5, 6.0)
        xs = np.arange(-hx + bay / 2, hx - bay / 4, bay)
        if bays:
            depth, width = rng.uniform(0.3, 0.6), rng.uniform(0.4, 0.8)
            for x in np.r_[-hx + width / 2, xs + bay / 2]:
                if abs(x) <= hx - width / 2 + 1e-9:
                    q = c + ex * x + ey * face * (hy + depth / 2)
                    placer.b.box(q[0], q[1], width / 2, depth / 2, z0, z1, yaw, KIND_FACADE)
        if balconies:
            floors = min(int((z1 - z0 - 0.5) / STOREY_M) - 1, MAX_BALCONY_FLOORS)
            for x in xs[::2]:
                q = c + ex * x + ey * face * (hy + 0.6)
                for f in range(1, floors + 1):
                    zb = z0 + 0.5 + f * STOREY_M
                    placer.b.box(q[0], q[1], 1.2, 0.6, zb - 0.15, zb + 1.0, yaw, KIND_FACADE)
