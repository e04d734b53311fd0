"""Street detail the first benchmarks' city lacked (:class:`~pnvlad_service.synth.world.
CityDetail`): hedges along the pavements' back edge, bollards by the junctions, benches, bins and
cabinets on the pavements, shrubs on free land, and tree crowns of several clumps.

Placed after the rest of an area, from a random stream of its own, so that switching detail on
leaves every building, tree and slot of the city where it was (and a tree made without detail is
built again the same). Free land is the placer's occupancy raster.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pnvlad_service.synth.streets import Street, box_samples, normal
from pnvlad_service.synth.world import (
    KIND_BOLLARD,
    KIND_CROWN,
    KIND_FURNITURE,
    KIND_HEDGE,
    CityDetail,
    Ellipsoids,
    Road,
    Scene,
)

#: Hedge clumps: radius (m) and spacing along the hedge (m); hedges are 0.8-1.6 m tall.
HEDGE_R, HEDGE_STEP = 0.55, 0.8
#: Pavement stretches a hedge may fill, metres.
HEDGE_PIECE_M = 12.0


def place_detail(
    placer: Any, roads: list[Road], detail: CityDetail, rng: np.random.Generator
) -> None:
    """Add ``detail``'s objects through ``placer`` (the city's ``_Placer``): along both sides
    of every road (hedges, then furniture), then bollards by the junctions and shrubs on free
    land, in that order from ``rng``."""
    for road in roads:
        street = Street(road)
        for side in (1.0, -1.0):
            if detail.hedges > 0:
                _hedges(placer, street, side, detail.hedges, rng)
            if detail.furniture_per_100m > 0:
                _furniture(placer, street, side, detail.furniture_per_100m, rng)
    if detail.bollard_spacing > 0:
        _bollards(placer, detail.bollard_spacing, rng)
    if detail.shrubs_per_1000m2 > 0:
        _shrubs(placer, detail.shrubs_per_1000m2, rng)


def _hedges(
    placer: Any, street: Street, side: float, share: float, rng: np.random.Generator
) -> None:
    """Hedges on ``share`` of the pavement stretches' back edge, clumps on free land only."""
    hw = street.half_width
    for s0 in np.arange(rng.uniform(0, 6), street.total - 4, HEDGE_PIECE_M + 2):
        if rng.random() >= share:
            continue
        tall = rng.uniform(0.8, 1.6)
        offset = hw + rng.uniform(2.6, 3.2)
        for s in np.arange(s0, min(s0 + HEDGE_PIECE_M, street.total), HEDGE_STEP):
            p, t = street.at(s)
            c = p + normal(t, side) * offset
            if placer.near_junction(p, hw + 8.0) or not placer.occ.free(
                box_samples(c, np.array([0.4, 0.4]), 0.0, 0.4)
            ):
                continue
            z = placer._z(c)
            r = HEDGE_R * rng.uniform(0.85, 1.15)
            placer.b.ellipsoid(c[0], c[1], z + tall / 2, r, tall / 2 + 0.1, 0.9, KIND_HEDGE)


def _furniture(
    placer: Any, street: Street, side: float, per_100m: float, rng: np.random.Generator
) -> None:
    """Benches, bins and utility cabinets on the pavement, ``per_100m`` on average."""
    hw, b = street.half_width, placer.b
    for s in rng.uniform(0, street.total, rng.poisson(per_100m * street.total / 100.0)):
        p, t = street.at(s)
        c = p + normal(t, side) * (hw + rng.uniform(0.8, 2.0))
        if placer.near_junction(p, hw + 4.0) or not placer.clear_of_roads(c[None], 0.4):
            continue
        z = placer._z(c)
        yaw = float(np.arctan2(t[1], t[0]))
        kind = rng.integers(3)
        if kind == 0:  # a bench
            b.box(c[0], c[1], 0.9, 0.3, z, z + 0.8, yaw, KIND_FURNITURE)
        elif kind == 1:  # a bin
            b.cylinder(c[0], c[1], 0.3, z, z + 1.0, KIND_FURNITURE)
        else:  # a utility cabinet
            b.box(c[0], c[1], 0.5, 0.25, z, z + 1.3, yaw, KIND_FURNITURE)


def _bollards(placer: Any, spacing: float, rng: np.random.Generator) -> None:
    """Rows of bollards ``spacing`` apart, 12-18 m out from each junction in four directions."""
    for node in placer.nodes:
        for ang in np.arange(0, 2 * np.pi, np.pi / 2) + rng.uniform(0, np.pi / 2):
            way = np.array([np.cos(ang), np.sin(ang)])
            for k in range(int(6.0 / spacing)):
                c = node + (12.0 + k * spacing) * way
                if placer.clear_of_roads(c[None], 0.3) and placer.occ.free(c[None]):
                    z = placer._z(c)
                    placer.b.cylinder(c[0], c[1], 0.1, z, z + 0.9, KIND_BOLLARD)


def _shrubs(placer: Any, per_1000m2: float, rng: np.random.Generator) -> None:
    """Shrubs at random places of the area, where the land is free."""
    w, h = placer.cfg.size
    for c in rng.uniform([0.0, 0.0], [w, h], (int(per_1000m2 * w * h / 1e3), 2)):
        if placer.occ.free(box_samples(c, np.array([0.8, 0.8]), 0.0, 0.8)):
            z = placer._z(c)
            r = rng.uniform(0.5, 1.3)
            placer.b.ellipsoid(c[0], c[1], z + 0.6 * r, r, 0.7 * r, 0.85, KIND_HEDGE)


def clumped_crowns(scene: Scene, clumps: int, rng: np.random.Generator) -> Scene:
    """``scene`` with each tree crown (``KIND_CROWN``) replaced by ``clumps`` smaller ellipsoids
    inside its volume: an uneven crown with gaps between its masses, as real ones are."""
    el = scene.ellipsoids
    crown = el.kind == KIND_CROWN
    if clumps <= 1 or not crown.any():
        return scene
    src = el.take(crown)
    n = len(src)
    # Clump centres spread through the crown's inner 55 %, radii about 0.6 of the crown's.
    dirs = rng.normal(size=(n, clumps, 3))
    dirs /= np.maximum(np.linalg.norm(dirs, axis=2, keepdims=True), 1e-9)
    reach = rng.uniform(0.2, 0.55, (n, clumps, 1))
    centre = src.center[:, None, :] + dirs * reach * src.radii[:, None, :]
    radii = src.radii[:, None, :] * rng.uniform(0.5, 0.7, (n, clumps, 1))
    radii[..., 1] = radii[..., 0]  # the caster's ellipsoids are round about z
    density = np.repeat(src.density, clumps)
    clumped = Ellipsoids(
        centre.reshape(-1, 3),
        radii.reshape(-1, 3),
        density,
        np.full(n * clumps, KIND_CROWN, np.int8),
    )
    return Scene(scene.boxes, scene.cylinders, Ellipsoids.concat(el.take(~crown), clumped))
