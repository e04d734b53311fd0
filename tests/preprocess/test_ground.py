"""preprocess.ground: the ground plane and the sort behind it, against plain loops and hand-made
scenes (the whole ground step through G's settings: test_filter_g.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.preprocess.ground import by_cell_then_height, fit_ground_plane, lowest_per_cell


def test_fit_ground_plane_ignores_walls() -> None:
    rng = np.random.default_rng(6)
    floor = np.c_[rng.uniform(-10, 10, (3000, 2)), rng.normal(0, 0.01, 3000) - 1.7]
    wall = np.c_[rng.uniform(-10, 10, 5000), np.full(5000, 4.0), rng.uniform(-1.7, 8, 5000)]
    normal, offset = fit_ground_plane(np.r_[floor, wall], rng=rng)
    assert normal[2] > 0.999 and offset == pytest.approx(1.7, abs=0.02)


def test_lowest_per_cell_against_a_plain_loop() -> None:
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(0, 10, (500, 2)), rng.normal(size=500)]
    x0, y0 = pts[:, 0].min(), pts[:, 1].min()  # the grid starts at the cloud's corner
    for sign in (1.0, -1.0):
        lowest: dict[tuple[int, int], int] = {}
        for i, (x, y, z) in enumerate(pts):
            key = (math.floor((x - x0) / 2.5), math.floor((y - y0) / 2.5))
            if key not in lowest or sign * z < sign * pts[lowest[key], 2]:
                lowest[key] = i
        assert sorted(lowest_per_cell(pts, 2.5, sign).tolist()) == sorted(lowest.values())


@settings(max_examples=60, deadline=None)
@given(
    cells=st.lists(st.integers(0, 6), min_size=1, max_size=60),
    seed=st.integers(0, 2**16),
)
def test_by_cell_then_height_against_a_plain_sort(cells: list[int], seed: int) -> None:
    """The order is Python's sort of (cell, height, index): by cell, then height, ties in
    input order (heights drawn from a few values, so there are ties); the starts are the
    first position of each cell present."""
    rng = np.random.default_rng(seed)
    height = rng.choice([-1.5, 0.0, 0.25, 3.0], size=len(cells)) * 7.3
    order, starts = by_cell_then_height(np.array(cells, dtype=np.int64), height)
    want = sorted(range(len(cells)), key=lambda i: (cells[i], height[i], i))
    assert order.tolist() == want
    firsts = [k for k, i in enumerate(want) if k == 0 or cells[want[k - 1]] != cells[i]]
    assert starts.tolist() == firsts


def test_by_cell_then_height_stays_exact_for_huge_cell_numbers() -> None:
    """Cell numbers near 1e13 (a vast grid) with a 100 m height range: one float key would round
    heights 2 mm apart together (and mix cells); the order is still exact."""
    cells = np.array([10**13 + 1, 10**13, 10**13, 10**13 + 1, 10**13], dtype=np.int64)
    height = np.array([0.002, 100.0, 0.002, 0.0, 0.0])
    order, starts = by_cell_then_height(cells, height)
    assert order.tolist() == [4, 2, 1, 3, 0]
    assert starts.tolist() == [0, 3]
