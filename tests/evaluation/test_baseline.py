"""The training-free baseline descriptor against a plain-loop reference."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.evaluation import baseline


def _reference(points: np.ndarray) -> np.ndarray:
    """Scan Context grid by a plain loop over the points: max(z + 1) per (ring, sector)."""
    grid = [[0.0] * baseline.SECTORS for _ in range(baseline.RINGS)]
    for x, y, z in points.tolist():
        r = math.hypot(x, y)
        if r > baseline.MAX_RADIUS:
            continue
        ring = min(int(r / baseline.MAX_RADIUS * baseline.RINGS), baseline.RINGS - 1)
        theta = math.atan2(y, x)
        sector = min(
            int((theta + math.pi) / (2 * math.pi) * baseline.SECTORS), baseline.SECTORS - 1
        )
        grid[ring][sector] = max(grid[ring][sector], z + 1.0)
    flat = np.array(grid).ravel()
    n = np.linalg.norm(flat)
    return flat / n if n > 0 else flat


def test_hand_worked_two_points() -> None:
    # (0.525, 0) lies in ring 10, sector 30 (theta 0); (0, -0.975) in ring 19, sector 15.
    pts = np.array([[0.525, 0.0, 0.2], [0.0, -0.975, -0.4], [0.525, 0.0, -0.5]])
    d = baseline.describe(pts)[0].reshape(baseline.RINGS, baseline.SECTORS)
    v = np.hypot(1.2, 0.6)
    assert d[10, 30] == np.float32(1.2 / v)  # max of the two heights in that bin
    assert d[19, 15] == np.float32(0.6 / v)
    assert np.count_nonzero(d) == 2


@settings(max_examples=25, deadline=None)
@given(st.integers(min_value=0, max_value=2**31 - 1), st.integers(min_value=1, max_value=300))
def test_matches_the_loop_and_has_unit_norm(seed: int, n: int) -> None:
    pts = np.random.default_rng(seed).uniform(-1, 1, (2, n, 3))
    got = baseline.describe(pts)
    assert got.shape == (2, baseline.DIM) and got.dtype == np.float32
    for b in range(2):
        np.testing.assert_allclose(got[b], _reference(pts[b]), atol=1e-6)
    # Unit rows, except a submap with no point inside the grid, which gives a zero row.
    inside = (np.hypot(pts[..., 0], pts[..., 1]) <= baseline.MAX_RADIUS).any(axis=1)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), inside.astype(float), atol=1e-5)


def test_a_place_is_closer_to_itself_shifted_slightly_than_to_another_place() -> None:
    rng = np.random.default_rng(0)
    a = rng.uniform(-1, 1, (4096, 3)) * [1, 1, 0.2]
    b = rng.uniform(-1, 1, (4096, 3)) * [1, 1, 0.2]
    da, da2, db = baseline.describe(np.stack([a, a + np.array([0.01, 0.0, 0.0]), b]))
    assert np.linalg.norm(da - da2) < np.linalg.norm(da - db)
