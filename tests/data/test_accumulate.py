"""data.accumulate: travelled distance, scans laid into one local frame, the scan cache."""

from __future__ import annotations

import numpy as np

from pnvlad_service.data.accumulate import ScanCache, accumulate, travelled_distance
from pnvlad_service.data.drive import Drive
from tests.data.helpers import ListDrive


def test_travelled_distance_is_horizontal_and_cumulative() -> None:
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, 3] = [[0, 0, 0], [3, 4, 10], [3, 4, 10], [3, 10, -5]]
    assert travelled_distance(poses).tolist() == [0.0, 5.0, 5.0, 11.0]


def test_accumulate_subtracts_the_centre_before_float32_precision_matters() -> None:
    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[0, :3, 3] = [620_000.0, 5_735_000.0, 0.0]
    poses[1, :3, 3] = [620_000.0 + 0.001, 5_735_000.0 + 0.002, 0.0]
    scans = [np.array([[1.0, 2.0, 3.0]]), np.array([[0.0, 0.0, 0.0]])]
    local = accumulate(poses, scans, [0, 1], poses[0, :3, 3])
    # Millimetres survive next to 5.7e6 m (float32 UTM would be off by up to 0.25 m); the only
    # loss is the 15 nm snapping grid.
    np.testing.assert_allclose(local, [[1.0, 2.0, 3.0], [0.001, 0.002, 0.0]], atol=1e-7)
    boxed = accumulate(poses, scans, [0, 1], poses[0, :3, 3], box_m=2.0)
    np.testing.assert_allclose(boxed, [[0.001, 0.002, 0.0]], atol=1e-7)


def test_scan_cache_drops_bad_points_and_caps_range_and_count() -> None:
    pts = np.array(
        [[1.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [0.0, 3.0, 4.0], [0.0, 6.0, 8.0], [np.inf, 0, 0]],
        dtype=np.float32,
    )
    drive = ListDrive([pts], np.eye(4)[None], [0])
    assert isinstance(drive, Drive)
    got = ScanCache(drive, seed=0, max_points_per_scan=None, max_range_m=5.0).get(0)
    assert got.dtype == np.float64
    np.testing.assert_array_equal(got, [[1.0, 0.0, 0.0], [0.0, 3.0, 4.0]])
    big = np.random.default_rng(0).normal(size=(1000, 3))
    drive = ListDrive([big], np.eye(4)[None], [0])
    first = ScanCache(drive, seed=3, max_points_per_scan=100, max_range_m=None).get(0)
    again = ScanCache(drive, seed=3, max_points_per_scan=100, max_range_m=None).get(0)
    other = ScanCache(drive, seed=4, max_points_per_scan=100, max_range_m=None).get(0)
    assert first.shape == (100, 3) and np.array_equal(first, again)
    assert not np.array_equal(first, other)
    # A subset of the scan's rows, in their original order.
    rows = [int(np.nonzero((big == r).all(axis=1))[0][0]) for r in first]
    assert rows == sorted(rows)
