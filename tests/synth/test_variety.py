"""synth.variety: each piece of street variety does what it says to the city it is given, and
nothing else (the same buildings and trees as the city without it, changed as asked)."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.presets import get_preset
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CROWN,
    KIND_TRUNK,
    CityDetail,
    StreetVariety,
    WorldConfig,
)

#: Every piece off: each test switches on the one it checks.
NONE = dict(
    height_scale=(1.0, 1.0),
    roofs=0.0,
    setback_jitter_m=0.0,
    narrow_share=0.0,
    vacant_lots=0.0,
    tree_scale=(1.0, 1.0),
    avenues=0.0,
)


def _world(district: str = "oldtown", **variety: object):
    v = None if variety.get("off") else StreetVariety(**{**NONE, **variety})
    cfg = WorldConfig(district=district, size=(320.0, 260.0), detail=CityDetail(variety=v))
    return generate_world(cfg, seed=4)


@pytest.fixture(scope="module")
def plain():
    return _world(off=True)


def _height(world, kind: int = KIND_BUILDING) -> np.ndarray:
    b = world.scene.boxes
    sel = b.kind == kind
    return b.z[sel, 1] - world.ground.height(b.center[sel, 0], b.center[sel, 1])


def test_heights_are_scaled_building_by_building_and_kept_above_the_floor(plain) -> None:
    low = _world(height_scale=(0.5, 0.5))
    before = _height(plain)
    np.testing.assert_allclose(_height(low), np.maximum(before * 0.5, 3.5), atol=1e-9)
    # A range draws a factor per building: neighbours' heights no longer repeat the templates.
    spread = _world(height_scale=(0.35, 1.1))
    ratio = _height(spread) / before
    assert ratio.min() >= 0.35 - 1e-9 and ratio.max() <= 1.1 + 1e-9
    assert len(np.unique(np.round(ratio, 3))) > 0.9 * len(ratio)


def test_trees_grow_about_their_foot(plain) -> None:
    big = _world(tree_scale=(2.0, 2.0))
    cp, cb = plain.scene.cylinders, big.scene.cylinders
    t0, t1 = cp.kind == KIND_TRUNK, cb.kind == KIND_TRUNK
    np.testing.assert_array_equal(cp.center[t0], cb.center[t1])
    foot = cp.z[t0, 0] + 0.3
    np.testing.assert_allclose(cb.z[t1, 1] - foot, 2.0 * (cp.z[t0, 1] - foot))
    np.testing.assert_allclose(cb.radius[t1], cp.radius[t0] * np.sqrt(2.0))
    # Crowns twice as large in volume terms (width and height about a shape factor).
    ep, eb = plain.scene.ellipsoids, big.scene.ellipsoids
    r0 = ep.radii[ep.kind == KIND_CROWN]
    r1 = eb.radii[eb.kind == KIND_CROWN]
    np.testing.assert_allclose(r1[:, 0] * r1[:, 2], 4.0 * r0[:, 0] * r0[:, 2])


def test_vacant_lots_take_the_buildings_away_and_avenues_add_trees(plain) -> None:
    empty = _world(vacant_lots=1.0)
    assert (plain.scene.boxes.kind == KIND_BUILDING).sum() > 20
    assert (empty.scene.boxes.kind == KIND_BUILDING).sum() == 0
    trees = _world(avenues=1.0).scene.cylinders.kind == KIND_TRUNK
    assert trees.sum() > (plain.scene.cylinders.kind == KIND_TRUNK).sum() + 20


def test_setbacks_move_buildings_away_from_their_street(plain) -> None:
    from scipy.spatial import cKDTree

    roads = cKDTree(np.concatenate([r.points for r in plain.roads]))
    moved = _world(setback_jitter_m=4.0)
    b0, b1 = plain.scene.boxes, moved.scene.boxes
    s0, s1 = b0.kind == KIND_BUILDING, b1.kind == KIND_BUILDING
    shift = np.linalg.norm(b1.center[s1] - b0.center[s0], axis=1)
    assert shift.max() <= 4.0 + 1e-9 and np.median(shift) > 1.0
    gain = roads.query(b1.center[s1])[0] - roads.query(b0.center[s0])[0]
    assert np.median(gain) > 1.0 and (gain > -0.5).mean() > 0.95


def test_without_variety_a_preset_dumps_as_before() -> None:
    assert "variety" not in get_preset("demo").model_dump()["city"]
    assert "partial_runs" not in get_preset("demo").model_dump()
    oxford = get_preset("oxford").model_dump()
    assert oxford["city"]["variety"] == StreetVariety().model_dump()
    assert type(get_preset("oxford")).model_validate(oxford) == get_preset("oxford")


@pytest.mark.parametrize(
    "bad", [{"height_scale": (1.2, 0.5)}, {"tree_scale": (0.0, 1.0)}, {"roofs": 1.5}]
)
def test_a_bad_variety_names_its_field(bad: dict) -> None:
    with pytest.raises(ValueError, match=next(iter(bad))):
        StreetVariety(**bad)
