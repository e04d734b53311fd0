"""data.motion: the heading, forward speed and yaw rate a drive's poses give at each scan,
against drives whose motion is known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data.motion import drive_motion, windowed_median
from pnvlad_service.errors import InputError


def _poses(xy: np.ndarray, heading: np.ndarray) -> np.ndarray:
    out = np.tile(np.eye(4), (len(xy), 1, 1))
    c, s = np.cos(heading), np.sin(heading)
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, :2, 3] = xy + np.array([620_000.0, 5_735_000.0])
    return out


@settings(max_examples=30, deadline=None)
@given(
    speed=st.floats(2.0, 20.0),
    radius=st.floats(8.0, 200.0),
    left=st.booleans(),
    start=st.floats(-math.pi, math.pi),
)
def test_a_circle_at_constant_speed(speed: float, radius: float, left: bool, start: float) -> None:
    # 10 Hz poses on a circle: heading along the tangent, yaw rate speed / radius.
    rate = (1 if left else -1) * speed / radius
    t = np.arange(60) * 0.1
    heading = start + rate * t
    centre_dir = heading + (math.pi / 2 if left else -math.pi / 2)
    xy = -radius * np.stack([np.cos(centre_dir), np.sin(centre_dir)], 1)
    stamps = (1_700_000_000_000_000 + t * 1e6).round().astype(np.int64)
    m = drive_motion(stamps, _poses(xy, heading))
    wrapped = (m[:, 0] - heading + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(wrapped, 0.0, atol=1e-9)
    # central differences of a circle: the chord over the arc, 1 - (w dt)^2 / 6 short
    inner = slice(1, -1)
    np.testing.assert_allclose(m[inner, 2], rate, rtol=1e-6)
    np.testing.assert_allclose(m[inner, 1], speed, rtol=(rate * 0.1) ** 2 / 6 + 1e-6)


def test_reversing_is_a_negative_speed_and_a_single_scan_stands_still() -> None:
    t = np.arange(10) * 0.1
    xy = np.stack([-3.0 * t, np.zeros_like(t)], 1)  # backwards along the sensor's +x (east)
    m = drive_motion((t * 1e6).astype(np.int64), _poses(xy, np.zeros(10)))
    np.testing.assert_allclose(m[:, 1], -3.0)
    np.testing.assert_allclose(m[:, [0, 2]], 0.0)
    one = drive_motion(np.array([5]), _poses(np.array([[1.0, 2.0]]), np.array([0.5])))
    np.testing.assert_allclose(one, [[0.5, 0.0, 0.0]])


def test_a_speed_spike_at_a_corner_is_the_windows_median() -> None:
    # the sensor swung wide for two scans: the window of a second either side keeps the speed
    seconds = np.arange(21) * 0.1
    speeds = np.full(21, 6.0)
    speeds[10:12] = 10.0
    np.testing.assert_allclose(windowed_median(speeds, seconds, 1.0), 6.0)
    ramp = 2.0 + seconds  # a steady ramp keeps its own values inside the window's reach
    np.testing.assert_allclose(windowed_median(ramp, seconds, 0.5)[5:-5], ramp[5:-5])


def test_timestamps_that_do_not_increase_are_refused() -> None:
    xy = np.zeros((3, 2))
    with pytest.raises(InputError, match="timestamps"):
        drive_motion(np.array([0, 100, 100]), _poses(xy, np.zeros(3)))
