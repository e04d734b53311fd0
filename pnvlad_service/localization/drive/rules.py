"""The drive localiser's rules (:class:`TrackerConfig`): when a fix is accepted, what tracking
keeps, when it is lost, and how a registration is weighed against the odometry. Measured choices:
docs/TRACKING.md."""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ConfigDict, field_validator

from pnvlad_service.localization.drive.fusion import OdometryNoise
from pnvlad_service.localization.verify.prior import DEFAULT_RADIUS_M


class TrackerConfig(BaseModel):
    """The localiser's rules; distances in metres, angles in degrees, times in seconds.

    ``radius_m``: the map entries within this of a prediction are registered to;
    ``confirm``: verified search answers that must agree with the odometry between them before
    a fix is accepted (1: the first verified answer); ``agree_m`` / ``agree_share`` /
    ``agree_deg``: they agree when the motion between them differs from the odometry's by at
    most ``agree_m`` plus ``agree_share`` of the distance driven, and ``agree_deg``;
    ``confirm_within_s``: candidates older than this are dropped; ``failures``: tracking
    failures in a row that make the localiser lost; ``reach_m`` / ``reach_share``: after a
    loss, a search answer farther than ``reach_m`` plus ``reach_share`` of the distance driven
    from where the odometry carries the last verified pose is checked by tracking it over
    ``far_confirm_m`` metres before it is a fix; ``gate_m`` / ``gate_deg``: a registration
    that moves the prediction by more is a failure; ``max_gap_s``: a longer gap between two
    scans starts a search; ``max_speed_mps`` / ``max_turn_dps``: odometry moving faster
    jumped (a search starts, and its motion is not used); ``fuse``: each registration weighed
    against the odometry's prediction by their covariances (:mod:`.fusion`), the odometry's
    error a step ``odometry_sigma_m`` + ``odometry_share`` of the distance and
    ``odometry_sigma_deg`` + ``odometry_turn_share`` of the turn; a registration the service
    did not verify (too loose along a direction, or fitting under its threshold) that fits at
    ``fuse_min_fitness`` or more, within the gates and as the odometry expects it, is then
    verified when the weighed pose's largest horizontal standard deviation is at most
    ``max_sigma_m``. ``fuse`` unset (``None``) is on here; ``pnvlad localize --follow`` sets
    it from the odometry (:func:`~.runner.tracker_config`: on only with ``--odometry
    registered``), so a library caller whose odometry is a recorded GNSS/INS stream passes
    ``fuse=False`` to follow as that command does. A value out of range is a
    ``ValueError`` (pydantic's ``ValidationError``) naming the field.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    radius_m: float = DEFAULT_RADIUS_M
    confirm: int = 2
    agree_m: float = 3.0
    agree_share: float = 0.05
    agree_deg: float = 5.0
    confirm_within_s: float = 30.0
    failures: int = 3
    reach_m: float = 30.0
    reach_share: float = 0.1
    far_confirm_m: float = 50.0
    gate_m: float = 3.0
    gate_deg: float = 5.0
    max_gap_s: float = 2.0
    max_speed_mps: float = 50.0
    max_turn_dps: float = 180.0
    fuse: bool | None = None
    odometry_sigma_m: float = OdometryNoise.sigma_m
    odometry_share: float = OdometryNoise.share
    odometry_sigma_deg: float = OdometryNoise.sigma_deg
    odometry_turn_share: float = OdometryNoise.turn_share
    max_sigma_m: float = 1.0
    fuse_min_fitness: float = 0.3

    @field_validator("confirm", "failures")
    @classmethod
    def _at_least_one(cls, value: int) -> int:
        if value < 1:
            raise ValueError("confirm and failures must be at least 1")
        return value

    @field_validator("radius_m", "agree_m", "agree_deg", "gate_m", "gate_deg", "max_gap_s",
                     "max_speed_mps", "max_turn_dps", "confirm_within_s", "reach_m",
                     "far_confirm_m", "odometry_sigma_m", "odometry_sigma_deg",
                     "max_sigma_m")  # fmt: skip
    @classmethod
    def _positive(cls, value: float, info: Any) -> float:
        if not value > 0:
            raise ValueError(f"{info.field_name} must be > 0, got {value}")
        return value

    @field_validator("reach_share", "odometry_share", "odometry_turn_share", "fuse_min_fitness")
    @classmethod
    def _not_negative(cls, value: float, info: Any) -> float:
        if not 0 <= value < math.inf:
            raise ValueError(f"{info.field_name} must be >= 0, got {value}")
        return value

    def odometry_noise(self) -> OdometryNoise:
        return OdometryNoise(self.odometry_sigma_m, self.odometry_share,
                             self.odometry_sigma_deg, self.odometry_turn_share)  # fmt: skip
