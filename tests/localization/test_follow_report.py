"""What is made of a tracked drive's rows (localization/drive/rows.py, report.py, plot.py), on
the stand-in drive followed: the CSV and back, the summary's figures recomputed from the rows,
the stages' times, the PNG."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.plot import plot_drive
from pnvlad_service.localization.drive.report import stage_means, summarise
from pnvlad_service.localization.drive.rows import COLUMNS, DriveRow, read_rows, write_rows
from tests.localization.stand_in import DT_US, STEP_M, N, followed


def test_summary_figures_recomputed_from_the_rows() -> None:
    rows, _ = followed()
    s = summarise(rows, "tracked", 2.0, off_map_m=3.0)
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
    path = write_rows(rows, tmp_path / "f.csv", "tracked")
    with open(path, newline="") as fh:
        back = list(csv.DictReader(fh))
    assert tuple(back[0]) == COLUMNS["tracked"] and len(back) == N
    assert [b["state"] for b in back] == [r.state for r in rows]
    assert [b["verified"] == "true" for b in back] == [r.verified for r in rows]
    assert float(back[10]["pose_northing"]) == pytest.approx(rows[10].pose_northing)
    again = read_rows(path)
    assert summarise(again, "tracked", 2.0, off_map_m=3.0).line() == (
        summarise(rows, "tracked", 2.0, off_map_m=3.0).line()
    )
    assert [a.reason for a in again] == [r.reason for r in rows]
    png = plot_drive(rows, tmp_path / "f.png", "tracked", map_ne=np.c_[[5735000.0], [620000.0]])
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    means = stage_means(rows)
    assert set(means) == {"search", "prior"}
    assert means["prior"]["scans"] == sum(r.asked == "prior" for r in rows)


def test_a_jump_of_the_truth_is_timed_to_lost_and_to_the_next_fix() -> None:
    rows = []
    for i in range(12):
        jumped = 400.0 if i >= 5 else 0.0
        r = DriveRow(i, i * 100_000, i * 0.1, true_northing=5735000.0 + i + jumped,
                      true_easting=620000.0)  # fmt: skip
        r.state, r.how = ("tracking", "registered") if i < 7 else ("searching", None)
        r.verified = i < 7
        rows.append(r)
    rows[7].event, rows[7].state = "lost", "lost"
    rows[7].verified = False
    rows[10].how, rows[10].event, rows[10].state = "fix", "relocalised", "tracking"
    rows[10].verified = True
    s = summarise(rows, "tracked", 1.0)
    assert s.jumps == ((2, pytest.approx(0.2), 5, pytest.approx(0.5)),)
    assert "the truth jumped: lost 2 scans (0.2 s) after it, a fix 5 scans (0.5 s) after it" in (
        s.line()
    )


def test_no_rows_to_summarise() -> None:
    with pytest.raises(InputError, match="no rows"):
        summarise([], "tracked", 1.0)
