"""The drive localiser (localization/drive/tracking.py) against a stand-in service whose answers are
set scan by scan: when a fix is accepted, what tracking asks and keeps, when it is lost, and
how bad input sends it back to searching without raising. The poses expected are computed here
from the scenario, not by the localiser's own helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.localization.drive.tracking import (
    LOST,
    SEARCHING,
    TRACKING,
    DriveLocalizer,
    DriveScan,
    TrackerConfig,
    follow,
)
from tests.localization.stand_in import (
    DT_US,
    ORIGIN,
    STEP_M,
    Service,
    cloud,
    odometry,
    pose,
    scans,
    truth,
)


def test_a_fix_needs_two_answers_that_agree_then_every_scan_is_tracked() -> None:
    svc = Service(right={2, 3})
    steps = follow(scans(40), svc)
    assert [s.state for s in steps[:3]] == [SEARCHING] * 3
    assert "waiting for 1 more" in steps[2].reason and steps[2].pose is None
    fix = steps[3]
    assert (fix.state, fix.verified, fix.how, fix.event) == (TRACKING, True, "fix", "fix")
    np.testing.assert_allclose(fix.pose, truth(3))
    for s in steps[4:]:
        assert (s.state, s.verified, s.how) == (TRACKING, True, "registered"), s
        np.testing.assert_allclose(s.pose, truth(s.scan), atol=1e-9)
    # Tracking asked with the last pose moved by the odometry between the scans: here the
    # truth of the scan itself, since the odometry is exact; the turn included.
    priors = [(i, p) for i, p in svc.calls if p is not None]
    assert [i for i, _ in priors] == list(range(4, 40))
    for i, p in priors:
        expected = truth(i)
        assert p.easting == pytest.approx(expected[0, 3]) and p.northing == pytest.approx(
            expected[1, 3]
        )
        assert p.yaw_deg == pytest.approx(math.degrees(math.atan2(expected[1, 0], expected[0, 0])))
        assert p.radius_m == TrackerConfig().radius_m


def test_confirm_one_takes_the_first_verified_answer() -> None:
    steps = follow(scans(6), Service(right={1}), TrackerConfig(confirm=1))
    assert steps[1].how == "fix" and steps[1].reason == "fix: the first verified answer"


def test_wrong_answers_that_disagree_are_never_a_fix() -> None:
    svc = Service(right={5, 9}, wrong={1, 2, 3, 4, 6, 7, 8})
    steps = follow(scans(12), svc)
    assert all(s.state == SEARCHING and s.pose is None for s in steps[:9])
    assert steps[9].how == "fix"  # 5 and 9 agree with the odometry between them
    np.testing.assert_allclose(steps[9].pose, truth(9))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from(["right", "wrong", "none"]), min_size=4, max_size=25))
def test_a_fix_is_right_and_comes_with_the_second_right_answer(kinds: list[str]) -> None:
    """Whatever the mix of answers, a fix is accepted exactly at the second right answer (the
    wrong ones never agree: each lies elsewhere), and it is the truth."""
    right = {i for i, k in enumerate(kinds) if k == "right"}
    wrong = {i for i, k in enumerate(kinds) if k == "wrong"}
    steps = follow(scans(len(kinds)), Service(right=right, wrong=wrong))
    fixes = [s for s in steps if s.how == "fix"]
    if len(right) < 2:
        assert fixes == [] and all(s.pose is None for s in steps)
        return
    second = sorted(right)[1]
    assert [s.scan for s in fixes] == [second]
    np.testing.assert_allclose(fixes[0].pose, truth(second))
    assert all(s.verified for s in steps[second:])


def test_failures_predict_then_lost_then_search_and_relocalise() -> None:
    off = set(range(10, 16))
    svc = Service(right={0, 1, 16, 17}, off_map=off)
    steps = follow(scans(20), svc, TrackerConfig(failures=3))
    assert [s.how for s in steps[10:12]] == ["predicted", "predicted"]
    assert steps[10].reason.startswith("tracking failure 1 of 3: no map within")
    np.testing.assert_allclose(steps[11].pose, truth(11), atol=1e-9)  # exact odometry
    assert not any(s.verified for s in steps if s.scan in off)
    lost = steps[12]
    assert (lost.state, lost.event, lost.verified) == (LOST, "lost", False)
    assert lost.reason.startswith("tracking failed 3 times in a row (no map within")
    assert all(s.state == SEARCHING and s.pose is None for s in steps[13:17])
    assert [c[1] is None for c in svc.calls if c[0] in (13, 14, 15)] == [True] * 3
    assert steps[17].event == "relocalised" and steps[17].how == "fix"


def test_a_registration_that_moves_the_prediction_too_far_is_a_failure() -> None:
    # From scan 3 on the odometry says the robot drives three times as far as it does: each
    # prediction lands 5 m ahead of the truth, and the service (reach 10 m) registers it back.
    def fast(i: int) -> np.ndarray:
        return pose(STEP_M * (i if i <= 3 else 3 + 3 * (i - 3)), 0.0, 0.0)

    svc = Service(right={0, 1}, reach=10.0)
    drive = [DriveScan(i, 1_000_000_000 + DT_US * i, cloud(i), fast(i)) for i in range(7)]
    steps = follow(drive, svc, TrackerConfig(gate_m=3.0, failures=2))
    assert [s.verified for s in steps[1:4]] == [True, True, True]
    assert steps[4].reason == (
        "tracking failure 1 of 2: the registration moved the prediction 5.0 m and 0.0 deg "
        "(more than 3 m or 5 deg)"
    )
    np.testing.assert_allclose(steps[4].pose[:2, 3], truth(4)[:2, 3] + [5.0, 0.0])
    assert steps[5].state == LOST and "moved the prediction 10.0 m" in steps[5].reason


def test_bad_input_sends_it_back_to_searching_and_never_raises() -> None:
    svc = Service(right={0, 1, 6, 7, 12, 13}, refuse={9})
    drive = scans(16)
    # scan 4 comes out of order (before scan 3); a gap of 10 s before scan 6; the odometry
    # jumps 400 m at scan 11.
    drive[4] = DriveScan(4, drive[2].timestamp - 1, cloud(4), odometry(4))
    late = 10_000_000
    drive[6:] = [DriveScan(s.index, s.timestamp + late, s.points, s.odometry) for s in drive[6:]]
    jump = pose(400.0, 0.0, 0.0)
    drive[11:] = [DriveScan(s.index, s.timestamp, s.points, jump @ s.odometry) for s in drive[11:]]
    steps = follow(drive, svc)
    assert steps[1].how == "fix"
    out_of_order = steps[4]
    assert (out_of_order.state, out_of_order.event) == (SEARCHING, "reset")
    assert "out of time order" in out_of_order.reason and out_of_order.reply is None
    assert all(c[0] != 4 for c in svc.calls)  # skipped, not asked
    assert steps[5].state == SEARCHING  # searching again after the reset
    gap = steps[6]
    assert gap.event == "reset" and gap.reason.startswith("a gap of 10.2 s")
    assert steps[7].how == "fix"
    assert steps[9].reason.startswith("tracking failure 1 of 3: refused: filter G")
    jumped = steps[11]
    moved = np.linalg.norm((np.linalg.inv(odometry(10)) @ jump @ odometry(11))[:2, 3])
    assert jumped.event == "reset"
    assert jumped.reason.startswith(f"odometry jumped {moved:.1f} m and 0 deg in 0.25 s")
    assert steps[13].how == "fix"
    np.testing.assert_allclose(steps[15].pose, truth(15), atol=1e-9)


def test_without_odometry_it_predicts_at_constant_velocity() -> None:
    svc = Service(right={0, 1})
    steps = follow(scans(8, odo=False), svc, TrackerConfig(confirm=2, agree_m=3.0))
    assert steps[1].how == "fix"
    assert all(s.verified for s in steps[1:])
    # The prior of scan 3 is scan 2's pose moved as from scan 1 to scan 2: 2.5 m east.
    p3 = next(p for i, p in svc.calls if i == 3 and p is not None)
    assert p3.easting == pytest.approx(truth(3)[0, 3]) and p3.northing == pytest.approx(ORIGIN[1])


def test_an_initial_pose_starts_tracking_and_a_wrong_one_gets_lost() -> None:
    steps = follow(scans(4), Service(), initial_pose=truth(0))
    assert [s.how for s in steps] == ["registered"] * 4
    wrong = pose(ORIGIN[0] + 500.0, ORIGIN[1], 0.0)
    steps = follow(scans(5), Service(right={3, 4}), TrackerConfig(failures=2), initial_pose=wrong)
    assert [s.state for s in steps] == [TRACKING, LOST, SEARCHING, SEARCHING, TRACKING]


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="confirm"):
        TrackerConfig(confirm=0)
    with pytest.raises(ValueError, match="radius_m"):
        TrackerConfig(radius_m=0.0)
    loc = DriveLocalizer(Service())
    assert loc.state == SEARCHING
