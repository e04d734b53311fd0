"""A followed drive (localization/follow.py) with the stand-in service: the rows, their errors
and off-map distances, the CSV, the summary's figures recomputed from the rows, the PNG."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.follow import (
    COLUMNS,
    follow_drive,
    plot_follow,
    read_follow_csv,
    stage_means,
    summarise_follow,
    write_follow_csv,
)
from pnvlad_service.localization.prior import MapPositions
from pnvlad_service.localization.tracking import TrackerConfig
from tests.localization.stand_in import DT_US, STEP_M, Service, cloud, odometry, truth

N = 44


class StandInDrive:
    """``N`` scans: ``poses`` the odometry (in its own frame), the points name the scan."""

    name = "stand-in"

    def __init__(self, n: int = N) -> None:
        self.timestamps = np.array([1_000_000_000 + DT_US * i for i in range(n)], dtype=np.int64)
        self.poses = np.stack([odometry(i) for i in range(n)])

    def scan(self, i: int) -> np.ndarray:
        return cloud(i)


def true_poses(n: int = N) -> np.ndarray:
    return np.stack([truth(i) for i in range(n)])


def map_without(hole: range, n: int = N) -> MapPositions:
    """A map of an entry at every scan's true place but those of ``hole``, and a far one."""
    keep = [i for i in range(n) if i not in hole]
    ne = np.array([[truth(i)[1, 3], truth(i)[0, 3]] for i in keep] + [[0.0, 0.0]])
    return MapPositions(ne[:, 0], ne[:, 1], np.array(["city/a"] * len(ne)))


def followed(**kw) -> tuple[list, Service]:
    svc = Service(right={2, 3, 30, 31}, off_map=set(range(18, 27)))
    rows = follow_drive(StandInDrive(), svc, truth=true_poses(), progress=False,
                        positions=map_without(range(18, 27)), **kw)  # fmt: skip
    return rows, svc


def test_rows_states_errors_and_off_map() -> None:
    rows, _ = followed()
    assert [r.scan for r in rows] == list(range(N))
    assert [r.time_s for r in rows] == pytest.approx([i * DT_US / 1e6 for i in range(N)])
    assert rows[3].how == "fix" and rows[3].event == "fix"
    for r in rows:
        t = truth(r.scan)
        assert (r.true_easting, r.true_northing) == (t[0, 3], t[1, 3])
        if r.pose_easting is not None:
            expected = math.hypot(r.pose_easting - t[0, 3], r.pose_northing - t[1, 3])
            assert r.pose_error_m == pytest.approx(expected, abs=1e-9)
            assert r.pose_error_m < 1e-6  # exact odometry and an exact service
        # The map's nearest entry: the scan's own place, or the hole's edge.
        inside = [i for i in range(N) if i not in range(18, 27)]
        nearest = min(math.dist(t[:2, 3], truth(i)[:2, 3]) for i in inside)
        assert r.off_map_m == pytest.approx(nearest, abs=1e-6)
    assert rows[20].event == "lost" and rows[31].event == "relocalised"
    assert rows[31].driven_m == pytest.approx(
        sum(math.dist(truth(i)[:2, 3], truth(i + 1)[:2, 3]) for i in range(31))
    )
    assert all(r.asked == ("prior" if r.state == "tracking" and r.how != "fix" else r.asked)
               for r in rows)  # fmt: skip
    assert {r.asked for r in rows} == {"search", "prior"}


def test_summary_figures_recomputed_from_the_rows() -> None:
    rows, _ = followed()
    s = summarise_follow(rows, wall_s=2.0, off_map_m=3.0)
    after = rows[3:]
    verified = [r for r in after if r.verified]
    assert (s.first_fix_scan, s.first_fix_s) == (3, pytest.approx(3 * DT_US / 1e6))
    assert s.first_fix_m == pytest.approx(3 * STEP_M)
    assert s.verified_share == pytest.approx(len(verified) / len(after))
    assert s.good_share == pytest.approx(len(verified) / len(after))  # all exact
    assert s.wrong == 0 and s.median_error_m == pytest.approx(0.0, abs=1e-6)
    assert (s.relocalisations, s.lost, s.resets) == (1, 1, 0)
    off = [r for r in rows if r.off_map_m > 3.0]
    assert s.off_map == len(off) and s.off_map_verified == 0
    # Left the map at its first scan off it, said lost at scan 20 (1 scan later, already 5 m
    # off); back on the map at the scan after the last one off it, a fix at scan 31.
    first_off, last_off = off[0], off[-1]
    assert [r.scan for r in off] == list(range(first_off.scan, last_off.scan + 1))
    assert s.to_lost == (
        (20 - first_off.scan, pytest.approx(rows[20].time_s - first_off.time_s),
         pytest.approx(rows[20].off_map_m)),
    )  # fmt: skip
    back = rows[last_off.scan + 1]
    assert s.back_to_fix == (
        (31 - back.scan, pytest.approx(rows[31].time_s - back.time_s),
         pytest.approx(rows[31].driven_m - back.driven_m)),
    )  # fmt: skip
    assert s.to_fix == ((11, pytest.approx(11 * DT_US / 1e6), pytest.approx(
        rows[31].driven_m - rows[20].driven_m)),)  # fmt: skip
    assert s.scans_per_s == N / 2.0 and s.realtime == pytest.approx(rows[-1].time_s / 2.0)
    line = s.line()
    assert line.startswith(f"follow: {N} scans in 2.0 s (22.0 scans/s, ")
    assert (
        "first fix at scan 3 (7.5 m, 0.8 s)" in line and "1 relocalisations, lost 1 times" in line
    )
    assert f"{s.off_map} scans off the map, 0 verified there" in line
    assert f"; lost +1 scans (+0.2 s, {rows[20].off_map_m:.0f} m off) from leaving the map" in line
    assert f"; a fix {31 - back.scan} scans (" in line


