"""synth.realism: each statistic against clouds whose answer is known by construction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pnvlad_service.synth.realism import (
    Layout,
    ScanStats,
    compare,
    emd,
    local_shape,
    pool,
    relative_difference,
    rings_by_elevation,
    rings_from_field,
    scan_stats,
    scan_turns,
    shape_shares,
)

LAYOUT = Layout(beams=8, elevation_max_deg=2.0, elevation_min_deg=-12.0)  # 2 degree steps


def _on_beams(counts: list[int], jitter_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Points on LAYOUT's beams, ``counts[b]`` on beam b, elevations within ``jitter_deg``."""
    el = np.repeat(LAYOUT.elevations(), counts) + rng.uniform(-jitter_deg, jitter_deg, sum(counts))
    az = rng.uniform(-math.pi, math.pi, len(el))
    r = rng.uniform(5.0, 50.0, len(el))
    e = np.radians(el)
    return np.stack([r * np.cos(e) * np.cos(az), r * np.cos(e) * np.sin(az), r * np.sin(e)], 1)


def test_rings_by_elevation_count_the_returns_of_each_beam() -> None:
    counts = [10, 20, 30, 40, 50, 60, 70, 80]
    pts = _on_beams(counts, 0.9, np.random.default_rng(0))
    assert np.bincount(rings_by_elevation(pts, LAYOUT), minlength=8).tolist() == counts


def test_rings_from_a_field_rank_its_ids_from_the_top() -> None:
    rng = np.random.default_rng(1)
    pts = _on_beams([5] * 8, 0.5, rng)
    beam = np.repeat(np.arange(8), 5)
    ids = np.array([3, 7, 0, 5, 1, 6, 2, 4])[beam]  # a format's own numbering
    assert rings_from_field(ids, pts).tolist() == beam.tolist()


def _turns(elevations_deg: list[float]) -> np.ndarray:
    """Beams one after the other in a file, each over one turn from 7 degrees (KITTI's way)."""
    az = np.radians(7.0 + np.linspace(0.0, 359.0, 500))
    return np.concatenate(
        [
            np.stack([np.cos(az), np.sin(az), np.full_like(az, math.tan(math.radians(e)))], 1)
            for e in elevations_deg
        ]
    )


def test_scan_turns_follow_the_azimuth_along_the_file() -> None:
    turn = np.repeat(np.arange(3), 500)
    assert scan_turns(_turns([2.0, 0.0, -2.0]) * 10).tolist() == turn.tolist()
    upward = _turns([-2.0, 0.0, 2.0]) * 10  # a file that starts with the bottom beam
    assert rings_from_field(scan_turns(upward), upward).tolist() == (2 - turn).tolist()


def test_local_shape_tells_a_line_a_plane_and_a_blob_apart() -> None:
    rng = np.random.default_rng(2)
    t = np.arange(2000) * 0.01
    line = np.stack([t, 1e-3 * rng.normal(size=2000), 1e-3 * rng.normal(size=2000)], 1)
    grid = np.stack(np.meshgrid(np.arange(60.0), np.arange(60.0)), -1).reshape(-1, 2) * 0.1
    plane = np.c_[grid, 1e-3 * rng.normal(size=len(grid))]
    blob = rng.normal(size=(3000, 3))
    linear, planar, scattered = (
        shape_shares(local_shape(c, k=k, sample=500, rng=rng))
        for c, k in ((line, 16), (plane, 16), (blob, 64))
    )
    assert linear[0] > 0.99
    assert planar[1] > 0.9
    assert scattered[2] > 0.9
    f = local_shape(blob, k=16, sample=100, rng=rng)
    assert f.shape == (100, 3) and np.allclose(f.sum(axis=1), 1.0)


def test_a_neighbourhood_with_no_extent_is_left_out() -> None:
    same = np.ones((20, 3))
    assert np.all(local_shape(same, k=8) == 0)
    assert np.isnan(shape_shares(local_shape(same, k=8))).all()


