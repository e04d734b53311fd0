"""synth.realism_cloud: the push-broom statistics on hand-made clouds and on the real ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.synth import realism_cloud as rc


def _road(spacing: float, heading_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A 40 m stretch of flat road swept by lines across it every ``spacing`` metres, 8 m wide,
    points 5 cm apart in a line, the track heading ``heading_deg`` from x."""
    along = np.arange(-20.0, 20.0, spacing)
    across = np.arange(-4.0, 4.0, 0.05)
    a, c = (g.ravel() for g in np.meshgrid(along, across, indexing="ij"))
    a = a + rng.normal(0, 0.005, len(a))
    t = np.deg2rad(heading_deg)
    x = a * np.cos(t) - c * np.sin(t)
    y = a * np.sin(t) + c * np.cos(t)
    return np.stack([x, y], 1)


@pytest.mark.parametrize(("spacing", "heading"), [(0.16, 30.0), (0.3, 125.0)])
def test_scan_lines_finds_the_spacing_and_the_track(spacing: float, heading: float) -> None:
    rng = np.random.default_rng(0)
    xy = _road(spacing, heading, rng)
    period, strength, gap, axis = rc.scan_lines(xy)
    assert period == pytest.approx(spacing, rel=0.05)
    assert strength > 20
    assert gap == pytest.approx(0.05, rel=0.1)
    track = np.array([np.cos(np.deg2rad(heading)), np.sin(np.deg2rad(heading))])
    assert abs(axis @ track) > np.cos(np.deg2rad(1.5))


def test_scan_lines_sees_no_comb_in_scattered_points() -> None:
    xy = np.random.default_rng(1).uniform(-10, 10, (6000, 2))
    _, strength, _, _ = rc.scan_lines(xy)
    assert strength < 20


def test_lay_like_real_keeps_a_disc_through_a_voxel_grid_and_turns_it() -> None:
    rng = np.random.default_rng(2)
    cloud = np.c_[rng.uniform(-50, 50, (200_000, 2)), rng.uniform(0, 10, 200_000)]
    laid = rc.lay_like_real(cloud, np.random.default_rng(3), radius=30.0, points=16_384)
    assert laid.shape == (16_384, 3)
    assert np.hypot(laid[:, 0], laid[:, 1]).max() <= 30.0 + 1e-9
    np.testing.assert_allclose(np.sort(laid[:, 2])[[0, -1]], [0, 10], atol=0.3)
    # one point a 0.2 m voxel: no two much closer than the points of the uniform cloud would be
    from scipy.spatial import cKDTree

    nn = cKDTree(laid).query(laid, k=2)[0][:, 1]
    assert np.mean(nn < 0.02) < 0.01


def test_the_real_robotcar_clouds_are_tall_and_voxelised(real_scans: Path) -> None:
    pts = np.fromfile(real_scans / "oxford_lms_front_270.bin", "<f4").reshape(-1, 6)[:, :3]
    s = rc.cloud_stats(pts.astype(np.float64), sample=2000)
    assert s.nn_spacing == pytest.approx(0.2, abs=0.03)  # the grid of REAL_LEAF_M
    assert np.percentile(s.heights, 90) > 4.0  # facades and trees to their tops
    assert 0.2 < s.ground_share < 0.7
    assert s.g_height > 0.3  # after G: far taller than a spinning sensor's 0.11


def test_the_benchmark_names_missing_real_clouds_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "realism_pushbroom.py"
    done = subprocess.run(
        [sys.executable, str(script), "--real", str(tmp_path), "--clouds", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr == (
        f"error: {tmp_path / 'oxford_lms_front_270.bin'}: not there (--real or "
        "$PNVLAD_REAL_SCANS)\n"
    )
