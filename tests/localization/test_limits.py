"""Limits.check_points: the check of one cloud as an array, shared by every way a cloud
arrives (JSON and binary bodies, library and CLI callers): accepted exactly at each limit,
refused just past it, with the first bad point named, and no copy of an array already fit."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import SUBMAP_BOUND, SUBMAP_POINTS
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.preprocess.filter_g import GConfig

LIM = Limits(max_raw_points=5000, max_top_n=7, max_batch_queries=3)


def refused(points: np.ndarray, preprocess: bool, limits: Limits = LIM) -> InputError:
    with pytest.raises(InputError) as info:
        limits.check_points(points, preprocess, "points")
    return info.value


def test_the_limits_are_the_formats_and_the_servers_defaults() -> None:
    from pnvlad_service.server.settings import ServerSettings

    d, s = Limits(), ServerSettings()
    assert d.points_per_cloud == SUBMAP_POINTS == 4096
    assert d.bound == SUBMAP_BOUND + 1e-4 and d.max_raw_coord == 100_000.0
    assert d.min_raw_points == GConfig().min_points == 16  # the filter G's fewest
    assert s.limits() == d  # the settings' defaults are the library's
    assert (s.max_raw_points, s.max_top_n, s.max_batch_queries) == (500_000, 100, 64)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_preprocessed_cloud_is_exactly_4096_points_within_the_bound(dtype) -> None:
    pts = np.zeros((SUBMAP_POINTS, 3), dtype)
    pts[10] = (LIM.bound, -LIM.bound, 0.0)  # at the bound: accepted
    out = LIM.check_points(pts, False, "points")
    assert out.dtype == np.float32 and out.shape == (4096, 3)
    assert np.array_equal(out, pts.astype(np.float32))
    if dtype is np.float32:
        assert np.shares_memory(out, pts)  # no copy
    for n in (4095, 4097):
        e = refused(np.zeros((n, 3), dtype), False)
        assert e.source == "points" and f"got {n}" in e.detail and "preprocess=true" in e.detail
    over = pts.copy()
    over[3, 2] = -1.0002
    over[7, 0] = 5.0
    e = refused(over, False)
    assert e.source == "points[3]" and "outside [-1, 1]" in e.detail


def test_a_raw_scan_is_16_to_max_raw_points_within_100_km() -> None:
    """16, the filter G's fewest, to ``max_raw_points``: accepted exactly at both ends."""
    fewest = np.arange(48, dtype=np.float32).reshape(16, 3)
    out = LIM.check_points(fewest, True, "points")
    assert out.dtype == np.float64 and out.tolist() == fewest.astype(np.float64).tolist()
    e = refused(fewest[:15], True)
    assert e.source == "points" and "between 16 and 5000 points, got 15" in e.detail
    far = np.full((LIM.max_raw_points, 3), 100_000.0)
    assert np.shares_memory(LIM.check_points(far, True, "points"), far)  # float64: no copy
    e = refused(np.zeros((LIM.max_raw_points + 1, 3)), True)
    assert e.source == "points" and "between 16 and 5000 points, got 5001" in e.detail
    assert "got 0" in refused(np.zeros((0, 3)), True).detail
    too_far = np.zeros((30, 3))
    too_far[21, 1] = -100_000.5
    e = refused(too_far, True)
    assert e.source == "points[21]" and "100,000 m from the sensor" in e.detail


def test_non_finite_points_and_bad_shapes_are_named_first() -> None:
    pts = np.zeros((4095, 3))  # wrong count too, but the NaN is reported first
    pts[17, 1] = np.nan
    pts[30, 0] = np.inf
    e = refused(pts, False)
    assert e.source == "points[17]" and "NaN or infinite" in e.detail
    assert refused(pts, True).source == "points[17]"
    e = refused(np.zeros((4096, 2)), False)
    assert e.source == "points" and "(4096, 2)" in e.detail


def test_top_n_and_batch_counts() -> None:
    assert LIM.check_top_n(1) == 1 and LIM.check_top_n(7) == 7
    for bad, words in ((0, "between 1 and 7, got 0"), (8, "got 8"), (2.5, "integer, got 2.5")):
        with pytest.raises(InputError, match=words) as info:
            LIM.check_top_n(bad)
        assert info.value.source == "top_n"
    with pytest.raises(InputError, match="integer, got true"):
        LIM.check_top_n(True)
    LIM.check_count(1, "body")
    LIM.check_count(3, "body")
    for n in (0, 4):
        with pytest.raises(InputError, match=f"expected 1 to 3 clouds, got {n}"):
            LIM.check_count(n, "body")
