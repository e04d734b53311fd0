"""synth.city: the same seed builds the same city, another seed another one."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CAR,
    KIND_FENCE,
    KIND_WALL,
    WorldConfig,
)


def _arrays(world) -> list[np.ndarray]:
    sc = world.scene
    return [
        world.nodes,
        *(r.points for r in world.roads),
        sc.boxes.center,
        sc.boxes.half,
        sc.boxes.z,
        sc.boxes.yaw,
        sc.boxes.kind,
        sc.cylinders.center,
        sc.cylinders.radius,
        sc.cylinders.z,
        sc.cylinders.kind,
        sc.ellipsoids.center,
        sc.ellipsoids.radii,
        sc.ellipsoids.density,
        sc.ellipsoids.kind,
        world.parking.center,
        world.parking.half,
        world.parking.z,
        world.parking.yaw,
    ]


@pytest.mark.parametrize("district", ["business", "residential", "campus"])
def test_same_seed_same_city_other_seed_other_city(district: str) -> None:
    cfg = WorldConfig(district=district, size=(300.0, 250.0))
    a, again, b = (generate_world(cfg, seed=s) for s in (3, 3, 4))
    assert all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(again), strict=True))
    assert not np.array_equal(a.nodes, b.nodes)
    assert len(a.scene.boxes) != len(b.scene.boxes) or not np.allclose(
        a.scene.boxes.center, b.scene.boxes.center
    )


def test_every_district_has_its_own_objects_and_an_unknown_one_is_refused() -> None:
    worlds = {
        d: generate_world(WorldConfig(district=d, size=(400.0, 300.0)), seed=1)
        for d in ("business", "residential", "campus")
    }
    kinds = {d: set(w.scene.boxes.kind.tolist()) for d, w in worlds.items()}
    assert all(KIND_BUILDING in k for k in kinds.values())
    assert KIND_FENCE in kinds["residential"] and KIND_FENCE not in kinds["business"]
    assert KIND_WALL in kinds["campus"] and KIND_WALL not in kinds["business"]
    for w in worlds.values():  # parked cars are slots each run fills, not static scene
        assert len(w.parking) > 0 and set(w.parking.kind.tolist()) == {KIND_CAR}
        assert KIND_CAR not in set(w.scene.boxes.kind.tolist())
    with pytest.raises(InputError, match="unknown district 'harbour'"):
        generate_world(WorldConfig(district="harbour"))
