"""data.splits.geometry: radius searches inclusive at exact distances, against plain loops.

Expected values come from hand-worked cases (points placed at exactly 10, 25, 50 and 150 m
along one axis, where float64 arithmetic on UTM magnitudes is exact) and from plain Python
loops over every pair of submaps.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data import splits as sp
from tests.data.splits.helpers import (
    CE,
    CN,
    brute_within,
)


def test_within_radius_is_inclusive_at_exact_distances() -> None:
    # one reference point, queries exactly 10, 25, 50 m away along each axis and on a 6-8-10
    # diagonal; and a hair beyond
    ref_n, ref_e = np.array([CN]), np.array([CE])
    offsets = [(10.0, 0.0), (0.0, -25.0), (-50.0, 0.0), (6.0, 8.0), (0.0, 10.000001)]
    qn = np.array([CN + a for a, _ in offsets])
    qe = np.array([CE + b for _, b in offsets])
    hits = lambda r: [len(x) == 1 for x in sp.within_radius(ref_n, ref_e, qn, qe, r)]  # noqa: E731
    assert hits(10.0) == [True, False, False, True, False]
    assert hits(25.0) == [True, True, False, True, True]
    assert hits(50.0) == [True, True, True, True, True]
    assert hits(9.999999) == [False, False, False, False, False]


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.tuples(st.integers(-120, 120), st.integers(-120, 120)), min_size=1, max_size=40),
    st.sampled_from([0.0, 5.0, 10.0, 25.0, 50.0]),
)
def test_within_radius_matches_a_plain_loop(pts, r) -> None:
    ref = [(CN + a * 0.5, CE + b * 0.5) for a, b in pts]
    n = np.array([p[0] for p in ref])
    e = np.array([p[1] for p in ref])
    expect = [brute_within(ref, q, r) for q in ref]
    assert [g.tolist() for g in sp.within_radius(n, e, n, e, r)] == expect
    assert [g.tolist() for g in sp.within_radius(n, e, n, e, r, chunk=7)] == expect
