"""Street detail, vehicle shapes and the vehicle kept clear of other cars (issue #37)."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.generate import REAL_CITY, get_preset
from pnvlad_service.synth.lidar import LidarConfig
from pnvlad_service.synth.runs import EGO_HALF, RunConditions, SimulatedDrive, make_route
from pnvlad_service.synth.vehicles import CLEARANCE_M, draw_shapes, vehicle_boxes
from pnvlad_service.synth.world import (
    KIND_BOLLARD,
    KIND_CAR,
    KIND_CROWN,
    KIND_FURNITURE,
    KIND_HEDGE,
    CityDetail,
    WorldConfig,
)

SMALL = {"district": "residential", "size": (400.0, 300.0)}


def test_detail_adds_to_the_city_and_moves_nothing_else() -> None:
    # the same hills (they move the buildings' feet), none of the rest
    plain = generate_world(WorldConfig(**SMALL, detail=CityDetail(hills=REAL_CITY.hills)), seed=4)
    rich = generate_world(WorldConfig(**SMALL, detail=REAL_CITY), seed=4)
    pb, rb = plain.scene.boxes, rich.scene.boxes
    # every box and cylinder of the plain city comes first, unchanged
    np.testing.assert_array_equal(rb.center[: len(pb)], pb.center)
    np.testing.assert_array_equal(rb.z[: len(pb)], pb.z)
    pc, rc = plain.scene.cylinders, rich.scene.cylinders
    np.testing.assert_array_equal(rc.center[: len(pc)], pc.center)
    np.testing.assert_array_equal(plain.parking.center, rich.parking.center)
    kinds = set(rb.kind.tolist()) | set(rc.kind.tolist()) | set(rich.scene.ellipsoids.kind.tolist())
    assert {KIND_HEDGE, KIND_BOLLARD, KIND_FURNITURE} <= kinds
    # crowns in clumps: four for each smooth crown, inside it
    n_crowns = int((plain.scene.ellipsoids.kind == KIND_CROWN).sum())
    clumps = rich.scene.ellipsoids.take(rich.scene.ellipsoids.kind == KIND_CROWN)
    assert len(clumps) == REAL_CITY.crown_clumps * n_crowns
    big = plain.scene.ellipsoids.take(plain.scene.ellipsoids.kind == KIND_CROWN)
    owner = np.repeat(np.arange(n_crowns), REAL_CITY.crown_clumps)
    off = np.abs(clumps.center - big.center[owner]) / big.radii[owner]
    assert (off <= 0.55 + 1e-9).all() and (clumps.radii <= 0.7 * big.radii[owner] + 1e-9).all()
    # the same seed and detail build the same city
    again = generate_world(WorldConfig(**SMALL, detail=REAL_CITY), seed=4)
    np.testing.assert_array_equal(again.scene.ellipsoids.center, rich.scene.ellipsoids.center)


def test_vehicle_boxes_body_and_cabin() -> None:
    rng = np.random.default_rng(0)
    shapes = draw_shapes(rng, 200)
    centre = rng.uniform(-50, 50, (200, 2))
    yaw = rng.uniform(-np.pi, np.pi, 200)
    boxes = vehicle_boxes(centre, yaw, np.zeros(200), shapes)
    cars = shapes.cabin > 0
    assert len(boxes) == 200 + int(cars.sum()) and (boxes.kind == KIND_CAR).all()
    assert 0 < cars.sum() < 200  # vans are one box
    body, cabin = boxes.take(np.arange(200)), boxes.take(np.arange(200, len(boxes)))
    np.testing.assert_allclose(body.z[:, 0], CLEARANCE_M)
    np.testing.assert_allclose(cabin.z[:, 1], shapes.height[cars])
    np.testing.assert_allclose(cabin.z[:, 0], body.z[cars, 1])
    # each cabin lies within its body's footprint
    rel = cabin.center - body.center[cars]
    fwd = np.stack([np.cos(yaw[cars]), np.sin(yaw[cars])], 1)
    along = np.abs((rel * fwd).sum(1)) + cabin.half[:, 0]
    assert (along <= body.half[cars, 0] + 1e-9).all()
    assert (cabin.half[:, 1] < body.half[cars, 1]).all()


def _inside(boxes, xy: np.ndarray, grow: tuple[float, float]) -> np.ndarray:
    """Which boxes (inflated by ``grow``) contain the point ``xy``: computed here, apart."""
    rel = xy - boxes.center
    c, s = np.cos(boxes.yaw), np.sin(boxes.yaw)
    u = np.abs(c * rel[:, 0] + s * rel[:, 1])
    v = np.abs(-s * rel[:, 0] + c * rel[:, 1])
    return (u < boxes.half[:, 0] + grow[0]) & (v < boxes.half[:, 1] + grow[1])


@pytest.mark.parametrize("clearance", [None, 0.3])
def test_the_vehicle_keeps_clear_of_parked_and_moving_cars(clearance: float | None) -> None:
    world = generate_world(WorldConfig(district="business", size=(500.0, 400.0)), seed=2)
    route = make_route(world, 600.0, seed=2)
    cond = RunConditions(ego_clearance=clearance, parked_share=(1.0, 1.0), traffic_per_km=150)
    hits = 0
    for seed in range(3):
        d = SimulatedDrive(
            world, route, "r", seed=seed, start_us=0, conditions=cond,
            lidar=LidarConfig(beams=8, columns=90), scan_spacing=4.0,
        )  # fmt: skip
        for i in range(len(d)):
            scene = d.scene.scene_at(float(d.times[i]), d.true_xy[i], 60.0)
            cars = scene.boxes.take(scene.boxes.kind == KIND_CAR)
            hits += int(_inside(cars, d.true_xy[i], EGO_HALF).any())
    if clearance is None:
        assert hits > 0  # the first benchmarks' lane ran through cars: the bug this fixes
    else:
        assert hits == 0


def test_the_benchmark_mixes_sensors_across_runs() -> None:
    spec = get_preset("benchmark")
    names = [[spec.run_lidar(a, k).name for k in range(spec.runs)] for a in range(3)]
    assert set(names[0]) == {"HDL-64E", "HDL-32E", "VLP-16", "OS1-128"}
    assert names[0] != names[1]  # each area starts at another sensor
    assert spec.conditions.ego_clearance is not None and spec.city.any
    assert spec.conditions.follow_ground and spec.city.hills > 0
    assert all(s.ego_roof_drop > 0 for s in spec.lidars)
    old = get_preset("benchmark_v1")
    assert not old.lidars and not old.city.any and not old.lidar.realistic
    assert not old.conditions.follow_ground and old.city.hills == 0
    assert CityDetail().any is False


def test_a_tree_of_mixed_sensors_and_street_detail_checks_and_repeats(tmp_path) -> None:
    import json

    from pnvlad_service.data.tree import check_tree
    from pnvlad_service.synth.generate import REAL_CONDITIONS, generate
    from pnvlad_service.synth.sensors import sensor
    from pnvlad_service.synth.windows import drives_of

    spec = get_preset("tiny").model_copy(
        update={
            "name": "tiny-real",
            "lidars": [sensor("vlp16", columns=360), sensor("hdl32e", columns=360)],
            "conditions": REAL_CONDITIONS,
            "city": REAL_CITY,
        }
    )
    a, b = tmp_path / "a", tmp_path / "b"
    summary = generate(spec, a, seed=5, workers=1, progress=False)
    generate(spec, b, seed=5, workers=1, progress=False)
    report = check_tree(a)
    assert report.ok, report.problems
    assert [r["sensor"] for r in summary["runs"]] == ["VLP-16", "HDL-32E", "VLP-16"]
    files = sorted(p.relative_to(a) for p in a.rglob("*.bin"))
    assert files and all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    # the tree's synth.json gives back each run's sensor (windows and realism re-cast from it)
    spec_back = next(iter(drives_of(a).values()))[0]
    assert spec_back.run_lidar(0, 1).name == "HDL-32E"
    assert json.loads((a / "synth.json").read_text())["preset"]["city"]["crown_clumps"] == 4
