"""data.accumulate: scans laid into one cloud, offline (accumulate, spaced_scans, prepare's
ScanCache) and online (WindowAccumulator).

Drives here are hand-made: poses built from yaw, pitch and roll with plain 3x3 matrices, scans
of random points. Expected clouds are worked out with the 4x4 matrices (inv(P_newest) · P_i),
and the scans a window should hold from the positions, with a plain loop.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data.accumulate import (
    ScanCache,
    WindowAccumulator,
    accumulate,
    scan_subset,
    spaced_scans,
    travelled_distance,
)
from pnvlad_service.data.drive import Drive
from pnvlad_service.errors import InputError
from tests.data.helpers import ListDrive

#: Positions are put on this grid (exact in binary, on the library's 2**-26 m snapping grid),
#: so that snapping changes nothing and clouds can be compared within 1e-9 m.
GRID_M = 2.0**-10


def rotation(yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll), radians, written out by hand."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def pose(position: np.ndarray, yaw: float, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation(yaw, pitch, roll)
    out[:3, 3] = position
    return out


def make_drive(
    seed: int, n: int, step: tuple[float, float] = (0.3, 1.2)
) -> tuple[np.ndarray, list[np.ndarray]]:
    """A winding drive of ``n`` scans: poses float64 [n, 4, 4] (positions on :data:`GRID_M`,
    some pitch and roll) and scans of 20-60 random points each (sensor frame, metres)."""
    rng = np.random.default_rng(seed)
    poses, scans = [], []
    xy, heading = np.array([12.0, -7.0]), 0.3
    for _ in range(n):
        z = rng.uniform(-0.5, 0.5)
        position = np.round(np.array([xy[0], xy[1], z]) / GRID_M) * GRID_M
        poses.append(pose(position, heading, rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)))
        scans.append(rng.normal(0.0, 10.0, size=(int(rng.integers(20, 61)), 3)))
        heading += rng.uniform(-0.2, 0.2)
        xy = xy + rng.uniform(*step) * np.array([math.cos(heading), math.sin(heading)])
    return np.stack(poses), scans


def distances(poses: np.ndarray) -> list[float]:
    """Travelled horizontal distance at each pose, summed step by step."""
    out = [0.0]
    for a, b in itertools.pairwise(poses):
        out.append(out[-1] + math.hypot(b[0, 3] - a[0, 3], b[1, 3] - a[1, 3]))
    return out


def window_indices(d: list[float], newest: int, window_m: float) -> list[int]:
    """The scans up to ``newest`` within ``window_m`` of travel of it."""
    return [i for i in range(newest + 1) if d[newest] - d[i] <= window_m]


def in_frame(frame_pose: np.ndarray, scan_pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` of the scan at ``scan_pose`` in the frame of ``frame_pose``:
    inv(frame_pose) · scan_pose applied to homogeneous points."""
    h = np.column_stack([points, np.ones(len(points))])
    return (np.linalg.inv(frame_pose) @ scan_pose @ h.T).T[:, :3]


def split(cloud: np.ndarray, sizes: list[int]) -> list[np.ndarray]:
    assert len(cloud) == sum(sizes), f"cloud of {len(cloud)} rows, scans of {sum(sizes)}"
    return np.split(cloud, np.cumsum(sizes)[:-1])


# --------------------------------------------------------------------------------------------
# travelled_distance, spaced_scans


def test_travelled_distance_is_horizontal_and_cumulative() -> None:
    poses = np.stack(
        [
            pose(np.array(p, dtype=float), 0.0)
            for p in [(0, 0, 0), (3, 4, 0), (3, 4, 10), (6, 8, -2), (6, 8, -2)]
        ]
    )
    # Height changes do not count: 5 m, 0 m, 5 m, 0 m.
    np.testing.assert_allclose(travelled_distance(poses), [0.0, 5.0, 5.0, 10.0, 10.0])


def test_spaced_scans_by_hand() -> None:
    d = np.array([0.0, 0.25, 0.75, 1.0, 2.0, 2.5])  # exact in binary
    # Kept: 0; 0.25 < 0.5 after 0; 0.75; 1.0 is 0.25 after 0.75; 2.0; 2.5 is exactly 0.5 on.
    assert spaced_scans(d, 0.5).tolist() == [True, False, True, False, True, True]
    assert spaced_scans(d, 0.0).all()
    assert spaced_scans(d, 100.0).tolist() == [True] + [False] * 5


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.floats(0.0, 3.0), min_size=1, max_size=40),
    spacing=st.floats(0.0, 2.0),
)
def test_spaced_scans_invariants(steps: list[float], spacing: float) -> None:
    d = np.concatenate([[0.0], np.cumsum(steps)])
    keep = spaced_scans(d, spacing)
    assert keep[0]
    kept = np.flatnonzero(keep)
    # Kept scans are at least ``spacing`` apart, and every dropped one is closer than that to
    # the kept one before it (otherwise it would have been kept).
    assert (np.diff(d[kept]) >= spacing).all()
    for i in np.flatnonzero(~keep):
        before = kept[kept < i][-1]
        assert d[i] - d[before] < spacing


