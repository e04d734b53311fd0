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


# -- after a loss: where the odometry says the robot can be --------------------------------------

#: A look-alike street 800 m away: the world moved east and turned 90 degrees about the origin.
ALIAS = pose(ORIGIN[0] + 800.0, ORIGIN[1], 90.0) @ np.linalg.inv(pose(*ORIGIN[:2], 0.0))


def _driven(a: int, b: int) -> float:
    """Metres driven from scan ``a`` to scan ``b`` (the truth's steps, as the odometry's)."""
    return sum(
        float(np.linalg.norm(truth(k)[:2, 3] - truth(k - 1)[:2, 3])) for k in range(a + 1, b + 1)
    )


def _off_truth(steps: list, scan_truth=truth) -> list[float]:
    return [
        float(np.linalg.norm(s.pose[:2, 3] - scan_truth(s.scan)[:2, 3]))
        for s in steps
        if s.verified
    ]


def test_a_look_alike_street_far_from_the_odometry_is_checked_and_never_fixed() -> None:
    # Fixed at scan 1, off the map from scan 10 (lost at 12); at 15 and 16 the search finds a
    # street 800 m away that agrees with the odometry between the two answers, and it even
    # registers there for three scans; then it does not. The robot comes back at 34-35.
    svc = Service(right={0, 1, 34, 35}, off_map=set(range(10, 34)), alias=ALIAS,
                  alias_search={15, 16}, alias_holds={16, 17, 18})  # fmt: skip
    steps = follow(scans(40), svc)
    assert steps[12].event == "lost"
    assert steps[15].state == SEARCHING and steps[15].pose is None
    off = np.linalg.norm((ALIAS @ truth(15))[:2, 3] - truth(15)[:2, 3])  # the reckoning: exact
    assert steps[15].reason.startswith(f"a verified answer {off:.0f} m from where the odometry")
    # Checked by registering near it moved by the odometry, never reported as a pose.
    assert [i for i, p in svc.calls if p is not None and 16 <= i <= 21] == list(range(16, 22))
    for i, p in svc.calls:
        if p is not None and 16 <= i <= 21:
            there = ALIAS @ truth(i)
            assert (p.easting, p.northing) == pytest.approx((there[0, 3], there[1, 3]))
    assert all(s.pose is None and not s.verified for s in steps[13:34])
    driven = _driven(15, 17)
    assert steps[17].reason == (
        f"checking an answer {off:.0f} m from the odometry's reckoning: 2 registrations over "
        f"{driven:.0f} of 50 m"
    )
    assert "did not hold: 3 failures in a row" in steps[21].reason
    assert svc.calls[-1][0] == 39 and (22, None) in svc.calls  # searching again from 22
    assert steps[35].event == "relocalised" and steps[35].how == "fix"
    assert max(_off_truth(steps)) < 1e-6
    # Without the reckoning (reach beyond the city) the same answers are a fix 800 m off.
    svc = Service(right={0, 1, 34, 35}, off_map=set(range(10, 34)), alias=ALIAS,
                  alias_search={15, 16}, alias_holds={16, 17, 18})  # fmt: skip
    steps = follow(scans(40), svc, TrackerConfig(reach_m=1e6))
    assert steps[16].how == "fix" and max(_off_truth(steps)) > 700


def test_a_kidnapped_robot_is_fixed_where_it_is_once_that_holds_over_far_confirm_m() -> None:
    # From scan 10 on the robot is 600 m away (carried there unseen: the clock and the odometry
    # go on as if nothing happened). Lost at 12; the right answers from 13 on are far from the
    # odometry's reckoning, and they hold: a fix once the robot has driven 50 m since 13.
    jump = pose(ORIGIN[0] + 600.0, ORIGIN[1] + 200.0, -30.0) @ np.linalg.inv(pose(*ORIGIN[:2], 0.0))

    def kidnapped(i: int) -> np.ndarray:
        return truth(i) if i < 10 else jump @ truth(i)

    svc = Service(right={0, 1} | set(range(13, 60)), scan_truth=kidnapped)
    steps = follow(scans(60), svc)
    assert steps[12].event == "lost"
    assert "checked by tracking it over 50 m" in steps[13].reason
    at = next(i for i in range(14, 60) if _driven(13, i) >= 50.0)
    assert all(s.pose is None for s in steps[13:at])
    fix = steps[at]
    assert (fix.event, fix.how, fix.verified) == ("relocalised", "fix", True)
    off = np.linalg.norm(kidnapped(13)[:2, 3] - truth(13)[:2, 3])
    assert fix.reason == (
        f"fix: an answer {off:.0f} m from where the odometry put the robot held {at - 13} "
        f"registrations over {_driven(13, at):.0f} m"
    )
    np.testing.assert_allclose(fix.pose, kidnapped(at), atol=1e-9)
    assert all(s.verified for s in steps[at:])
    assert max(_off_truth(steps, kidnapped)) < 1e-6


@pytest.mark.parametrize(("shift_m", "far"), [(32.0, False), (33.5, True)])
def test_the_reach_grows_with_the_distance_driven_since_the_last_verified_pose(
    shift_m: float, far: bool
) -> None:
    # Last verified at scan 9, lost at 12; at scan 20 the robot has driven 11 scans of 2.5 m
    # since: reach 30 + 0.1 * 27.5 = 32.75 m.
    moved = pose(0.0, shift_m, 0.0)
    svc = Service(right={0, 1}, off_map=set(range(10, 30)), alias=moved, alias_search={20})
    steps = follow(scans(22), svc)
    if far:
        assert steps[20].reason.startswith(f"a verified answer {shift_m:.0f} m from where")
        assert "(more than 33 m)" in steps[20].reason
    else:
        assert steps[20].reason.startswith("a verified answer; waiting for 1 more")


def test_a_reset_forgets_the_last_pose() -> None:
    # A gap of 10 s before scan 15: the robot may be anywhere; answers 800 m away fix at once.
    drive = scans(20)
    drive[15:] = [DriveScan(s.index, s.timestamp + 10_000_000, s.points, s.odometry)
                  for s in drive[15:]]  # fmt: skip
    svc = Service(right={0, 1}, off_map=set(range(10, 20)), alias=ALIAS, alias_search={15, 16})
    steps = follow(drive, svc)
    assert steps[15].event == "reset" and steps[16].how == "fix"
