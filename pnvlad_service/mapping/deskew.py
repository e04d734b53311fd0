"""The sweep's motion taken out of the nodes' scans before they are registered.

A spinning LiDAR fires its columns one after another through a sweep (a tenth of a second at
10 Hz) while the vehicle moves and turns; a driver that does not de-skew gives every point in
the sensor's frame at the moment it was fired, as if the sensor had stood still at the sweep's
middle. Two such scans registered onto each other disagree by the motion each sweep smeared
in: the registration of consecutive keyframes turns a little too far at every step, a bias
common to every run that drives the same way, which no closure between them sees.

De-skewing here is what KISS-ICP and LIO stacks do: a constant velocity through the sweep
(the node's forward speed and yaw rate, measured by the odometry registered on the skewed
scans, a first pass), each point's time in the sweep from its azimuth (the sensors turn
clockwise seen from above, starting behind the vehicle; clouds carry no per-point times), and
each point moved to where it lies in the sensor's frame at the sweep's middle.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

#: Sweeps a second of the sensors this stage assumes by default (Velodyne, Ouster: 10 Hz).
SWEEP_HZ = 10.0


def sweep_time(azimuth: np.ndarray, hz: float) -> np.ndarray:
    """Seconds from the sweep's middle at which a column at ``azimuth`` (radians, from the
    sensor's forward axis, anticlockwise) fires: the sweep starts behind the sensor and turns
    clockwise (rear, left, front, right, rear)."""
    return (np.mod(np.pi - azimuth, 2 * np.pi) / (2 * np.pi) - 0.5) / hz


def deskew_points(
    points: np.ndarray, heading: float, speed: float, yaw_rate: float, hz: float = SWEEP_HZ
) -> np.ndarray:
    """``points`` float [N, 3] of one sweep, in a frame whose origin is the sensor and whose
    axes are turned by ``heading`` (radians, anticlockwise) from the sensor's forward axis,
    given as fired while moving ``speed`` m/s forward and turning ``yaw_rate`` rad/s: float64
    [N, 3] as the sensor would see them standing at the sweep's middle, in the same frame.

    A point fired at time ``t`` is ``R(-w t) (p - v t x)`` of its place ``p`` at the middle;
    the azimuth that gives ``t`` is taken once from the skewed point, then once more from the
    de-skewed one."""
    p = np.asarray(points, dtype=np.float64)
    c, s = math.cos(heading), math.sin(heading)
    q = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]], 1)
    m = q
    for _ in range(2):
        t = sweep_time(np.arctan2(m[:, 1], m[:, 0]), hz)
        ca, sa = np.cos(yaw_rate * t), np.sin(yaw_rate * t)
        m = np.stack([ca * q[:, 0] - sa * q[:, 1] + speed * t, sa * q[:, 0] + ca * q[:, 1]], 1)
    return np.stack([c * m[:, 0] - s * m[:, 1], s * m[:, 0] + c * m[:, 1], p[:, 2]], 1)


def skew(
    points: np.ndarray, heading: float, speed: float, yaw_rate: float, hz: float = SWEEP_HZ
) -> np.ndarray:
    """The inverse of :func:`deskew_points` as a sensor that does not de-skew records it
    (each point's time from its azimuth at the sweep's middle): for tests and checks."""
    p = np.asarray(points, dtype=np.float64)
    c, s = math.cos(heading), math.sin(heading)
    q = np.stack([c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]], 1)
    t = sweep_time(np.arctan2(q[:, 1], q[:, 0]), hz)
    x, y = q[:, 0] - speed * t, q[:, 1]
    ca, sa = np.cos(-yaw_rate * t), np.sin(-yaw_rate * t)
    m = np.stack([ca * x - sa * y, sa * x + ca * y], 1)
    return np.stack([c * m[:, 0] - s * m[:, 1], s * m[:, 0] + c * m[:, 1], p[:, 2]], 1)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def run_motion(
    stamps: np.ndarray, steps: Sequence[np.ndarray | None], poses: np.ndarray
) -> np.ndarray:
    """Each node's motion through its sweep, float64 [N, 3]: heading (radians, in the node's
    local axes), forward speed (m/s) and yaw rate (rad/s), from the steps to and from its
    neighbours (``steps[k]`` lays node ``k + 1``'s frame into node ``k``'s, ``None`` where
    the odometry failed: the recorded relative pose stands in). ``stamps`` int [N]
    microseconds.

    The heading is the mean direction of the two steps, the speed their length over their
    time, the yaw rate the turn from one step's direction to the next's over the time between
    their middles (the vehicle goes where it points): a measure that holds whether the local
    frames turn with the vehicle or keep the map's axes (the keyframes'). An end node takes
    its one step, and its neighbour's yaw rate."""
    n = len(stamps)
    seconds = np.asarray(stamps, dtype=np.float64) * 1e-6
    rel = [
        s if s is not None else np.linalg.inv(poses[k]) @ poses[k + 1] for k, s in enumerate(steps)
    ]
    out = np.zeros((n, 3))
    rates = np.full(n, np.nan)
    for k in range(n):
        moves, dts = [], []
        if k > 0:  # from node k - 1 to node k, in node k's axes
            moves.append(-np.linalg.inv(rel[k - 1])[:2, 3])
            dts.append(seconds[k] - seconds[k - 1])
        if k < n - 1:
            moves.append(rel[k][:2, 3])
            dts.append(seconds[k + 1] - seconds[k])
        dirs = [math.atan2(m[1], m[0]) for m in moves]
        out[k, 0] = dirs[0] + _wrap(dirs[-1] - dirs[0]) / 2
        if sum(dts) > 0:
            out[k, 1] = sum(math.hypot(*m) for m in moves) / sum(dts)
        if len(dirs) == 2 and sum(dts) > 0:
            rates[k] = _wrap(dirs[1] - dirs[0]) / (sum(dts) / 2)
    known = np.flatnonzero(np.isfinite(rates))
    if len(known):
        out[:, 2] = rates[known[np.abs(np.arange(n)[:, None] - known[None]).argmin(1)]]
    return out


def skewed_sensors(root: str | Path) -> dict[str, float] | None:
    """For a tree made by ``pnvlad synth``: ``dataset/run`` -> the sweeps a second of the
    sensor that recorded it when its scans are skewed by the sweep, 0.0 when it de-skews (its
    ``synth.json`` says which sensor recorded each run, whether it de-skews and how fast it
    turns); ``None`` for any other tree."""
    import json

    path = Path(root) / "synth.json"
    if not path.is_file():
        return None
    meta = json.loads(path.read_text())
    preset = meta.get("preset", {})
    default = preset.get("lidar") or {}
    sensors = [*(preset.get("lidars") or []), default]

    def sweeps(cfg: dict) -> float:
        return 0.0 if cfg.get("deskewed", True) else float(cfg.get("rotation_hz", SWEEP_HZ))

    def rate(name: str) -> float:
        for cfg in sensors:
            if (cfg.get("name") or f"{cfg.get('beams')} beams") == name:
                return sweeps(cfg)
        return sweeps(default)

    return {f"{r['area']}/{r['run']}": rate(r.get("sensor", "")) for r in meta.get("runs", [])}