# --------------------------------------------------------------------------------------------
# accumulate, scan_subset


def test_accumulate_by_hand() -> None:
    poses = np.stack(
        [pose(np.array([100.0, 200.0, 1.0]), 0.0), pose(np.array([104.0, 200.0, 1.0]), math.pi / 2)]
    )
    scans = [np.array([[1.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0], [0.0, 3.0, 2.0]])]
    centre = np.array([102.0, 201.0, 0.0])
    out = accumulate(poses, scans, [0, 1], centre)
    # Scan 1 faces north: its x is world north, its y world west; offsets from the centre
    # (-2, -1, 1) and (2, -1, 1).
    expected = [[-1.0, -1.0, 1.0], [2.0, 0.0, 1.0], [-1.0, -1.0, 3.0]]
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # Only scan 1; and a 2.5 m box about the centre keeps |x|, |y| <= 1.25.
    np.testing.assert_allclose(accumulate(poses, scans, [1], centre), expected[1:], atol=1e-12)
    np.testing.assert_allclose(
        accumulate(poses, scans, [0, 1], centre, box_m=2.5),
        [[-1.0, -1.0, 1.0], [-1.0, -1.0, 3.0]],
        atol=1e-12,
    )
    assert accumulate(poses, scans, [], centre).shape == (0, 3)


def test_accumulate_keeps_precision_at_utm_coordinates() -> None:
    poses, scans = make_drive(seed=5, n=6)
    far = poses.copy()
    far[:, :3, 3] += np.array([620_000.123, 5_700_000.456, 110.0])
    centre = poses[3, :3, 3]
    near = accumulate(poses, scans, range(6), centre)
    shift = np.array([620_000.123, 5_700_000.456, 110.0])
    utm = accumulate(far, scans, range(6), centre + shift)
    # Float32 anywhere would be off by decimetres; snapping costs at most ~2 x 2**-26 m.
    np.testing.assert_allclose(utm, near, rtol=0, atol=1e-7)


def test_scan_subset_small_enough_is_the_points_themselves() -> None:
    pts = np.arange(30.0).reshape(10, 3)
    assert scan_subset(pts, 10, (0, 1)) is pts
    assert scan_subset(pts, 50, (0, 1)) is pts
    assert scan_subset(pts, None, (0, 1)) is pts


@settings(max_examples=60, deadline=None)
@given(n=st.integers(2, 400), frac=st.floats(0.0, 0.99), seed=st.integers(0, 2**31 - 1))
def test_scan_subset_is_a_sorted_seeded_subset(n: int, frac: float, seed: int) -> None:
    cap = max(1, int(n * frac))
    if cap >= n:
        cap = n - 1
    pts = np.column_stack([np.arange(n, dtype=float), np.zeros(n), np.ones(n)])  # row i: x = i
    out = scan_subset(pts, cap, (seed, 7))
    assert out.shape == (cap, 3)
    rows = out[:, 0].astype(int)
    # Distinct rows of the input, in file order, untouched.
    assert (np.diff(rows) > 0).all()
    np.testing.assert_array_equal(out, pts[rows])
    np.testing.assert_array_equal(scan_subset(pts, cap, (seed, 7)), out)


def test_scan_subset_depends_on_the_seed() -> None:
    pts = np.random.default_rng(0).normal(size=(1000, 3))
    a, b = scan_subset(pts, 100, (0, 1)), scan_subset(pts, 100, (0, 2))
    assert not np.array_equal(a, b)


# --------------------------------------------------------------------------------------------
# WindowAccumulator


def test_enu_window_is_accumulate_of_the_last_window_m() -> None:
    window_m = 6.0
    poses, scans = make_drive(seed=1, n=30)
    d = distances(poses)
    acc = WindowAccumulator(window_m=window_m, frame="enu")
    for n in range(len(poses)):
        acc.add(scans[n], poses[n])
        # The drive's steps are random: no scan sits on the window's edge.
        assert all(abs(d[n] - d[i] - window_m) > 1e-6 for i in range(n + 1))
        idx = window_indices(d, n, window_m)
        assert acc.scans == len(idx)
        assert acc.span_m == pytest.approx(d[n] - d[idx[0]], abs=1e-9)
        cloud = acc.cloud()
        expected = accumulate(poses, scans, idx, poses[n, :3, 3])
        np.testing.assert_array_equal(cloud, expected)
        # And by hand: R_i p + t_i - t_newest, world axes.
        for i, part in zip(idx, split(cloud, [len(scans[i]) for i in idx]), strict=True):
            by_hand = scans[i] @ poses[i, :3, :3].T + (poses[i, :3, 3] - poses[n, :3, 3])
            np.testing.assert_allclose(part, by_hand, rtol=0, atol=1e-9)
    assert acc.scans < len(poses)  # the window did move on
    np.testing.assert_array_equal(acc.newest_pose, poses[-1])


