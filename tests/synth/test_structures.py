"""The city's slopes, ground cover and structures, and the sensor on them (issue #37): the
vehicle's own roof, a sensor leaning with the slope, grass, bridges and building fronts."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.synth import lidar
from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.generate import get_preset, simulated_drive
from pnvlad_service.synth.lidar import cast_scan, on_roof
from pnvlad_service.synth.runs import ground_attitude
from pnvlad_service.synth.sensors import LidarConfig, sensor
from pnvlad_service.synth.streets import box_samples
from pnvlad_service.synth.world import (
    KIND_BRIDGE,
    KIND_BUILDING,
    KIND_FACADE,
    KIND_GRASS,
    Boxes,
    CityDetail,
    Scene,
    WorldConfig,
)
from tests.synth.scenes import CLEAN, FLAT, NO_BOX, NO_CYL, NO_ELL

RICH = CityDetail(grass_verges=1.0, lawns=1.0, hills=4.0, bridges_per_km=3.0, facade_bays=1.0,
                  balconies=1.0)  # fmt: skip
SMALL = {"district": "residential", "size": (400.0, 300.0)}


def _direction(az_deg: float, el_deg: float) -> np.ndarray:
    a, e = np.deg2rad(az_deg), np.deg2rad(el_deg)
    return np.array([[np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]])


@pytest.mark.parametrize(
    ("az", "el", "blocked"),
    [
        (0.0, -25.0, True),  # meets the roof's plane 0.86 m ahead: inside the front at 0.87
        (0.0, -24.0, False),  # 0.90 m ahead: past it
        (180.0, -22.0, True),  # 0.99 m behind: inside the rear at 1.0
        (90.0, -24.0, True),  # 0.898 m aside: inside the side at 0.91
        (45.0, -24.0, False),  # the diagonal: (0.635 / 0.87)^2 + (0.635 / 0.91)^2 = 1.02
        (0.0, 5.0, False),  # upwards never
    ],
)
def test_the_roof_hides_the_rays_that_meet_it(az: float, el: float, blocked: bool) -> None:
    cfg = LidarConfig(ego_roof_drop=0.4)
    assert bool(on_roof(cfg, _direction(az, el))[0]) is blocked


def test_the_lowest_beams_see_the_ground_past_the_roof_corners_only() -> None:
    table = sensor("hdl64e").elevations_deg
    cfg = LidarConfig(beams=64, elevations_deg=table, columns=720, ego_roof_drop=0.4, **CLEAN)
    o = np.array([0.0, 0.0, cfg.mount_height])
    scene = Scene(NO_BOX, NO_CYL, NO_ELL)
    _, beams = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(0), rings=True)
    seen = np.bincount(beams, minlength=64) / 720
    # expected: the share of a fine ring of azimuths where the beam meets the roof's plane
    # outside its outline (half ellipses: ahead 0.87, behind 1.0, aside 0.91 m)
    a = np.linspace(0, 2 * np.pi, 36_000, endpoint=False)
    expect = []
    for e in np.deg2rad(np.sort(table)[::-1]):
        r = 0.4 / np.tan(-e) if e < 0 else 1e9
        x, y = r * np.cos(a), r * np.sin(a)
        outside = np.where(x >= 0, x / 0.87, x / 1.0) ** 2 + (y / 0.91) ** 2 >= 1
        expect.append(float(np.mean(outside)))
    np.testing.assert_allclose(seen[40:], expect[40:], atol=0.01)
    assert seen[-1] < 0.05 and seen[-3] < 0.5 < seen[-6] and min(expect[:50]) == 1.0


def test_a_leaning_sensor_finds_what_every_ray_would() -> None:
    # The cast's windows (shifted and widened for the lean) against every primitive paired
    # with every ray, on a hilly street with the sensor on the slope and rolled a little more.
    world = generate_world(WorldConfig(**SMALL, detail=RICH), seed=3)
    cfg = LidarConfig(beams=24, elevation_min_deg=-30.0, elevation_max_deg=10.0, columns=240)
    cfg = cfg.model_copy(update=CLEAN)
    everything = lidar._pairs

    def brute(center, radius, zlo, zhi, origin, yaw, rays, max_range, tilt=None):
        n, m = len(center), rays.dirs.shape[0] * rays.dirs.shape[1]
        return np.repeat(np.arange(n), m), np.tile(np.arange(m), n)

    roll = np.array([[1, 0, 0], [0, np.cos(0.06), -np.sin(0.06)], [0, np.sin(0.06), np.cos(0.06)]])
    leans = []
    for k, xy in enumerate(((100.0, 8.0), (200.0, 150.0), (300.0, 100.0))):
        yaw = 0.4 + 1.7 * k
        att = ground_attitude(world, np.array([xy]), np.array([yaw]))[0] @ roll
        leans.append(np.degrees(np.arccos(att[2, 2])))
        pos = np.array([*xy, float(world.ground.height(*xy)) + 1.9])
        near_b = np.hypot(*(world.scene.boxes.center - pos[:2]).T) < 45
        near_c = np.hypot(*(world.scene.cylinders.center - pos[:2]).T) < 45
        scene = Scene(world.scene.boxes.take(near_b), world.scene.cylinders.take(near_c), NO_ELL)
        fast = cast_scan(scene, world.ground, pos, yaw, cfg, np.random.default_rng(0), attitude=att)
        try:
            lidar._pairs = brute
            slow = cast_scan(
                scene, world.ground, pos, yaw, cfg, np.random.default_rng(0), attitude=att
            )
        finally:
            lidar._pairs = everything
        np.testing.assert_array_equal(fast, slow)
    assert max(leans) > 4.0  # the hills lean it well past the margins of a level sensor


def test_on_the_slope_the_scans_and_poses_lay_the_ground_where_it_is() -> None:
    spec = get_preset("tiny").model_copy(deep=True)
    spec.city = CityDetail(hills=5.0)
    spec.conditions.follow_ground = True
    spec.lidar = spec.lidar.model_copy(update=CLEAN)
    drive = simulated_drive(spec, 0, 0, 3)
    poses = drive.true_poses
    leans = np.degrees(np.arccos(poses[:, 2, 2]))
    i = int(np.argmax(leans))
    assert leans[i] > 2.0
    pts = drive.scan(i).astype(np.float64)
    world = pts @ poses[i, :3, :3].T + poses[i, :3, 3] - [*drive.world.origin, 0.0]
    off = world[:, 2] - drive.world.ground.height(world[:, 0], world[:, 1])
    ground = np.abs(off) < 0.1
    assert ground.mean() > 0.3
    # far ground too: a level sensor's scan laid level would miss by the lean x the range
    far = np.hypot(pts[:, 0], pts[:, 1]) > 20
    assert np.median(np.abs(off[ground | far][np.abs(off[ground | far]) < 1.0])) < 0.03


def test_grass_returns_from_inside_its_blades_for_a_real_sensor() -> None:
    grass = Boxes(
        np.array([[8.0, 0.0]]),
        np.array([[4.0, 4.0]]),
        np.array([[-0.05, 0.15]]),
        np.zeros(1),
        np.array([KIND_GRASS], np.int8),
    )
    scene = Scene(grass, NO_CYL, NO_ELL)
    o = np.array([0.0, 0.0, 1.9])
    base = LidarConfig(beams=32, columns=720, elevation_min_deg=-30.0, **CLEAN)
    heights = {}
    for depth in (0.0, 0.4):
        cfg = base.model_copy(update={"foliage_depth": depth})
        pts = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(0)) + o
        on = (np.abs(pts[:, 0] - 8.0) < 3.5) & (np.abs(pts[:, 1]) < 3.5)
        heights[depth] = pts[on, 2]
    np.testing.assert_allclose(heights[0.0], 0.15, atol=1e-6)  # solid: the top
    z = heights[0.4]
    assert (z >= -1e-6).all() and (z <= 0.15 + 1e-6).all()  # never under the ground
    assert z.std() > 0.03 and (z < 0.01).mean() > 0.05  # spread, some down to the soil


def test_hills_bridges_grass_and_fronts_are_where_a_street_has_them() -> None:
    plain = generate_world(WorldConfig(**SMALL, detail=CityDetail(hills=4.0)), seed=2)
    rich = generate_world(WorldConfig(**SMALL, detail=RICH), seed=2)
    b = rich.scene.boxes
    n = len(plain.scene.boxes)
    np.testing.assert_array_equal(b.center[:n], plain.scene.boxes.center)  # only added to
    counts = {k: int((b.kind == k).sum()) for k in (KIND_GRASS, KIND_BRIDGE, KIND_FACADE)}
    assert min(counts.values()) > 0, counts
    # hills: streets of several per cent, and every building's foot under all its corners
    pts = np.concatenate([r.points for r in rich.roads])
    _, gx, gy = rich.ground.height_and_grad(pts[:, 0], pts[:, 1])
    assert np.percentile(np.hypot(gx, gy), 95) > 0.03
    for k in np.flatnonzero(b.kind == KIND_BUILDING):
        corners = box_samples(b.center[k], b.half[k], float(b.yaw[k]), step=1e3)
        assert (rich.ground.height(corners[:, 0], corners[:, 1]) >= b.z[k, 0]).all()
    # grass lies on the ground, off the carriageways
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    hw = np.concatenate([np.full(len(r.points), r.half_width) for r in rich.roads])
    g = b.take(b.kind == KIND_GRASS)
    dist, i = tree.query(g.center)
    assert (dist > hw[i]).all()
    h = rich.ground.height(g.center[:, 0], g.center[:, 1])
    assert ((g.z[:, 0] < h) & (g.z[:, 1] > h) & (g.z[:, 1] - h < 0.6)).all()
    # decks span a street with 5 m or more under them; their piers stand off the road
    br = b.take(b.kind == KIND_BRIDGE)
    decks = br.z[:, 0] > rich.ground.height(br.center[:, 0], br.center[:, 1]) + 4.0
    dist, i = tree.query(br.center)
    assert decks.any() and (dist[decks] < 1.0).all() and (dist[~decks] > hw[i[~decks]]).all()
