"""A drive's settings in sections (pydantic): where its scans come from (``source``), what
is asked (``service``), how it is asked (the ``policy``, ``every``, ``odometry``, ``window_m``
and the tracker's rules, ``tracking``) and what is written (``output``).

``pnvlad localize --rosbag`` / ``--kitti`` fills one from its options; a program builds one
the same way (``DriveConfig(policy="per-scan", service={"url": ...})``). A value of the wrong
type is pydantic's ``ValidationError``; :func:`config_error` turns it into an
:class:`~pnvlad_service.errors.InputError` naming the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.rows import TRACKED, Policy
from pnvlad_service.localization.drive.rules import TrackerConfig


class _Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class SourceConfig(_Section):
    """Where the scans come from: a ROS bag (``rosbag`` with its ``cloud_topic`` and, for its
    poses, ``pose_topic`` or ``tf_frame``; ``truth_topic``: the true poses, for the errors;
    ``max_pose_gap``: seconds, default 2) or a KITTI sequence folder (``kitti``); placed in UTM
    by ``origin_ne`` (northing, easting of the pose frame's origin) and ``yaw_deg`` (its x
    axis, degrees counter-clockwise from east)."""

    rosbag: Path | None = None
    kitti: Path | None = None
    cloud_topic: str | None = None
    pose_topic: str | None = None
    tf_frame: str | None = None
    truth_topic: str | None = None
    max_pose_gap: float | None = None
    origin_ne: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0


class ServiceConfig(_Section):
    """What is asked: a server at ``url`` (``api_key``: its bearer token) or the bundle at
    ``index`` in this process (``model``: default the bundle's); ``top_n`` matches an answer;
    ``aligned_map`` (with ``index``): whether the map's drives agree (``pnvlad map align``), so
    that a scan is registered to the nearest entries of any of them (the rules of
    ``PriorSection.config``), not to a few of one. ``None`` (the default): as the bundle records
    (``pnvlad index build`` of a tree that ``map align`` wrote records it); a server follows its
    own bundle and settings (``PNVLAD_PRIOR_ALIGNED_MAP`` and the other ``PNVLAD_PRIOR_*``)."""

    url: str | None = None
    index: Path | None = None
    model: Path | None = None
    api_key: str | None = Field(default=None, repr=False)
    top_n: int = 5
    aligned_map: bool | None = None

    def localizer_config(self) -> Any:
        """The :class:`~..query.config.LocalizerConfig` a bundle in this process is loaded
        with (``None``: the defaults, which follow the bundle)."""
        if self.aligned_map is None:
            return None
        from pnvlad_service.localization.query.config import LocalizerConfig, PriorSection

        return LocalizerConfig(prior=PriorSection(aligned_map=self.aligned_map))


class OutputConfig(_Section):
    """What is written: ``out``.csv (a row a scan) and ``out``.png (``plot``; default: beside
    the source, named for the drive and the policy); ``map_bundle``: a copy of the server's
    bundle, to draw the map (with ``service.index`` that bundle is used); ``progress``: a
    progress bar on stderr.

    The robotics outputs (:mod:`pnvlad_service.localization.outputs`): ``foxglove``, the live
    view's ``(host, port)``; ``mcap``, the same to a file; ``ros2_bag``, a ROS 2 bag folder;
    ``trajectories``: TUM and KITTI files at ``trajectories``.tum, ...; ``utm_zone``: the map's
    zone when its bundle does not say (``""``: unknown, no latitude and longitude)."""

    out: Path | None = None
    map_bundle: Path | None = None
    plot: bool = True
    progress: bool = True
    foxglove: tuple[str, int] | None = None
    mcap: Path | None = None
    ros2_bag: Path | None = None
    trajectories: Path | None = None
    utm_zone: str | None = None


class DriveConfig(_Section):
    """A drive's settings: the ``policy`` (``tracked``: followed by the drive localiser;
    ``per-scan``: each scan asked alone), ``every`` Nth scan (default 1 tracked, 10 per-scan),
    the ``odometry`` of a tracked drive (``auto``, ``poses``, ``registered``, ``kiss-icp`` or
    ``none``),
    ``window_m`` (per-scan: ask with the last metres of driving laid together) and the
    sections."""

    policy: Policy = TRACKED
    every: int | None = None
    odometry: str = "auto"
    window_m: float | None = None
    source: SourceConfig = SourceConfig()
    service: ServiceConfig = ServiceConfig()
    tracking: TrackerConfig = TrackerConfig()
    output: OutputConfig = OutputConfig()

    @property
    def scan_every(self) -> int:
        """``every`` with its default for the policy."""
        return (1 if self.policy == TRACKED else 10) if self.every is None else self.every

    def check(self) -> None:
        """InputError naming the field for a value the drive cannot run with: ``every`` below
        1, a window that is not a positive length or not posed by poses or KISS-ICP."""
        if self.scan_every < 1:
            raise InputError(f"must be >= 1, got {self.scan_every}", "every")
        if self.service.aligned_map is not None and self.service.url is not None:
            raise InputError(
                "applies to --index (a server registers as its bundle and its own settings "
                "say: PNVLAD_PRIOR_ALIGNED_MAP)",
                "--aligned-map",
            )
        if self.window_m is not None:
            if not self.window_m > 0:
                raise InputError(
                    f"must be a positive number of metres, got {self.window_m}", "window_m"
                )
            if self.odometry not in ("auto", "poses", "kiss-icp"):
                raise InputError("a window is posed by the bag's poses or kiss-icp", "odometry")


def config_error(exc: ValidationError, prefix: str = "") -> InputError:
    """The first error of a pydantic ``ValidationError`` as an InputError naming its field
    (``prefix`` + the field's path, e.g. ``tracking.confirm``); a validator's own message is
    kept as it is."""
    first = exc.errors()[0]
    where = ".".join(str(p) for p in first.get("loc", ()))
    error = (first.get("ctx") or {}).get("error")
    message = str(error) if isinstance(error, Exception) else str(first.get("msg", exc))
    return InputError(message, f"{prefix}{where}" if where else prefix.rstrip(".") or None)