def test_sensor_window_is_in_the_newest_scans_frame() -> None:
    window_m = 8.0
    poses, scans = make_drive(seed=2, n=25)
    d = distances(poses)
    acc = WindowAccumulator(window_m=window_m, frame="sensor")
    assert WindowAccumulator().frame == "sensor"  # the default
    for n in range(len(poses)):
        acc.add(scans[n], poses[n])
        idx = window_indices(d, n, window_m)
        parts = split(acc.cloud(), [len(scans[i]) for i in idx])
        # The newest scan comes back as it was given.
        np.testing.assert_allclose(parts[-1], scans[n], rtol=0, atol=1e-9)
        for i, part in zip(idx[:-1], parts[:-1], strict=True):
            np.testing.assert_allclose(
                part, in_frame(poses[n], poses[i], scans[i]), rtol=0, atol=1e-9
            )


def test_sensor_window_does_not_depend_on_where_the_drive_is() -> None:
    poses, scans = make_drive(seed=3, n=12)
    moved = poses.copy()
    moved[:, :3, 3] += (620_000.37, 5_700_000.81, 231.0)
    # Turn the whole drive by 70 degrees about the origin as well: the sensor frame cloud
    # holds only relative poses.
    turn = pose(np.zeros(3), math.radians(70.0))
    moved = np.einsum("ij,tjk->tik", turn, moved)
    a, b = WindowAccumulator(window_m=5.0), WindowAccumulator(window_m=5.0)
    for p, q, s in zip(poses, moved, scans, strict=True):
        a.add(s, p)
        b.add(s, q)
    assert a.scans == b.scans > 1
    np.testing.assert_allclose(b.cloud(), a.cloud(), rtol=0, atol=1e-6)


def test_driving_three_windows_evicts_the_oldest_scans() -> None:
    window_m = 5.0
    poses, scans = make_drive(seed=4, n=60, step=(0.2, 0.5))
    d = distances(poses)
    assert d[-1] > 3 * window_m
    # One marker point a scan, at the sensor: the enu cloud then lists the held scans' places.
    markers = [np.zeros((1, 3)) for _ in scans]
    acc = WindowAccumulator(window_m=window_m, frame="enu")
    for n in range(len(poses)):
        acc.add(markers[n], poses[n])
        assert acc.span_m <= window_m
        held = window_indices(d, n, window_m)
        np.testing.assert_allclose(
            acc.cloud(), poses[held, :3, 3] - poses[n, :3, 3], rtol=0, atol=1e-9
        )
    first = window_indices(d, len(poses) - 1, window_m)[0]
    assert first > 0
    # The scan just before the oldest held one is more than a window away.
    assert d[-1] - d[first - 1] > window_m
    acc.clear()
    assert acc.scans == 0 and acc.span_m == 0.0
    with pytest.raises(InputError):
        acc.cloud()


