"""data.frames: the frame sidecar reads back exactly what was written, and every bad row is
refused naming the file and the line."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.frames import (
    SubmapFrame,
    check_frames,
    frames_path,
    pose_matrix,
    read_frames_csv,
    write_frames_csv,
)
from pnvlad_service.errors import InputError


def _frames() -> list[SubmapFrame]:
    rng = np.random.default_rng(0)
    return [
        SubmapFrame(
            1_000_000 + k,
            np.array([620_000.0, 5_735_000.0, 40.0]) + rng.normal(size=3),
            rng.normal(size=3),
            float(rng.uniform(5, 20)) * (-1 if k == 2 else 1),
            "enu",
            None if k == 1 else rng.normal(size=3) * 1e5,
            None if k == 1 else float(rng.uniform(-180, 180)),
            None if k == 3 else np.array([rng.uniform(-180, 180), 7.5, rng.normal() * 30]),
        )
        for k in range(4)
    ]


def test_round_trip_is_exact(tmp_path: Path) -> None:
    path = frames_path(tmp_path / "pointcloud_locations_20m.csv")
    assert path.name == "pointcloud_locations_20m.frames.csv"
    frames = _frames()
    write_frames_csv(path, frames)
    back = read_frames_csv(path)
    assert len(back) == len(frames)
    for a, b in zip(frames, back, strict=True):
        assert a.timestamp == b.timestamp and a.scale == b.scale and a.frame == b.frame
        assert np.array_equal(a.origin, b.origin) and np.array_equal(a.centre, b.centre)
        if a.true_position is None:
            assert b.true_position is None and b.true_yaw_deg is None and b.true_pose is None
        else:
            assert np.array_equal(a.true_position, b.true_position)
            assert a.true_yaw_deg == b.true_yaw_deg
        if a.motion is None:
            assert b.motion is None and b.sweep_motion is None
        else:
            assert np.array_equal(a.motion, b.motion)
            np.testing.assert_allclose(
                b.sweep_motion, [math.radians(a.motion[0]), 7.5, math.radians(a.motion[2])]
            )


def test_local_metres_and_poses_by_hand() -> None:
    f = SubmapFrame(1, np.array([10.0, 20.0, 3.0]), np.array([1.0, 2.0, 0.5]), 8.0, "enu",
                    np.array([100.0, 200.0, 4.0]), 90.0)  # fmt: skip
    # local = centre + scale * bin
    assert np.allclose(f.local_m(np.array([[0.5, -0.25, 0.0]])), [[5.0, 0.0, 0.5]])
    # yaw 90 degrees: local x (east) truly points north.
    p = f.true_pose @ np.array([1.0, 0.0, 0.0, 1.0])
    assert np.allclose(p[:3], [100.0, 201.0, 4.0])
    assert np.allclose(f.map_pose[:3, 3], [10.0, 20.0, 3.0])
    assert np.allclose(
        pose_matrix(np.zeros(3), 30.0)[:2, :2], [[0.8660254, -0.5], [0.5, 0.8660254]]
    )


HEADER = (
    "timestamp,origin_easting,origin_northing,origin_height,centre_x,centre_y,centre_z,scale,"
    "frame,true_easting,true_northing,true_height,true_yaw_deg,heading_deg,speed_mps,yaw_rate_dps"
)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("1,0,0,0,0,0,0,abc,enu,,,,", "line 2: scale 'abc' is not a number"),
        ("1,0,0,0,0,0,0,0,enu,,,,", "line 2: scale is 0"),
        ("1,0,0,0,0,0,nan,1,enu,,,,", "line 2: centre_z is not finite"),
        ("x,0,0,0,0,0,0,1,enu,,,,", "line 2: timestamp 'x' is not an integer"),
        ("1,0,0,0,0,0,0,1,sensor,,,,", "line 2: frame 'sensor' is not one of"),
        ("1,0,0,0,0,0,0,1,enu,1,2,,", "line 2: the true pose needs all of"),
        ("1,0,0,0,0,0,0,1,enu,,,,,10,,", "line 2: the motion needs all of heading_deg"),
        ("1,0,0,0,0,0,0,1,enu,,,,,10,x,3", "line 2: speed_mps 'x' is not a number"),
        ("1,0,0,0,0,0,0,1,enu,,,,,10,5,inf", "line 2: yaw_rate_dps is not finite"),
    ],
)
def test_bad_rows_name_the_file_and_line(tmp_path: Path, row: str, message: str) -> None:
    path = tmp_path / "a.frames.csv"
    path.write_text(f"{HEADER}\n{row}\n")
    with pytest.raises(InputError, match=message) as exc:
        read_frames_csv(path)
    assert str(path) in str(exc.value)


def test_missing_column_and_timestamps_that_disagree(tmp_path: Path) -> None:
    path = tmp_path / "a.frames.csv"
    path.write_text("timestamp,scale\n1,2\n")
    with pytest.raises(InputError, match="missing column"):
        read_frames_csv(path)
    write_frames_csv(path, _frames())
    ts = [f.timestamp for f in _frames()]
    assert len(check_frames(path, ts)) == 4
    with pytest.raises(InputError, match="4 rows where the locations CSV has 3"):
        check_frames(path, ts[:3])
    with pytest.raises(InputError, match="line 3: timestamp 1000001 where the locations CSV has 7"):
        check_frames(path, [ts[0], 7, ts[2], ts[3]])


def test_journal_round_trip_stops_at_a_line_cut_short(tmp_path: Path) -> None:
    from pnvlad_service.data.frames import journal_line, read_journal

    frames = _frames()
    text = "".join(journal_line(f) for f in frames)
    path = tmp_path / "j.jsonl"
    path.write_text(text + journal_line(frames[0])[:20])  # a crash mid-line
    back = read_journal(path)
    assert [f.timestamp for f in back] == [f.timestamp for f in frames]
    for a, b in zip(frames, back, strict=True):
        assert np.array_equal(a.origin, b.origin) and a.scale == b.scale
        assert (a.true_position is None) == (b.true_position is None)
        assert (a.motion is None and b.motion is None) or np.array_equal(a.motion, b.motion)
