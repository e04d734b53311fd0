"""synth.runs: what differs between two runs of one city, and what stays."""

from __future__ import annotations

import numpy as np

from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.lidar import LidarConfig
from pnvlad_service.synth.runs import SimulatedDrive, make_route
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CAR,
    WorldConfig,
)


def test_two_runs_differ_but_the_static_city_is_the_same() -> None:
    world = generate_world(WorldConfig(district="residential", size=(400.0, 300.0)), seed=1)
    route = make_route(world, 300.0, seed=1)
    lidar = LidarConfig(beams=16, columns=180)
    r1 = SimulatedDrive(world, route, "a", seed=10, start_us=0, lidar=lidar)
    r2 = SimulatedDrive(world, route, "b", seed=11, start_us=0, lidar=lidar)
    s1, s2 = r1.scene, r2.scene

    def buildings(s) -> np.ndarray:
        k = s.boxes.kind == KIND_BUILDING
        return np.c_[s.boxes.center[k], s.boxes.half[k], s.boxes.z[k], s.boxes.yaw[k]]

    # Static: every building is where the city put it, in both runs.
    np.testing.assert_array_equal(buildings(s1), buildings(s2))
    world_b = world.scene.boxes.kind == KIND_BUILDING
    assert len(buildings(s1)) == int(world_b.sum())
    # Parked cars: different slots taken.
    p1 = {tuple(c) for c in s1.boxes.center[s1.boxes.kind == KIND_CAR].round(3)}
    p2 = {tuple(c) for c in s2.boxes.center[s2.boxes.kind == KIND_CAR].round(3)}
    assert p1 != p2
    # Vegetation: crowns of other sizes and densities (season).
    assert not np.allclose(s1.crowns.radii.mean(), s2.crowns.radii.mean())
    # Traffic: different vehicles at the same time.
    t = 10.0
    c1 = s1.scene_at(t, route.points[0], 1e9).boxes
    c2 = s2.scene_at(t, route.points[0], 1e9).boxes
    assert len(c1) != len(c2) or not np.allclose(c1.center, c2.center)
    # Moving objects move: the same run at two times.
    m_a = s1.scene_at(0.0, route.points[0], 1e9).boxes.center
    m_b = s1.scene_at(5.0, route.points[0], 1e9).boxes.center
    assert m_a.shape == m_b.shape and not np.allclose(m_a, m_b)
    # Pose noise: the poses used for submaps are off the true trajectory, differently per run.
    err1 = r1.poses[:, :2, 3] - (r1.true_xy + world.origin)
    err2 = r2.poses[:, :2, 3] - (r2.true_xy + world.origin)
    assert 0.2 < np.sqrt((err1**2).sum(1).mean()) < 6.0
    assert not np.allclose(err1, err2)
    # Same scan index, same points (deterministic whatever the order of the calls).
    np.testing.assert_array_equal(r1.scan(3), (r1.scan(5), r1.scan(3))[1])
