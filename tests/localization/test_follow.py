"""A followed drive (localization/follow.py) with the stand-in service: the rows, their errors
and off-map distances (their CSV, summary and PNG: test_follow_report.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.follow import follow_drive
from pnvlad_service.localization.tracking import TrackerConfig
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


def test_a_scan_without_truth_has_no_errors_and_the_distance_goes_on() -> None:
    truth = true_poses()
    truth[10] = np.nan  # the truth topic had no pose for scan 10
    rows = follow_drive(StandInDrive(), Service(right={2, 3}), truth=truth, progress=False)
    assert rows[10].true_northing is None and rows[10].pose_error_m is None
    assert rows[9].pose_error_m is not None and rows[11].pose_error_m is not None
    driven = [r.driven_m for r in rows if r.driven_m is not None]
    assert len(driven) == N - 1 and all(np.isfinite(driven)) and driven == sorted(driven)
