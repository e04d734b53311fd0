"""synth.sensors and the real sensor's failures in synth.lidar, against hand-placed geometry."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from pnvlad_service.synth import realism as rl
from pnvlad_service.synth.generate import get_preset, simulated_drive
from pnvlad_service.synth.lidar import (
    WINDOW_BAY_M,
    WINDOW_FLOOR_M,
    WINDOW_SHARE,
    WINDOW_SILL_M,
    cast_scan,
    ray_bundle,
)
from pnvlad_service.synth.sensors import SENSORS, LidarConfig, sensor
from pnvlad_service.synth.world import KIND_BUILDING, KIND_CROWN, Boxes, Ellipsoids, Scene
from tests.synth.scenes import CLEAN, FLAT, NO_BOX, NO_CYL, NO_ELL, four_walls


def _wall(x0: float, half_y: float = 20.0) -> Boxes:
    """A building's side facing the sensor at x = x0 (metres ahead), 30 m tall."""
    return Boxes(
        np.array([[x0 + 2.0, 0.0]]),
        np.array([[2.0, half_y]]),
        np.array([[-2.0, 28.0]]),
        np.array([0.0]),
        np.array([KIND_BUILDING], np.int8),
    )


def test_catalogue_beam_tables() -> None:
    hdl64 = SENSORS["hdl64e"]
    el = hdl64.elevations()
    assert len(el) == 64 and el[0] == pytest.approx(2.0) and el[-1] == pytest.approx(-24.8)
    gaps = -np.diff(el)
    # the upper block a third of a degree apart, the lower about half a degree
    np.testing.assert_allclose(gaps[:31], 10.33 / 31, atol=1e-3)
    np.testing.assert_allclose(gaps[32:], (24.8 - 8.83) / 31, atol=1e-3)
    np.testing.assert_allclose(np.rad2deg(ray_bundle(hdl64).elevation), el)
    assert [SENSORS[n].beams for n in ("hdl32e", "vlp16", "os128")] == [32, 16, 128]
    assert SENSORS["vlp16"].elevations()[0] == 15.0 and SENSORS["vlp16"].elevations()[-1] == -15
    with pytest.raises(ValueError, match="beams"):
        LidarConfig(beams=3, elevations_deg=[1.0, 0.0])


def test_rings_of_a_beam_table_are_the_beams() -> None:
    # Points cast along each beam of the HDL-64E's two blocks fall in that beam's ring.
    cfg = sensor("hdl64e", columns=90, **CLEAN)
    scene = Scene(_wall(10.0, 100.0), NO_CYL, NO_ELL)
    rays = ray_bundle(cfg)
    pts, beams = cast_scan(
        scene, FLAT, np.array([0.0, 0.0, 30.0]), 0.0, cfg, np.random.default_rng(0), rings=True
    )
    rings = rl.rings_by_elevation(pts, rl.Layout.of(cfg))
    np.testing.assert_array_equal(rings, beams)  # the beam each point was cast with
    expected = np.argmin(
        np.abs(rl.elevation_deg(pts)[:, None] - np.rad2deg(rays.elevation)[None]), axis=1
    )
    np.testing.assert_array_equal(rings, expected)
    assert len(np.unique(rings)) > 40


def test_motion_during_the_sweep_shifts_each_column_by_its_time() -> None:
    # A room of four walls; the same rays and draws with and without motion: each point moves
    # back by speed x its column's time from the sweep's middle, turned by the yaw rate x it.
    cfg = LidarConfig(beams=4, columns=360, deskewed=False, **CLEAN)
    scene = four_walls()
    o = np.array([0.0, 0.0, 1.5])
    still = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(1), motion=(0.0, 0.0))
    speed, rate = 10.0, 0.3
    moved = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(1), motion=(speed, rate))
    assert still.shape == moved.shape
    az = np.mod(np.arctan2(still[:, 1], still[:, 0]), 2 * np.pi)
    col = np.rint(az / (2 * np.pi / 360)) % 360
    tau = (np.mod(np.pi - col * 2 * np.pi / 360, 2 * np.pi) / (2 * np.pi) - 0.5) / 10.0
    a = -rate * tau
    x, y = still[:, 0] - speed * tau, still[:, 1]
    expect = np.stack([np.cos(a) * x - np.sin(a) * y, np.sin(a) * x + np.cos(a) * y], 1)
    np.testing.assert_allclose(moved[:, :2], expect, atol=1e-3)
    # the seam behind the vehicle: half a metre apart at 10 m/s and 10 Hz
    assert np.ptp(moved[:, 0] - still[:, 0]) == pytest.approx(speed / 10.0, abs=0.05)