def test_standing_still_keeps_the_first_scan_of_the_stop_and_the_newest() -> None:
    rng = np.random.default_rng(6)
    acc = WindowAccumulator(window_m=10.0, min_spacing_m=0.5)
    base = np.array([3.0, 4.0, 0.0])
    first = None
    for k in range(5):  # jitter of a few centimetres, and turning on the spot
        jitter = np.round(rng.uniform(-0.05, 0.05, 3) / GRID_M) * GRID_M
        p = pose(base + jitter, 0.4 * k)
        last = (rng.normal(size=(40, 3)), p)
        first = first or last
        acc.add(*last)
        assert acc.scans == min(k + 1, 2) and acc.span_m < 0.1
    # The stop's first scan, then its newest (which the next scan replaces), as offline
    # spaced_scans keeps the first and the window's centre scan.
    parts = split(acc.cloud(), [40, 40])
    np.testing.assert_allclose(parts[1], last[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(parts[0], in_frame(last[1], first[1], first[0]), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(acc.newest_pose, last[1])
    # Moving on 2 m keeps the stop's first scan and the new one; the stop's newest gives way.
    moved = pose(base + np.array([2.0, 0.0, 0.0]), 0.0)
    acc.add(np.zeros((1, 3)), moved)
    assert acc.scans == 2
    parts = split(acc.cloud(), [40, 1])
    np.testing.assert_allclose(parts[0], in_frame(moved, first[1], first[0]), rtol=0, atol=1e-9)


def test_creeping_slowly_still_fills_the_window() -> None:
    window_m, spacing = 5.0, 0.05
    acc = WindowAccumulator(window_m=window_m, min_spacing_m=spacing, frame="enu")
    for k in range(250):  # 0.04 m a scan, 10 m in all
        acc.add(np.zeros((1, 3)), pose(np.array([0.04 * k, 0.0, 0.0]), 0.0))
    reach = -acc.cloud()[:, 0].min()  # how far back the oldest held scan really is
    assert acc.scans > 1
    assert window_m - 2 * spacing <= reach <= window_m + 2 * spacing


def test_max_points_per_scan_is_a_seeded_cap() -> None:
    poses, _ = make_drive(seed=7, n=8)
    rng = np.random.default_rng(7)
    scans = [rng.normal(0.0, 10.0, size=(500, 3)) for _ in range(7)] + [rng.normal(size=(30, 3))]

    def run(seed: int) -> WindowAccumulator:
        acc = WindowAccumulator(window_m=100.0, max_points_per_scan=64, seed=seed)
        for p, s in zip(poses, scans, strict=True):
            acc.add(s, p)
        return acc

    a = run(0)
    parts = split(a.cloud(), [64] * 7 + [30])
    np.testing.assert_allclose(parts[-1], scans[-1], rtol=0, atol=1e-9)  # 30 < 64: all kept
    for i, part in enumerate(parts[:-1]):
        # Rows of scan i, each once, in file order.
        full = in_frame(poses[-1], poses[i], scans[i])
        gap = np.abs(part[:, None, :] - full[None, :, :]).max(axis=2)
        rows = gap.argmin(axis=1)
        assert gap.min(axis=1).max() < 1e-9
        assert (np.diff(rows) > 0).all()
    np.testing.assert_array_equal(run(0).cloud(), a.cloud())  # same seed, same subset
    assert not np.array_equal(run(1).cloud(), a.cloud())


def test_max_range_and_non_finite_points_are_dropped() -> None:
    rng = np.random.default_rng(8)
    pts = rng.normal(0.0, 20.0, size=(300, 4))  # a fourth column (intensity) is ignored
    pts[::17, 1] = np.nan
    pts[5, 2] = np.inf
    acc = WindowAccumulator(max_range_m=25.0)
    acc.add(pts, np.eye(4))
    xyz = pts[:, :3]
    keep = np.isfinite(xyz).all(axis=1)
    keep[keep] = np.sqrt((xyz[keep] ** 2).sum(axis=1)) <= 25.0
    assert 0 < keep.sum() < len(pts)
    np.testing.assert_allclose(acc.cloud(), xyz[keep], rtol=0, atol=1e-9)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"window_m": 0.0}, "window_m"),
        ({"window_m": -3.0}, "window_m"),
        ({"window_m": float("nan")}, "window_m"),
        ({"window_m": float("inf")}, "window_m"),
        ({"frame": "utm"}, "frame"),
    ],
)
def test_bad_settings_name_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(InputError) as exc:
        WindowAccumulator(**kwargs)
    assert exc.value.source == field
    assert str(exc.value).startswith(f"{field}: ")


@pytest.mark.parametrize(
    "bad_pose",
    [
        np.where(np.eye(4) == 1, np.nan, 0.0),
        np.array([[1.0, 0, 0, np.inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        np.eye(4)[:3],
        np.eye(3),
    ],
)
def test_a_bad_pose_is_refused_and_not_taken(bad_pose: np.ndarray) -> None:
    acc = WindowAccumulator()
    acc.add(np.ones((5, 3)), np.eye(4))
    with pytest.raises(InputError) as exc:
        acc.add(np.ones((5, 3)), bad_pose)
    assert exc.value.source == "pose"
    assert acc.scans == 1
    np.testing.assert_array_equal(acc.newest_pose, np.eye(4))


def test_cloud_before_any_scan_is_an_input_error() -> None:
    acc = WindowAccumulator()
    assert acc.scans == 0 and acc.span_m == 0.0
    for call in (acc.cloud, lambda: acc.newest_pose):
        with pytest.raises(InputError) as exc:
            call()
        assert exc.value.source == "window"


# --------------------------------------------------------------------------------------------
# Offline, as prepare reads and lays a drive's scans (moved here from test_prepare.py)


def test_travelled_distance_of_a_climb_and_a_stop() -> None:
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
