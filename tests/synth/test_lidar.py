"""synth.lidar: first surfaces, shadows and the ground, against hand-placed geometry."""

from __future__ import annotations

import numpy as np

from pnvlad_service.synth.lidar import LidarConfig, cast_scan, ray_bundle
from pnvlad_service.synth.world import KIND_BUILDING, Boxes, Ground, Scene
from tests.synth.scenes import FLAT, NO_CYL, NO_ELL


def _one_box_scene(distance: float) -> tuple[Scene, Ground]:
    boxes = Boxes(
        center=np.array([[distance + 0.5, 0.0]]),
        half=np.array([[0.5, 2.0]]),
        z=np.array([[-5.0, 50.0]]),
        yaw=np.array([0.0]),
        kind=np.array([KIND_BUILDING], np.int8),
    )
    return Scene(boxes, NO_CYL, NO_ELL), FLAT


def test_lidar_first_surface_and_occlusion_shadow() -> None:
    # A wall 10 m ahead (x = 10 .. 11, y = -2 .. 2); sensor 2 m above a flat ground, no noise.
    scene, ground = _one_box_scene(10.0)
    cfg = LidarConfig(beams=8, columns=720, range_noise=0.0, dropout=0.0, min_range=0.5)
    pts = cast_scan(scene, ground, np.array([0.0, 0.0, 2.0]), 0.0, cfg, np.random.default_rng(0))
    az = np.arctan2(pts[:, 1], pts[:, 0])
    toward = np.abs(az) < np.arctan2(1.9, 10.0)  # rays that must meet the wall's front face
    rays = ray_bundle(cfg)
    # Expected per ray, computed independently: front face x = 10 unless the ground comes first.
    hits_wall = toward & (pts[:, 2] > -2.0 + 1e-6)
    assert hits_wall.any()
    np.testing.assert_allclose(pts[hits_wall, 0], 10.0, atol=1e-5)
    # Shadow: nothing is seen behind the wall.
    behind = (pts[:, 0] > 11.0) & (np.abs(pts[:, 1]) < 1.5)
    assert not behind.any()
    # Elsewhere the down-looking beams reach the flat ground at z = -2 (sensor frame).
    ground_pts = pts[np.abs(az) > np.arctan2(2.1, 10.0)]
    assert ground_pts.size and np.allclose(ground_pts[:, 2], -2.0, atol=1e-6)
    assert len(rays.elevation) == 8