def test_distances() -> None:
    a = np.random.default_rng(3).normal(size=1000)
    assert emd(a, a) == 0.0
    assert emd(a, a + 1.5) == pytest.approx(1.5)
    assert emd([0, 1], [0, 1], [1, 0], [0, 1]) == pytest.approx(1.0)  # weights move all mass
    assert relative_difference(100.0, 50.0) == -0.5
    assert math.isnan(relative_difference(0.0, 1.0))


def _street(rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """A flat road 1.8 m under the sensor (a 0.25 m grid from 1 to 30 m) and two walls 8 m
    either side; the number of road points farther than 2.5 m."""
    g = np.stack(np.meshgrid(np.arange(-30, 30, 0.25), np.arange(-30, 30, 0.25)), -1)
    g = g.reshape(-1, 2)
    g = g[(np.hypot(g[:, 0], g[:, 1]) >= 1.0) & (np.hypot(g[:, 0], g[:, 1]) <= 30.0)]
    road = np.c_[g, np.full(len(g), -1.8) + 0.01 * rng.normal(size=len(g))]
    x, z = np.meshgrid(np.arange(-20, 20, 0.2), np.arange(-1.0, 6.0, 0.2))
    walls = [np.stack([x.ravel(), np.full(x.size, y), z.ravel()], 1) for y in (-8.0, 8.0)]
    far = int((np.linalg.norm(road, axis=1) >= 2.5).sum())
    return np.concatenate([road, *walls]), far


def test_scan_stats_of_a_street() -> None:
    rng = np.random.default_rng(4)
    pts, road = _street(rng)
    walls = len(pts) - int((np.abs(pts[:, 2] + 1.8) < 0.1).sum())
    layout = Layout(64, 2.0, -24.8)
    s = scan_stats(pts, layout, sample=2000)
    assert s.scans == 1 and s.points == road + walls
    assert s.sensor_height == pytest.approx(1.8, abs=0.02)
    assert s.ground_share == pytest.approx(road / (road + walls), abs=0.02)
    assert s.ranges.min() >= 2.5 and len(s.ranges) == len(s.heights) == s.points
    assert s.ring_counts.sum() == s.points and len(s.ring_counts) == 64
    assert s.shape[1] > 0.9  # a road and two walls: planes
    assert s.g_ground_left < 0.01 and s.g_heights.min() > -1.8 + 0.2
    assert s.g_points > 0 and s.g_leaf > 0


def _stats(points: float, shift: float = 0.0) -> ScanStats:
    rng = np.random.default_rng(5)
    return ScanStats(
        scans=1,
        points=points,
        sensor_height=1.8,
        ground_share=0.5,
        shape=np.array([0.6, 0.3, 0.1]),
        g_points=points / 10,
        g_leaf=0.4,
        g_ground_left=0.01,
        g_shape=np.array([0.5, 0.4, 0.1]),
        ranges=(rng.uniform(3, 50, 100) + shift).astype(np.float32),
        heights=rng.normal(-1, 1, 100).astype(np.float32) + shift,
        g_heights=rng.normal(0, 1, 100).astype(np.float32) + shift,
        ring_counts=np.array([10, 20, 30, 40]),
    )


def test_pool_averages_scalars_joins_samples_and_sums_rings() -> None:
    p = pool([_stats(1000.0), _stats(3000.0)])
    assert p.scans == 2 and p.points == 2000.0 and p.g_points == 200.0
    assert len(p.ranges) == 200
    assert p.ring_counts.tolist() == [20, 40, 60, 80]
    assert np.allclose(p.shape, [0.6, 0.3, 0.1])


def test_compare_gives_zero_for_the_same_and_the_change_otherwise() -> None:
    same = compare(_stats(1000.0), _stats(1000.0))
    assert len(same) == 16 and all(r.distance == 0 for r in same)
    rows = {r.label: r for r in compare(_stats(1000.0), _stats(500.0, shift=2.0))}
    assert rows["points per scan"].distance == pytest.approx(-50.0)
    assert rows["range (mean)"].distance == pytest.approx(2.0, abs=1e-5)
    assert rows["G: height about the sensor (mean)"].distance == pytest.approx(2.0, abs=1e-5)
    assert rows["returns per ring (mean ring, 0 = top)"].real == pytest.approx(2.0)
