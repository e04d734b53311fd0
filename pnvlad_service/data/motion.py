"""The vehicle's motion at each scan, as the drive's recorded poses give it.

A spinning sensor that does not de-skew fires its columns through a tenth of a second while
the vehicle moves and turns; taking that smear out of a keyframe (``pnvlad map align
--sweep-hz``) needs the motion at the keyframe's own moment. Between keyframes a few metres
apart the odometry cannot give it through a sharp turn (a corner taken in about a second
turns 8 degrees within one sweep and is over before the next keyframe). The recording can: a
GNSS/INS or odometry topic gives a pose at every scan (10 Hz and more), so the heading, the
forward speed and the yaw rate at a scan come from its poses and its neighbours'. The prepare
step records them beside each keyframe (:mod:`.frames`: ``heading_deg``, ``speed_mps``,
``yaw_rate_dps``).
"""

from __future__ import annotations

import numpy as np

from pnvlad_service.errors import InputError

#: Seconds either side of a scan over which its speed is the median (a vehicle's speed changes
#: little within a second; positions differentiated between scans a tenth of a second apart
#: carry their noise tenfold, and a corner swings the sensor wide of the vehicle's path).
SPEED_WINDOW_S = 1.0


def windowed_median(values: np.ndarray, seconds: np.ndarray, half_s: float) -> np.ndarray:
    """float64 [T]: the median of ``values`` [T] over the samples within ``half_s`` seconds of
    each (``seconds`` [T] increasing); a symmetric window keeps a steady ramp's own value."""
    reach = half_s + 1e-6  # a microsecond: stamps on the window's edge are in it, both sides
    lo = np.searchsorted(seconds, seconds - reach, side="left")
    hi = np.searchsorted(seconds, seconds + reach, side="right")
    return np.array([np.median(values[a:b]) for a, b in zip(lo, hi, strict=True)])


def drive_motion(timestamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Each scan's motion, float64 [T, 3]: heading (radians anticlockwise from east: the
    direction of the sensor's forward axis in UTM axes), forward speed (m/s, the velocity
    along that axis: negative when reversing; the median over :data:`SPEED_WINDOW_S` either
    side) and yaw rate (rad/s, anticlockwise positive).

    ``timestamps`` int [T] microseconds, strictly increasing; ``poses`` float64 [T, 4, 4]
    sensor -> UTM. Velocity and yaw rate are central differences of the poses over time
    (one-sided at the ends; zero for a single scan). ``InputError`` on timestamps that do not
    increase."""
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    out = np.zeros((n, 3))
    if n == 0:
        return out
    forward = poses[:, :2, 0]
    heading = np.arctan2(forward[:, 1], forward[:, 0])
    out[:, 0] = heading
    if n < 2:
        return out
    seconds = np.asarray(timestamps, dtype=np.float64) * 1e-6
    if not (np.diff(seconds) > 0).all():
        raise InputError("timestamps must increase strictly", "timestamps")
    velocity = np.gradient(poses[:, :2, 3], seconds, axis=0)
    unit = np.stack([np.cos(heading), np.sin(heading)], 1)
    out[:, 1] = windowed_median((velocity * unit).sum(1), seconds, SPEED_WINDOW_S)
    out[:, 2] = np.gradient(np.unwrap(heading), seconds)
    return out


def motion_columns(motion: np.ndarray) -> np.ndarray:
    """One scan's :func:`drive_motion` row as the frame sidecar records it: float64 [3],
    heading (degrees), speed (m/s), yaw rate (degrees a second)."""
    h, v, w = (float(x) for x in motion)
    return np.array([np.degrees(h), v, np.degrees(w)])
