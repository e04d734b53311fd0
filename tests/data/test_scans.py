"""data.scans: raw single scans of a run folder (KITTI .bin files and raw_scans.csv).

Pose conventions are checked against rotations written out by hand (intrinsic z-y'-x'': yaw
about up, then pitch, then roll; yaw 0 faces east, counter-clockwise positive); files are read
back with numpy and the csv module, not with the code under test.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data.scans import (
    COLUMNS,
    RAW_CSV,
    RAW_FOLDER,
    TRUE_COLUMNS,
    has_raw_scans,
    pose_matrix,
    pose_values,
    read_raw_scans,
    write_raw_scans_csv,
    write_scan,
)
from pnvlad_service.errors import InputError


def by_hand(north: float, east: float, height: float, yaw: float, pitch: float, roll: float):
    """float64 [4, 4]: Rz(yaw) @ Ry(pitch) @ Rx(roll) (degrees), at (east, north, height)."""
    y, p, r = (math.radians(v) for v in (yaw, pitch, roll))
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    out = np.eye(4)
    out[:3, :3] = rz @ ry @ rx
    out[:3, 3] = (east, north, height)
    return out


positions = st.floats(-1e7, 1e7, allow_nan=False)
pose_strategy = st.tuples(
    positions,
    positions,
    st.floats(-1e4, 1e4),
    st.floats(-179.0, 179.0),
    st.floats(-60.0, 60.0),
    st.floats(-60.0, 60.0),
)


# --------------------------------------------------------------------------------------------
# pose_values / pose_matrix


@settings(max_examples=150, deadline=None)
@given(values=pose_strategy)
def test_pose_round_trip(values: tuple[float, ...]) -> None:
    m = by_hand(*values)
    np.testing.assert_allclose(pose_matrix(values), m, rtol=0, atol=1e-9)
    back = pose_values(m)
    # Positions are copied, not computed: exact. Angles within 1e-7 degrees.
    assert back[:3] == [values[0], values[1], values[2]]
    np.testing.assert_allclose(back[3:], values[3:], rtol=0, atol=1e-7)
    np.testing.assert_allclose(pose_matrix(back), m, rtol=0, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(yaw=st.floats(-179.0, 179.0))
def test_pure_yaw_has_no_pitch_or_roll(yaw: float) -> None:
    values = pose_values(by_hand(10.0, 20.0, 0.0, yaw, 0.0, 0.0))
    assert values[3] == pytest.approx(yaw, abs=1e-9)
    assert values[4] == pytest.approx(0.0, abs=1e-9)
    assert values[5] == pytest.approx(0.0, abs=1e-9)


def test_yaw_convention_east_zero_counter_clockwise() -> None:
    # Yaw 0: the sensor's x axis points east; yaw 90: north; yaw -90: south.
    np.testing.assert_allclose(pose_matrix([0, 0, 0, 0, 0, 0])[:3, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(pose_matrix([0, 0, 0, 90, 0, 0])[:3, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(pose_matrix([0, 0, 0, -90, 0, 0])[:3, 0], [0, -1, 0], atol=1e-12)
    # Northing is world y, easting world x.
    m = pose_matrix([5_700_000.5, 620_000.25, 112.0, 0, 0, 0])
    assert m[:3, 3].tolist() == [620_000.25, 5_700_000.5, 112.0]
    assert pose_values(m)[:3] == [5_700_000.5, 620_000.25, 112.0]


# --------------------------------------------------------------------------------------------
# write_scan


def test_write_scan_is_kitti_float32x4(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    xyz = rng.normal(0.0, 30.0, size=(257, 3))
    write_scan(tmp_path / "a.bin", xyz)
    got = np.fromfile(tmp_path / "a.bin", dtype="<f4")
    assert got.size == 257 * 4
    got = got.reshape(-1, 4)
    np.testing.assert_array_equal(got[:, :3], xyz.astype(np.float32))
    assert (got[:, 3] == 0).all()  # no intensity given
    xyzi = np.column_stack([xyz, rng.uniform(0, 1, 257), rng.normal(size=257)])  # [N, 5]
    write_scan(tmp_path / "b.bin", xyzi)
    got = np.fromfile(tmp_path / "b.bin", dtype="<f4").reshape(-1, 4)
    np.testing.assert_array_equal(got, xyzi[:, :4].astype(np.float32))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin"]


@pytest.mark.parametrize(
    "bad",
    [
        np.array([[1.0, 2.0, np.nan]]),
        np.array([[1.0, 2.0, 3.0, np.inf]]),
        np.array([[1.0, 2.0, 3.0], [1e39, 0.0, 0.0]]),  # finite, but not as float32
        np.zeros((0, 3)),
        np.zeros((0, 4)),
        np.zeros((5, 2)),
        np.zeros(6),
        np.zeros((2, 3, 4)),
    ],
    ids=["nan", "inf", "float32-overflow", "empty3", "empty4", "two-columns", "1d", "3d"],
)
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
def test_write_scan_refuses_and_leaves_no_file(tmp_path: Path, bad: np.ndarray) -> None:
    path = tmp_path / "scans" / "s.bin"
    with pytest.raises(InputError) as exc:
        write_scan(path, bad)
    assert exc.value.source == str(path)
    assert not path.exists()
    assert not path.parent.exists() or list(path.parent.iterdir()) == []


def test_write_scan_refused_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "s.bin"
    write_scan(path, np.ones((3, 3)))
    before = path.read_bytes()
    with pytest.raises(InputError):
        write_scan(path, np.full((3, 3), np.nan))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.bin"]


# --------------------------------------------------------------------------------------------
# raw_scans.csv


def make_run(tmp_path: Path, n: int, truth: list[bool]) -> tuple[Path, list]:
    """A run folder of ``n`` raw scans and their CSV; row k has a true pose when truth[k]."""
    rng = np.random.default_rng(n)
    run = tmp_path / "run"
    rows = []
    for k in range(n):
        stamp = 1_600_000_000_000_000 + 100_000 * k
        values = (
            5_700_000.0 + rng.uniform(0, 500),
            620_000.0 + rng.uniform(0, 500),
            rng.uniform(100, 120),
            rng.uniform(-179, 179),
            rng.uniform(-10, 10),
            rng.uniform(-10, 10),
        )
        true = by_hand(*(v + rng.normal(0, 0.5) for v in values)) if truth[k] else None
        rows.append((stamp, by_hand(*values), true))
        write_scan(run / RAW_FOLDER / f"{stamp}.bin", rng.normal(size=(50, 3)))
    write_raw_scans_csv(run / RAW_CSV, rows)
    return run, rows


def csv_rows(path: Path) -> list[list[str]]:
    with path.open(newline="", encoding="utf-8") as fh:
        return list(csv.reader(fh))


def test_raw_scans_round_trip_with_true_poses(tmp_path: Path) -> None:
    run, rows = make_run(tmp_path, 4, [True] * 4)
    assert has_raw_scans(run)
    table = csv_rows(run / RAW_CSV)
    assert table[0] == [*COLUMNS, *TRUE_COLUMNS]
    # The CSV's own numbers: northing is the pose's y, easting its x.
    assert float(table[1][1]) == rows[0][1][1, 3]
    assert float(table[1][2]) == rows[0][1][0, 3]
    assert float(table[1][7]) == rows[0][2][1, 3]
    got = read_raw_scans(run)
    assert [s.timestamp for s in got] == [r[0] for r in rows]
    for scan, (stamp, recorded, true) in zip(got, rows, strict=True):
        assert scan.path == run / RAW_FOLDER / f"{stamp}.bin"
        np.testing.assert_allclose(scan.pose, recorded, rtol=0, atol=1e-9)
        np.testing.assert_allclose(scan.true_pose, true, rtol=0, atol=1e-9)
        assert scan.northing == recorded[1, 3] and scan.easting == recorded[0, 3]


@pytest.mark.parametrize("truth", [[False] * 3, [True, False, True]])
def test_raw_scans_true_columns_only_when_every_row_has_one(
    tmp_path: Path, truth: list[bool]
) -> None:
    run, rows = make_run(tmp_path, 3, truth)
    assert csv_rows(run / RAW_CSV)[0] == list(COLUMNS)
    got = read_raw_scans(run)
    assert all(s.true_pose is None for s in got)
    for scan, (_, recorded, _) in zip(got, rows, strict=True):
        np.testing.assert_allclose(scan.pose, recorded, rtol=0, atol=1e-9)


def test_no_rows_and_blank_lines(tmp_path: Path) -> None:
    write_raw_scans_csv(tmp_path / RAW_CSV, [])
    assert csv_rows(tmp_path / RAW_CSV) == [list(COLUMNS)]
    assert read_raw_scans(tmp_path) == []
    run, rows = make_run(tmp_path / "b", 2, [False, False])
    text = (run / RAW_CSV).read_text()
    (run / RAW_CSV).write_text(text.replace("\n", "\n\n", 1) + ",,,\n")
    assert [s.timestamp for s in read_raw_scans(run)] == [r[0] for r in rows]
    assert not has_raw_scans(tmp_path / "nowhere")


def replace_field(path: Path, line: int, column: str, value: str) -> None:
    table = csv_rows(path)
    table[line - 1][table[0].index(column)] = value
    path.write_text("".join(",".join(r) + "\n" for r in table))


@pytest.mark.parametrize(
    ("column", "value", "says"),
    [
        ("yaw_deg", "north-east", "non-numeric"),
        ("easting", "", "non-numeric"),
        ("timestamp", "12.5", "non-numeric"),
        ("true_height", "abc", "non-numeric"),
        ("pitch_deg", "nan", "not finite"),
        ("true_roll_deg", "inf", "not finite"),
    ],
)
def test_a_bad_value_names_the_file_and_line(
    tmp_path: Path, column: str, value: str, says: str
) -> None:
    run, _ = make_run(tmp_path, 3, [True] * 3)
    replace_field(run / RAW_CSV, 3, column, value)
    with pytest.raises(InputError) as exc:
        read_raw_scans(run)
    assert exc.value.source == str(run / RAW_CSV)
    assert "line 3" in str(exc.value) and says in str(exc.value)


def test_a_missing_scan_file_names_the_file_and_line(tmp_path: Path) -> None:
    run, rows = make_run(tmp_path, 3, [False] * 3)
    (run / RAW_FOLDER / f"{rows[1][0]}.bin").unlink()
    with pytest.raises(InputError) as exc:
        read_raw_scans(run)
    assert "line 3" in str(exc.value)
    assert f"{rows[1][0]}.bin" in str(exc.value)
    assert str(run / RAW_FOLDER) in str(exc.value)


def test_a_missing_column_or_file_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_raw_scans(tmp_path)
    run, _ = make_run(tmp_path, 2, [False] * 2)
    table = csv_rows(run / RAW_CSV)
    (run / RAW_CSV).write_text("".join(",".join(r[:-1]) + "\n" for r in table))  # no roll
    with pytest.raises(InputError, match="roll_deg") as exc:
        read_raw_scans(run)
    assert exc.value.source == str(run / RAW_CSV)
