"""A tracked drive (localization/drive/runner.py, policy ``tracked``) with the stand-in service:
the rows, their errors and off-map distances (their CSV, summary and PNG:
test_follow_report.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.runner import run_drive
from pnvlad_service.localization.drive.tracking import TrackerConfig
from tests.localization.stand_in import (
    DT_US,
    N,
    Service,
    StandInDrive,
    followed,
    true_poses,
    truth,
)


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


def test_odometry_choices_and_bad_arguments() -> None:
    svc = Service(right={0, 1})
    rows = run_drive(StandInDrive(8), svc, "tracked", odometry="none", progress=False,
                        config=TrackerConfig(confirm=2))  # fmt: skip
    assert rows[1].how == "fix" and all(r.verified for r in rows[1:])
    assert all(r.pose_error_m is None for r in rows)  # no truth given
    rows = run_drive(StandInDrive(8), Service(right={0, 2}), "tracked", every=2, progress=False)
    assert [r.scan for r in rows] == [0, 2, 4, 6] and rows[1].how == "fix"
    with pytest.raises(InputError, match="every"):
        run_drive(StandInDrive(), svc, "tracked", every=0)
    with pytest.raises(InputError, match="true poses"):
        run_drive(StandInDrive(), svc, "tracked", truth=true_poses(3))

    no_poses = StandInDrive()
    no_poses.poses = None
    with pytest.raises(InputError, match="no poses"):
        run_drive(no_poses, svc, "tracked", odometry="poses")


def test_a_scan_without_truth_has_no_errors_and_the_distance_goes_on() -> None:
    truth = true_poses()
    truth[10] = np.nan  # the truth topic had no pose for scan 10
    rows = run_drive(StandInDrive(), Service(right={2, 3}), "tracked", truth=truth, progress=False)
    assert rows[10].true_northing is None and rows[10].pose_error_m is None
    assert rows[9].pose_error_m is not None and rows[11].pose_error_m is not None
    driven = [r.driven_m for r in rows if r.driven_m is not None]
    assert len(driven) == N - 1 and all(np.isfinite(driven)) and driven == sorted(driven)


def stand_in_service() -> Service:
    return Service(right={2, 3, 30, 31}, off_map=set(range(18, 27)))


def test_a_whole_drive_from_its_config(tmp_path) -> None:
    """run_job: the drive run by the config's policy, its CSV and the lines the command
    prints."""
    from pnvlad_service.localization.drive import service
    from pnvlad_service.localization.drive.config import DriveConfig
    from pnvlad_service.localization.drive.job import run_job
    from pnvlad_service.localization.drive.rows import read_rows

    config = DriveConfig(policy="tracked", output={"plot": False, "progress": False})
    svc = service.Service(stand_in_service(), lambda: None)
    result = run_job(config, StandInDrive(), svc, source=tmp_path / "bag", truth=true_poses())
    assert result.written == [tmp_path / "stand-in.follow.csv"]
    lines = result.lines()
    assert lines[:2] == [f"wrote {tmp_path / 'stand-in.follow.csv'}", "odometry: registered"]
    assert lines[-1] == result.summary.line() and lines[-1].startswith(f"follow: {N} scans")
    assert any(line.startswith("stages, tracking (") for line in lines)
    again = read_rows(result.written[0])
    assert [(r.state, r.how, r.verified) for r in again] == [
        (r.state, r.how, r.verified) for r in result.rows
    ]
    direct = run_drive(StandInDrive(), stand_in_service(), "tracked", truth=true_poses(),
                       progress=False)  # fmt: skip
    assert [r.pose_error_m for r in direct] == [r.pose_error_m for r in result.rows]


def test_the_configs_errors_name_their_field() -> None:
    from pydantic import ValidationError

    from pnvlad_service.localization.drive.config import DriveConfig, config_error

    cases = (
        ({"tracking": {"confirm": 0}}, "tracking.confirm", "confirm and failures must be at"),
        ({"tracking": {"radius_m": -1}}, "tracking.radius_m", "radius_m must be > 0, got -1"),
        ({"every": "often"}, "every", "integer"),
        ({"output": {"colour": "red"}}, "output.colour", "Extra inputs"),
    )
    for bad, field, message in cases:
        with pytest.raises(ValidationError) as err:
            DriveConfig(**bad)
        error = config_error(err.value)
        assert error.source == field and message in error.detail, (bad, error)
    for bad, field in (({"every": 0}, "every"), ({"window_m": -2.0}, "window_m"),
                       ({"window_m": 20.0, "odometry": "none"}, "odometry")):  # fmt: skip
        with pytest.raises(InputError) as ierr:
            DriveConfig(policy="per-scan", **bad).check()
        assert ierr.value.source == field