def test_glass_loses_the_windows_and_recesses_what_returns() -> None:
    cfg = LidarConfig(beams=32, columns=1440, glass_loss=1.0, **CLEAN)
    cfg = cfg.model_copy(update={"elevation_max_deg": 40.0, "elevation_min_deg": -10.0})
    scene = Scene(_wall(8.0), NO_CYL, NO_ELL)
    o = np.array([0.0, 0.0, 1.5])
    pts = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(0))
    face = pts[np.abs(pts[:, 0] - 8.0) < 1e-4]
    # independently: the wall's face runs y = -20 .. 20, its foot at z = -2 (world)
    along = face[:, 1] + 20.0
    height = face[:, 2] + o[2] + 2.0
    lo = (1 - WINDOW_SHARE) / 2
    u = np.mod(along, WINDOW_BAY_M) / WINDOW_BAY_M
    v = np.mod(height, WINDOW_FLOOR_M) / WINDOW_FLOOR_M
    glass = (u > lo + 1e-3) & (u < 1 - lo - 1e-3) & (v > lo + 1e-3) & (v < 1 - lo - 1e-3)
    glass &= height > WINDOW_SILL_M + 1e-3
    assert len(face) > 500 and not glass.any()
    # with half of the glass lost the rest returns from 0.1-0.6 m behind it
    keep = cast_scan(
        scene, FLAT, o, 0.0, cfg.model_copy(update={"glass_loss": 0.5}), np.random.default_rng(0)
    )
    behind = keep[(keep[:, 0] > 8.0 + 1e-4) & (keep[:, 0] < 8.0 + 0.61 * 1.5)]
    assert len(behind) > 100


def test_foliage_returns_from_inside_the_crown() -> None:
    crown = Ellipsoids(
        np.array([[10.0, 0.0, 30.0]]),
        np.array([[3.0, 3.0, 3.0]]),
        np.array([1.0]),
        np.array([KIND_CROWN], np.int8),
    )
    cfg = LidarConfig(beams=32, columns=720, **CLEAN)
    o = np.array([0.0, 0.0, 30.0])  # the ground far below
    for depth, (lo, hi) in ((0.0, (2.999, 3.001)), (0.8, (0.0, 3.0001))):
        c = cfg.model_copy(update={"foliage_depth": depth})
        pts = cast_scan(Scene(NO_BOX, NO_CYL, crown), FLAT, o, 0.0, c, np.random.default_rng(0))
        r = np.linalg.norm(pts + o - crown.center[0], axis=1)
        inside = r < 3.5
        assert inside.sum() > 100 and (r[inside] >= lo).all() and (r[inside] <= hi).all()
    # along each ray, the depth past the crown's surface (entry computed independently) is
    # exponential with the mean asked for, cut at the far side
    p = pts[inside].astype(np.float64)
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    c = crown.center[0] - o
    dc = d @ c
    root = np.sqrt(dc**2 - (c @ c - 9.0))
    past = np.linalg.norm(p, axis=1) - (dc - root)
    assert (past > -1e-3).all() and (past <= 2 * root + 1e-3).all()
    assert 0.35 < float(np.median(past)) < 0.7


def test_dropouts_grow_with_range() -> None:
    cfg = LidarConfig(beams=16, columns=720, dropout_far=0.6, **CLEAN)
    cfg = cfg.model_copy(update={"elevation_max_deg": 5.0, "elevation_min_deg": -5.0})
    o = np.array([0.0, 0.0, 20.0])  # every beam meets the wall before the ground
    rays = ray_bundle(cfg)
    el, az = np.meshgrid(rays.elevation, rays.azimuth, indexing="ij")
    az = np.angle(np.exp(1j * az))
    ahead = np.abs(az) < np.deg2rad(20)
    share = []
    for x in (10.0, 80.0):
        scene = Scene(_wall(x, 200.0), NO_CYL, NO_ELL)
        pts = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(3))
        seen = (np.abs(pts[:, 0] - x) < 1e-3) & (
            np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < np.deg2rad(20)
        )
        # independently: every ray ahead meets the wall at x / (cos az cos el)
        r = x / (np.cos(az[ahead]) * np.cos(el[ahead]))
        expected = float(np.sum(1 - 0.6 * (r / 100.0) ** 2))
        share.append((int(seen.sum()), expected))
    (near, near_exp), (far, far_exp) = share
    assert near == pytest.approx(near_exp, rel=0.04)
    assert far == pytest.approx(far_exp, rel=0.08)
    assert far < 0.75 * near


def test_trees_made_before_the_sensors_cast_the_same_scans() -> None:
    # The tiny preset (the perfect sensor, no detail): scans hashed by the code before #37.
    d = simulated_drive(get_preset("tiny"), 0, 1, 7)
    for i, (n, digest) in ((0, (10761, "1634b1d68f7835d9")), (5, (9732, "0a63e3c737a53801"))):
        pts = d.scan(i)
        assert (len(pts), hashlib.sha256(pts.tobytes()).hexdigest()[:16]) == (n, digest)
