"""The drive localiser weighing each registration against its odometry
(localization/drive/tracking.py with fusion.py): on a street that leaves the registration
loose along it, a registration that slides does not move the pose, one too loose to be verified
alone is verified with the odometry, and a prediction the map contradicts gives way. The
stand-in's odometry is exact, so the truth is what a weighed pose must stay at."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pnvlad_service.localization.drive.runner import tracker_config
from pnvlad_service.localization.drive.tracking import (
    TRACKING,
    DriveLocalizer,
    DriveScan,
    TrackerConfig,
    follow,
)
from tests.localization.stand_in import DT_US, Service, answer, cloud, odometry, truth

LOOSE = np.diag([0.9**2, 0.05**2, 0.01, 1e-5, 1e-5, math.radians(0.2) ** 2])  # along x
FIRM = np.diag([0.1**2, 0.1**2, 0.01, 1e-5, 1e-5, math.radians(0.2) ** 2])
FREE = np.diag([1e6, 0.05**2, 0.01, 1e-5, 1e-5, math.radians(0.2) ** 2])


def shifted(i: int, east_m: float) -> np.ndarray:
    p = truth(i).copy()
    p[0, 3] += east_m
    return p


class StreetService(Service):
    """Search: the truth on scans 0 and 1. Priors: registrations with their covariance,
    sliding ``slide_m`` east (along the street) on ``slides``, too loose to verify alone
    (``uncertain``, 2 m east) on ``loose``, the truth with a firm covariance else."""

    def __init__(self, slides: set[int], loose: set[int], slide_m: float = 1.5,
                 weak: dict[int, float] | None = None) -> None:  # fmt: skip
        super().__init__(right={0, 1})
        self.slides, self.loose, self.slide_m = slides, loose, slide_m
        self.weak = weak or {}  # scan -> the fitness of a fit under the service's threshold

    def __call__(self, points, prior=None, kind="scan"):
        i = int(points[0, 0])
        if prior is None:
            return super().__call__(points, prior, kind)
        self.calls.append((i, prior))
        if i in self.loose:
            reg = shifted(i, 2.0)
            return answer(None, "prior", "position uncertain along a direction: sigma 1000 m",
                          fitness=0.7, sigma_m=1e3, uncertain=True, fit_pose=reg,
                          fit_covariance=FREE)  # fmt: skip
        if i in self.weak:
            reg = shifted(i, 0.3)
            f = self.weak[i]
            return answer(None, "prior", f"fitness {f:.2f} < 0.4", fitness=f, sigma_m=0.1,
                          fit_pose=reg, fit_covariance=FIRM)  # fmt: skip
        if i in self.slides:
            reg = shifted(i, self.slide_m)
            return answer(reg, "prior", fitness=0.6, sigma_m=0.9, fit_pose=reg,
                          fit_covariance=LOOSE)  # fmt: skip
        reg = truth(i)
        return answer(reg, "prior", fitness=0.8, sigma_m=0.1, fit_pose=reg, fit_covariance=FIRM)


def drive(n: int, odo=odometry) -> list[DriveScan]:
    return [DriveScan(i, 1_000_000_000 + DT_US * i, cloud(i), odo(i)) for i in range(n)]


def east_error(step) -> float:
    return float(step.pose[0, 3] - truth(step.scan)[0, 3])


def test_a_registration_sliding_along_the_street_leaves_the_pose_on_the_odometry() -> None:
    slides = set(range(8, 12))
    fused = follow(drive(16), StreetService(slides, set()))
    alone = follow(drive(16), StreetService(slides, set()), TrackerConfig(fuse=False))
    # The error along the street, as a scalar filter: the fix's 0.5 m, each 2.5 m step adds
    # (0.02 + 0.02 * 2.5)^2 (the defaults), firm registrations at the truth (0.1 m) on scans
    # 2-7 and 12-15, sliding ones 1.5 m ahead (0.9 m) on scans 8-11.
    q2, var, err, expected = (0.02 + 0.02 * 2.5) ** 2, 0.5**2, 0.0, {}
    for i in range(2, 16):
        var += q2
        z, r2 = (1.5, 0.81) if i in slides else (0.0, 0.01)
        k = var / (var + r2)
        err, var = err + k * (z - err), (1 - k) * var
        expected[i] = err
    for s, a in zip(fused[8:12], alone[8:12], strict=True):
        assert s.verified and s.how == "registered"
        assert a.verified and east_error(a) == 1.5  # the registration as it came
        assert abs(east_error(s) - expected[s.scan]) < 1e-6, (s.scan, east_error(s))
        # Across the street the registration is firm and right: it stays there.
        assert abs(s.pose[1, 3] - truth(s.scan)[1, 3]) < 1e-6
    assert max(expected[i] for i in slides) < 0.15
    assert all(abs(east_error(s) - expected[s.scan]) < 1e-6 for s in fused[12:])


def test_a_registration_too_loose_alone_is_verified_with_the_odometry() -> None:
    loose = {9, 10, 11}
    fused = follow(drive(14), StreetService(set(), loose))
    alone = follow(drive(14), StreetService(set(), loose), TrackerConfig(fuse=False))
    for s, a in zip(fused[9:12], alone[9:12], strict=True):
        assert (s.state, s.verified, s.how, s.reason) == (TRACKING, True, "registered", None)
        assert abs(east_error(s)) < 1e-3  # along the street: the odometry alone
        assert s.sigma_m is not None and s.sigma_m < TrackerConfig().max_sigma_m
        assert (a.verified, a.how) == (False, "predicted")
        assert a.reason.startswith("uncertain, the prediction kept")
    # The pose's covariance is the weighed one: along the street it grows by a step's
    # (0.02 + 0.02 * 2.5)^2 each scan, the registration adding nothing there; across it the
    # registration's 0.05 m pins it; no cross terms with height.
    along = [s.covariance[0, 0] for s in fused[9:12]]
    np.testing.assert_allclose(np.diff(along), (0.02 + 0.02 * 2.5) ** 2, rtol=1e-3)
    assert all(s.covariance[1, 1] < 0.05**2 and s.covariance[0, 2] == 0.0 for s in fused[9:12])
    assert fused[9].covariance[2, 2] == FREE[2, 2]


def test_a_loose_registration_is_not_verified_once_the_odometry_has_drifted_too_far() -> None:
    # Every prior registration from scan 3 on is loose along the street: the odometry alone
    # carries the position along it, its variance growing each step until the weighed std
    # passes max_sigma_m; from there on the scans are predicted, not verified.
    cfg = TrackerConfig(odometry_sigma_m=0.2, odometry_share=0.0, max_sigma_m=0.6)
    steps = follow(drive(20), StreetService(set(), set(range(3, 20))), cfg)
    verified = [s.verified for s in steps[2:]]
    first_out = verified.index(False)
    assert first_out > 1 and not any(verified[first_out:])
    # Independently: the fix's 0.5 m and a step's 0.2 m, then scan 2's firm registration
    # (0.1 m); from scan 3 each step adds 0.2^2 along the street (a straight drive: no heading
    # swing) and the across-street update leaves the along variance alone.
    var = 1.0 / (1.0 / (0.5**2 + 0.2**2) + 1.0 / 0.1**2)
    n = 1  # scan 2
    while math.sqrt(var + 0.2**2) <= 0.6:
        var += 0.2**2
        n += 1
    assert first_out == n == 9


def test_a_map_that_contradicts_the_prediction_wins() -> None:
    # The odometry claims 1 m more east than driven from scan 6 on; the firm registrations
    # (0.1 m) put the pose back on the truth at once, not a share of the way.
    def drifted(i: int) -> np.ndarray:
        o = odometry(i)
        if i >= 6:
            o = o @ np.linalg.inv(truth(i)) @ shifted(i, 1.0)
        return o

    steps = follow(drive(10, drifted), StreetService(set(), set()))
    assert all(s.verified for s in steps[1:])
    for s in steps[6:]:
        np.testing.assert_allclose(s.pose, truth(s.scan), atol=1e-6)


def test_a_fit_under_the_threshold_is_verified_only_where_the_odometry_expects_it() -> None:
    # Scans 6 and 7 fit at 0.35 and 0.25 (the service's threshold 0.4), 0.3 m ahead; the
    # odometry is exact. 0.35 is over fuse_min_fitness (0.3): weighed and verified, a share of
    # the 0.3 m; 0.25 is a failure, the prediction kept. Without fusion both are failures.
    weak = {6: 0.35, 7: 0.25}
    fused = follow(drive(10), StreetService(set(), set(), weak=weak))
    alone = follow(drive(10), StreetService(set(), set(), weak=weak), TrackerConfig(fuse=False))
    assert (fused[6].verified, fused[6].how, fused[6].reason) == (True, "registered", None)
    assert 0.0 < east_error(fused[6]) < 0.3
    assert (fused[7].verified, fused[7].how) == (False, "predicted")
    assert fused[7].reason == "tracking failure 1 of 3: fitness 0.25 < 0.4"
    assert [a.verified for a in alone[6:8]] == [False, False]
    assert alone[6].reason == "tracking failure 1 of 3: fitness 0.35 < 0.4"
    assert alone[7].reason == "tracking failure 2 of 3: fitness 0.25 < 0.4"
    assert all(s.verified for s in fused[8:]) and all(a.verified for a in alone[8:])


def test_a_drive_weighs_the_pose_only_with_the_refined_steps_unless_told() -> None:
    for source, fused in (("registered", True), ("poses", False), ("kiss-icp", False),
                          ("none", False)):  # fmt: skip
        assert tracker_config(None, source).fuse is fused, source
        assert tracker_config(TrackerConfig(fuse=True), source).fuse is True
        assert tracker_config(TrackerConfig(fuse=False), source).fuse is False
    # The localiser itself weighs unless told not to (its caller knows its odometry).
    assert DriveLocalizer(StreetService(set(), set()))._filter is not None
    assert DriveLocalizer(StreetService(set(), set()), TrackerConfig(fuse=False))._filter is None


def test_the_odometry_noise_must_be_a_positive_finite_number() -> None:
    for field, value in (("odometry_sigma_m", 0.0), ("odometry_sigma_deg", -1.0),
                         ("odometry_share", math.inf), ("fuse_min_fitness", -0.1),
                         ("max_sigma_m", 0.0)):  # fmt: skip
        with pytest.raises(ValueError, match=field):
            TrackerConfig(**{field: value})


def test_a_verified_registration_without_covariance_restarts_the_filter() -> None:
    class NoCovariance(StreetService):
        def __call__(self, points, prior=None, kind="scan"):
            reply = super().__call__(points, prior, kind)
            if prior is not None and int(points[0, 0]) == 5:
                return dataclasses.replace(reply, fit_covariance=None)
            return reply

    loc = DriveLocalizer(NoCovariance(set(), set()))
    steps = [loc.step(s) for s in drive(6)]
    assert steps[5].verified and steps[5].covariance is None
    P = loc._filter.P
    np.testing.assert_allclose(np.diag(P), [0.25, 0.25, math.radians(1.0) ** 2])
