"""The planar filter (localization/drive/fusion.py): a registration weighed against the
odometry's prediction by their covariances. The expected values are the scalar weighted means
and variance sums computed here, axis by axis, not the filter's own matrices."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.localization.drive.fusion import (
    OdometryNoise,
    PlanarFilter,
    planar,
    with_planar,
)


def pose(x: float, y: float, yaw_deg: float, z: float = 0.0, roll_deg: float = 0.0) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    r = math.radians(roll_deg)
    roll = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    out = np.eye(4)
    out[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ roll
    out[:3, 3] = [x, y, z]
    return out


def cov6(sx: float, sy: float, syaw_deg: float) -> np.ndarray:
    """A registration's covariance (x, y, z, roll, pitch, yaw) with the given x, y, yaw stds."""
    return np.diag([sx**2, sy**2, 0.01, 1e-4, 1e-4, math.radians(syaw_deg) ** 2])


def started(sx: float, sy: float, syaw_deg: float) -> PlanarFilter:
    f = PlanarFilter()
    f.start(cov6(sx, sy, syaw_deg))
    return f


@settings(max_examples=80, deadline=None)
@given(
    st.floats(0.05, 2.0), st.floats(0.05, 2.0), st.floats(0.05, 2.0), st.floats(0.05, 2.0),
    st.floats(-0.8, 0.8), st.floats(-0.8, 0.8), st.floats(0.2, 3.0), st.floats(0.2, 3.0),
)  # fmt: skip
def test_a_diagonal_update_is_the_weighted_mean_axis_by_axis(
    px: float, py: float, rx: float, ry: float, dx: float, dy: float, pyaw: float, ryaw: float
) -> None:
    f = started(px, py, pyaw)
    predicted = pose(100.0, 200.0, 30.0, z=5.0)
    registered = pose(100.0 + dx, 200.0 + dy, 30.5, z=5.3)
    w = f.weigh(predicted, registered, cov6(rx, ry, ryaw))
    if not w.fused:  # the gate: only when the innovation is far outside both covariances
        assert w.distance > f.gate
        return
    for got, p, r, x, z in (
        (w.pose[0, 3], px, rx, 100.0, 100.0 + dx),
        (w.pose[1, 3], py, ry, 200.0, 200.0 + dy),
    ):
        expected = (x / p**2 + z / r**2) / (1 / p**2 + 1 / r**2)
        assert got == pytest.approx(expected, abs=1e-9)
    yaw = (30.0 / pyaw**2 + 30.5 / ryaw**2) / (1 / pyaw**2 + 1 / ryaw**2)
    assert math.degrees(planar(w.pose)[2]) == pytest.approx(yaw, abs=1e-9)
    var = [1 / (1 / px**2 + 1 / rx**2), 1 / (1 / py**2 + 1 / ry**2)]
    np.testing.assert_allclose(np.diag(w.P)[:2], var, rtol=1e-9)
    assert w.sigma_m == pytest.approx(math.sqrt(max(var)), rel=1e-9)
    assert w.pose[2, 3] == 5.3  # the height is the registration's


def test_a_street_loose_along_it_keeps_the_prediction_along_and_the_map_across() -> None:
    f = started(0.05, 0.05, 0.1)
    predicted = pose(50.0, 10.0, 0.0)  # driving east
    registered = pose(51.7, 10.2, 0.0)  # slid 1.7 m along the street, 0.2 m across
    w = f.weigh(predicted, registered, cov6(1e3, 0.05, 0.2))
    assert w.fused
    assert abs(w.pose[0, 3] - 50.0) < 1e-5  # along: the odometry's
    assert w.pose[1, 3] == pytest.approx(10.1, abs=1e-9)  # across: equal weights, halfway
    assert f.P is not None and f.P[0, 0] == pytest.approx(0.05**2)  # not committed yet
    f.commit(w)
    assert f.P[1, 1] == pytest.approx(0.05**2 / 2)


def test_an_innovation_outside_both_covariances_is_the_registration_alone() -> None:
    f = started(0.1, 0.1, 0.2)
    registered = pose(53.0, 10.0, 0.0)
    w = f.weigh(pose(50.0, 10.0, 0.0), registered, cov6(0.2, 0.2, 0.5))
    # 3 m against a combined std of sqrt(0.1^2 + 0.2^2) = 0.22 m: (3 / 0.2236)^2 = 180.
    assert not w.fused and w.distance == pytest.approx(9.0 / 0.05, rel=1e-6)
    np.testing.assert_array_equal(w.pose, registered)
    np.testing.assert_allclose(np.diag(w.P)[:2], [0.04, 0.04])


