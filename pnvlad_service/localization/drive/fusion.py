"""The tracked pose as a planar Kalman filter: the odometry predicts, each registration corrects.

A registration alone is as good as the map entries around the robot and their geometry: on a
street of plain facades it is loose along the street (a standard deviation of a metre), and a
registration that slides there moves the pose with it. The odometry between two scans (the
recorded steps refined by the scans) is a few millimetres off. Weighing the two by their
covariances, as hdl_localization's UKF and every localisation stack does, holds the pose to
the odometry where the map does not constrain it and to the map where it does.

The state is the sensor's horizontal position and heading ``(x, y, yaw)`` in UTM axes and its
covariance ``P`` [3, 3]; height, roll and pitch are the registration's.
:meth:`PlanarFilter.predict` moves it by the odometry's motion (``P`` grows by
:class:`OdometryNoise`); :meth:`PlanarFilter.weigh` weighs a registration (the pose and the x,
y, yaw block of its covariance) against it and :meth:`PlanarFilter.commit` keeps the result. A
registration whose innovation the two covariances do not explain (the Mahalanobis distance
over ``gate``) is not fused: the filter starts again from it, so that a wrong prediction cannot
hold the pose away from the map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pnvlad_service.localization.verify.prior import UNCONSTRAINED

#: The x, y and yaw rows of a registration's covariance (x, y, z, roll, pitch, yaw).
XY_YAW = (0, 1, 5)


@dataclass(frozen=True)
class OdometryNoise:
    """The odometry's error over one step, as standard deviations: ``sigma_m`` + ``share`` of
    the distance driven (each horizontal axis) and ``sigma_deg`` + ``turn_share`` of the turn.
    The defaults fit the recorded steps refined by the scans (a few millimetres a step at the
    median, centimetres at p99)."""

    sigma_m: float = 0.02
    share: float = 0.02
    sigma_deg: float = 0.05
    turn_share: float = 0.02

    def covariance(self, motion: np.ndarray) -> np.ndarray:
        """float64 [3, 3]: the noise a step ``motion`` (sensor frame, [4, 4]) adds."""
        moved = float(np.linalg.norm(motion[:2, 3]))
        turned = abs(math.atan2(motion[1, 0], motion[0, 0]))
        s = self.sigma_m + self.share * moved
        y = math.radians(self.sigma_deg) + self.turn_share * turned
        return np.diag([s * s, s * s, y * y])


def heading(pose: np.ndarray) -> float:
    """The heading of a pose's (float [4, 4]) x axis, radians counter-clockwise from east."""
    return math.atan2(pose[1, 0], pose[0, 0])


def planar(pose: np.ndarray) -> np.ndarray:
    """float64 [3]: a pose's (x, y, yaw)."""
    return np.array([pose[0, 3], pose[1, 3], heading(pose)])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def with_planar(pose: np.ndarray, state: np.ndarray) -> np.ndarray:
    """``pose`` (float [4, 4]) moved to the horizontal position and heading ``state``: turned
    about the vertical axis, its height, roll and pitch kept."""
    d = _wrap(float(state[2]) - heading(pose))
    c, s = math.cos(d), math.sin(d)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = np.array(pose, dtype=np.float64, copy=True)
    out[:3, :3] = turn @ out[:3, :3]
    out[0, 3], out[1, 3] = float(state[0]), float(state[1])
    return out


@dataclass
class Fused:
    """A weighing's result: the ``pose`` (float64 [4, 4]) and its covariance ``P`` (x, y, yaw),
    its horizontal standard deviation ``sigma_m`` (the larger axis), whether the registration
    was ``fused`` (else the result is the registration alone) and the innovation's squared
    Mahalanobis ``distance``."""

    pose: np.ndarray
    P: np.ndarray
    sigma_m: float
    fused: bool
    distance: float