def test_csv_round_trip_and_the_png(tmp_path: Path) -> None:
    rows, _ = followed()
    path = write_follow_csv(rows, tmp_path / "f.csv")
    with open(path, newline="") as fh:
        back = list(csv.DictReader(fh))
    assert tuple(back[0]) == COLUMNS and len(back) == N
    assert [b["state"] for b in back] == [r.state for r in rows]
    assert [b["verified"] == "true" for b in back] == [r.verified for r in rows]
    assert float(back[10]["pose_northing"]) == pytest.approx(rows[10].pose_northing)
    again = read_follow_csv(path)
    assert summarise_follow(again, 2.0, 3.0).line() == summarise_follow(rows, 2.0, 3.0).line()
    assert [a.reason for a in again] == [r.reason for r in rows]
    png = plot_follow(rows, tmp_path / "f.png", map_ne=np.c_[[5735000.0], [620000.0]])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    means = stage_means(rows)
    assert set(means) == {"search", "prior"}
    assert means["prior"]["scans"] == sum(r.asked == "prior" for r in rows)


def test_odometry_choices_and_bad_arguments() -> None:
    svc = Service(right={0, 1})
    rows = follow_drive(StandInDrive(8), svc, odometry="none", progress=False,
                        config=TrackerConfig(confirm=2))  # fmt: skip
    assert rows[1].how == "fix" and all(r.verified for r in rows[1:])
    assert all(r.pose_error_m is None for r in rows)  # no truth given
    rows = follow_drive(StandInDrive(8), Service(right={0, 2}), every=2, progress=False)
    assert [r.scan for r in rows] == [0, 2, 4, 6] and rows[1].how == "fix"
    with pytest.raises(InputError, match="every"):
        follow_drive(StandInDrive(), svc, every=0)
    with pytest.raises(InputError, match="true poses"):
        follow_drive(StandInDrive(), svc, truth=true_poses(3))

    no_poses = StandInDrive()
    no_poses.poses = None
    with pytest.raises(InputError, match="no poses"):
        follow_drive(no_poses, svc, odometry="poses")
    with pytest.raises(InputError, match="no rows"):
        summarise_follow([], 1.0)


def test_a_jump_of_the_truth_is_timed_to_lost_and_to_the_next_fix() -> None:
    from pnvlad_service.localization.follow import FollowRow

    rows = []
    for i in range(12):
        jumped = 400.0 if i >= 5 else 0.0
        r = FollowRow(i, i * 100_000, i * 0.1, true_northing=5735000.0 + i + jumped,
                      true_easting=620000.0)  # fmt: skip
        r.state, r.how = ("tracking", "registered") if i < 7 else ("searching", None)
        r.verified = i < 7
        rows.append(r)
    rows[7].event, rows[7].state = "lost", "lost"
    rows[7].verified = False
    rows[10].how, rows[10].event, rows[10].state = "fix", "relocalised", "tracking"
    rows[10].verified = True
    s = summarise_follow(rows, 1.0)
    assert s.jumps == ((2, pytest.approx(0.2), 5, pytest.approx(0.5)),)
    assert "the truth jumped: lost 2 scans (0.2 s) after it, a fix 5 scans (0.5 s) after it" in (
        s.line()
    )


def test_a_scan_without_truth_has_no_errors_and_the_distance_goes_on() -> None:
    truth = true_poses()
    truth[10] = np.nan  # the truth topic had no pose for scan 10
    rows = follow_drive(StandInDrive(), Service(right={2, 3}), truth=truth, progress=False)
    assert rows[10].true_northing is None and rows[10].pose_error_m is None
    assert rows[9].pose_error_m is not None and rows[11].pose_error_m is not None
    driven = [r.driven_m for r in rows if r.driven_m is not None]
    assert len(driven) == N - 1 and all(np.isfinite(driven)) and driven == sorted(driven)