def test_an_empty_filter_takes_the_registration() -> None:
    f = PlanarFilter()
    registered = pose(1.0, 2.0, 3.0)
    w = f.weigh(pose(0.0, 0.0, 0.0), registered, cov6(0.3, 0.4, 1.0))
    assert not w.fused and math.isnan(w.distance)
    np.testing.assert_array_equal(w.pose, registered)
    f.commit(w)
    assert f.ready and f.P[1, 1] == pytest.approx(0.16)


def test_the_prediction_grows_by_the_step_and_the_heading_error_swings_it_sideways() -> None:
    noise = OdometryNoise(sigma_m=0.02, share=0.02, sigma_deg=0.05, turn_share=0.0)
    f = PlanarFilter(noise)
    f.start(cov6(0.1, 0.1, 1.0))
    before = pose(0.0, 0.0, 90.0)  # heading north
    motion = pose(2.5, 0.0, 0.0)  # 2.5 m ahead: north in the world
    f.predict(before, motion)
    s = 0.02 + 0.02 * 2.5
    yaw_var = math.radians(1.0) ** 2
    # A heading error e turns the 2.5 m step by e: the end moves 2.5 e east (x), not north.
    assert f.P[0, 0] == pytest.approx(0.01 + 2.5**2 * yaw_var + s**2, rel=1e-9)
    assert f.P[1, 1] == pytest.approx(0.01 + s**2, rel=1e-9)
    assert f.P[2, 2] == pytest.approx(yaw_var + math.radians(0.05) ** 2, rel=1e-9)
    assert f.P[0, 2] == pytest.approx(-2.5 * yaw_var, rel=1e-9)


def test_with_planar_turns_about_the_vertical_and_keeps_height_and_tilt() -> None:
    p = pose(5.0, 6.0, 40.0, z=7.0, roll_deg=3.0)
    out = with_planar(p, np.array([8.0, 9.0, math.radians(-170.0)]))
    assert math.degrees(planar(out)[2]) == pytest.approx(-170.0)
    assert out[:3, 3] == pytest.approx([8.0, 9.0, 7.0])
    np.testing.assert_allclose(out[2, :3], p[2, :3], atol=1e-12)  # the tilt against gravity
    np.testing.assert_allclose(out[:3, :3] @ out[:3, :3].T, np.eye(3), atol=1e-12)


def test_the_heading_is_weighed_across_the_wrap() -> None:
    f = started(0.1, 0.1, 1.0)
    w = f.weigh(pose(0.0, 0.0, 179.0), pose(0.0, 0.0, -179.0), cov6(0.1, 0.1, 1.0))
    assert w.fused and abs(abs(math.degrees(planar(w.pose)[2])) - 180.0) < 1e-9


def test_a_covariance_that_is_not_finite_is_a_direction_nothing_measured() -> None:
    f = started(0.1, 0.1, 0.5)
    cov = cov6(0.1, 0.1, 0.5)
    cov[0, 0] = math.nan  # along x: nothing
    cov[0, 1] = cov[1, 0] = math.inf
    w = f.weigh(pose(0.0, 0.0, 0.0), pose(2.0, 0.05, 0.0), cov)
    assert w.fused and np.all(np.isfinite(w.P))
    assert abs(w.pose[0, 3]) < 1e-5  # along x the prediction's
    assert w.pose[1, 3] == pytest.approx(0.025, abs=1e-9)  # across: halfway
    f.commit(w)
    f.predict(pose(0.0, 0.0, 0.0), pose(2.5, 0.0, 0.0))
    assert np.all(np.isfinite(f.P))


def test_a_singular_sum_is_the_registration_alone_not_an_error() -> None:
    f = PlanarFilter()
    f.P = np.zeros((3, 3))
    registered = pose(1.0, 0.0, 0.0)
    w = f.weigh(pose(0.0, 0.0, 0.0), registered, np.zeros((6, 6)))
    assert not w.fused
    np.testing.assert_array_equal(w.pose, registered)