class PlanarFilter:
    """The tracked pose's (x, y, yaw) and covariance (see the module doc). Empty until
    :meth:`start`; :meth:`clear` empties it (a search, a prediction without odometry)."""

    def __init__(self, noise: OdometryNoise | None = None, gate: float = 16.27) -> None:
        self.noise = noise or OdometryNoise()
        self.gate = gate  # chi-square, 3 degrees of freedom, 0.999
        self.P: np.ndarray | None = None

    @property
    def ready(self) -> bool:
        return self.P is not None

    def clear(self) -> None:
        self.P = None

    def start(self, covariance: np.ndarray | None, default_sigma_m: float = 0.5,
              default_sigma_deg: float = 1.0) -> None:  # fmt: skip
        """Start from a pose whose covariance is ``covariance`` ([6, 6] as a registration's,
        or ``None``: ``default_sigma_m`` and ``default_sigma_deg``)."""
        if covariance is None:
            s, y = default_sigma_m, math.radians(default_sigma_deg)
            self.P = np.diag([s * s, s * s, y * y])
        else:
            self.P = _block(covariance)

    def predict(self, pose_before: np.ndarray, motion: np.ndarray) -> None:
        """The covariance carried by one odometry ``motion`` from ``pose_before``: a heading
        error at the start moves the end sideways by the step's length."""
        if self.P is None:
            return
        step = pose_before[:2, :2] @ motion[:2, 3]
        F = np.eye(3)
        F[0, 2], F[1, 2] = -step[1], step[0]
        self.P = F @ self.P @ F.T + self.noise.covariance(motion)

    def weigh(self, predicted: np.ndarray, registered: np.ndarray,
              covariance: np.ndarray) -> Fused:  # fmt: skip
        """The ``registered`` pose (its [6, 6] ``covariance``) weighed against the
        ``predicted`` one; the filter is unchanged until :meth:`commit`."""
        R = _block(covariance)
        z = planar(registered)
        alone = np.array(registered, dtype=np.float64)
        if self.P is None:
            return Fused(alone, R, _sigma(R), False, math.nan)
        x = planar(predicted)
        nu = z - x
        nu[2] = _wrap(float(nu[2]))
        S = self.P + R
        try:
            S_inv = np.linalg.inv(S)
        except np.linalg.LinAlgError:
            return Fused(alone, R, _sigma(R), False, math.nan)
        d2 = float(nu @ S_inv @ nu)
        if not math.isfinite(d2) or d2 > self.gate:
            return Fused(alone, R, _sigma(R), False, d2)
        K = self.P @ S_inv
        I_K = np.eye(3) - K
        P = I_K @ self.P @ I_K.T + K @ R @ K.T  # Joseph's form: stays positive
        P = (P + P.T) / 2
        return Fused(with_planar(registered, x + K @ nu), P, _sigma(P), True, d2)

    def commit(self, fused: Fused) -> None:
        """Keep a weighing's covariance as the filter's."""
        self.P = fused.P


def with_block(covariance: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A registration's [6, 6] ``covariance`` with its x, y and yaw block the filter's ``P``
    and their cross terms with height, roll and pitch dropped (the filter does not carry
    them)."""
    out = np.array(covariance, dtype=np.float64, copy=True)
    idx = np.array(XY_YAW)
    rest = np.setdiff1d(np.arange(6), idx)
    out[np.ix_(idx, rest)] = 0.0
    out[np.ix_(rest, idx)] = 0.0
    out[np.ix_(idx, idx)] = P
    return out


def _block(covariance: np.ndarray) -> np.ndarray:
    """The x, y, yaw block of a [6, 6] covariance; a value that is not finite is a direction
    nothing measured (:data:`UNCONSTRAINED`, as the registration gives one)."""
    c = np.asarray(covariance, dtype=np.float64)[np.ix_(XY_YAW, XY_YAW)].copy()
    bad = ~np.isfinite(c)
    if bad.any():
        c[bad] = 0.0
        c[np.diag_indices(3)] = np.where(bad.diagonal(), UNCONSTRAINED, c.diagonal())
    return (c + c.T) / 2


def _sigma(P: np.ndarray) -> float:
    return float(math.sqrt(max(np.linalg.eigvalsh(P[:2, :2])[-1], 0.0)))
