"""The drive runner: the scans of a drive, in order, to the service by one of two policies, one
:class:`~.rows.DriveRow` a scan.

:func:`run_drive` takes any drive (``timestamps``, ``scan(i)``, and ``poses`` when it has a
pose stream; :class:`pnvlad_service.data.drive.Drive`) and knows nothing of where its scans
come from, nor of where the answers come from (an :class:`~.service.Ask`). The policy says what
is asked:

- ``per-scan``: scans 0, ``every``, 2 * ``every``, ... each asked alone (a search; with
  :class:`Windows`, the last stretch of the drive laid together); a refused scan (too few
  points left by G, ...) is a row with its reason, not the end of the drive.
- ``tracked``: every ``every``-th scan to a :class:`~.tracking.DriveLocalizer` with the
  odometry chosen (the drive's poses, KISS-ICP on the scans, or none): it searches until a
  fix is confirmed, then registers each scan near the predicted pose, and says when lost.

With the drive's true poses each row gets its errors; with the map's positions
(:class:`~.maps.DriveMap`) how far the truth is from the nearest map entry, and with the map's
own truth how far the pose is from where the map itself would put the scan.
"""

from __future__ import annotations

import itertools
import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import replace
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.rows import PER_SCAN, TRACKED, DriveRow, Policy
from pnvlad_service.localization.drive.scan_steps import ScanSteps, StepsAhead
from pnvlad_service.localization.drive.service import Ask, Reply
from pnvlad_service.localization.drive.tracking import (
    DriveLocalizer,
    DriveScan,
    TrackerConfig,
    wrap_deg,
    yaw_of,
)
from pnvlad_service.localization.outputs.sinks import Outputs, Sink
from pnvlad_service.localization.outputs.step import DriveStep, roll_pitch_yaw, upper_triangle

#: Where a tracked drive's motion between scans comes from.
ODOMETRY = ("auto", "poses", "registered", "kiss-icp", "none")
#: A drive of at least this many scans has its refined steps taken one scan ahead in a worker
#: process (:class:`~.scan_steps.StepsAhead`; it starts in about a second) on a machine of two
#: cores or more; a shorter one steps them in this process.
AHEAD_MIN_SCANS = 100


def choose_odometry(choice: str, has_poses: bool) -> str:
    """``odometry``: ``auto`` resolved (the drive's poses with their steps refined by the
    scans, else KISS-ICP when installed, else none); InputError naming ``odometry`` for an
    unknown choice or poses the drive lacks."""
    if choice not in ODOMETRY:
        raise InputError(
            f"must be auto, poses, registered, kiss-icp or none, got {choice!r}", "odometry"
        )
    if choice in ("poses", "registered") and not has_poses:
        raise InputError("the drive has no poses: give --pose-topic or --tf, or choose "
                         "kiss-icp or none", "odometry")  # fmt: skip
    if choice != "auto":
        return choice
    if has_poses:
        return "registered"
    import importlib.util

    return "kiss-icp" if importlib.util.find_spec("kiss_icp") is not None else "none"


class Windows:
    """The windows of a per-scan drive with accumulated queries: every scan of the drive up to
    the one asked about goes into a :class:`~pnvlad_service.data.accumulate.WindowAccumulator`
    of ``window_m`` metres (the code ``pnvlad data prepare`` lays submaps with), posed by the
    drive's ``poses`` or, with ``odometry``, by LiDAR odometry on the scans (KISS-ICP, extra
    ``odometry``); the window is asked about in the newest scan's axes, its scans laid as the
    map's were (``map_record``: the bundle manifest's ``map`` entry, see
    :meth:`~pnvlad_service.data.accumulate.WindowAccumulator.for_map`)."""

    def __init__(self, window_m: float, odometry: bool = False, map_record: Any = None) -> None:
        from pnvlad_service.data.accumulate import WindowAccumulator

        self.accumulator = WindowAccumulator.for_map(map_record, window_m, frame="sensor")
        self.odometry: Any = None
        if odometry:
            from pnvlad_service.data.sources.odometry import LidarOdometry

            self.odometry = LidarOdometry()
        self.taken = 0

    def through(self, drive: Any, i: int) -> np.ndarray:
        """Take scans up to ``i`` (in order; each once) and return the window's points."""
        poses = getattr(drive, "poses", None)
        if self.odometry is None and poses is None:
            raise InputError(
                "accumulated queries need poses: a pose topic or /tf, or odometry",
                getattr(drive, "name", "drive"),
            )
        for j in range(self.taken, i + 1):
            pts = drive.scan(j)
            pose = poses[j] if self.odometry is None else self.odometry.update(pts)
            self.accumulator.add(pts, pose)
        self.taken = i + 1
        return self.accumulator.cloud()


class _PerScan:
    """Each scan asked alone: the top-1 match, the answer's verdict and pose."""

    desc, unit, nothing = "replay", "query", "no scans to replay"

    def __init__(self, ask: Ask, windows: Windows | None) -> None:
        self.ask, self.windows = ask, windows
        self.points: np.ndarray | None = None
        self.covariance: np.ndarray | None = None

    def fill(self, drive: Any, i: int, row: DriveRow) -> np.ndarray | None:
        t0 = time.perf_counter()
        reply = None
        self.points = self.covariance = None
        try:
            if self.windows is None:
                self.points = drive.scan(i)
                reply = self.ask(self.points)
            else:
                reply = self.ask(self.windows.through(drive, i), None, "window")
        except InputError as exc:
            row.status = f"refused: {getattr(exc, 'detail', None) or exc}"
        row.step_ms = (time.perf_counter() - t0) * 1e3
        if reply is None:
            return None
        _timings(row, reply)
        if reply.top is None:
            row.status = "no match"
            return None
        top = reply.top
        row.submap, row.run, row.kind = top.timestamp, top.run, top.kind
        row.northing, row.easting, row.distance = top.northing, top.easting, top.distance
        row.verified, row.confidence = reply.verified, reply.confidence
        self.covariance = reply.covariance if reply.pose is not None else None
        return reply.pose

    def postfix(self, row: DriveRow) -> dict[str, str]:
        return {} if row.error_m is None else {"error": f"{row.error_m:.1f} m"}

    def close(self) -> None:
        pass


def tracker_config(config: TrackerConfig | None, odometry: str) -> TrackerConfig:
    """The tracker's rules for a drive followed with ``odometry``: ``fuse`` unset is on only
    with the recorded steps refined by the scans (``registered``, millimetres off a step); the
    recorded GNSS/INS steps alone are decimetres off, KISS-ICP's scans drift, and without
    odometry there is nothing to weigh against (docs/TRACKING.md)."""
    config = config or TrackerConfig()
    if config.fuse is None:
        config = config.model_copy(update={"fuse": odometry == "registered"})
    return config


class _Tracked:
    """Every scan to the drive localiser, with the odometry chosen."""

    desc, unit, nothing = "follow", "scan", "no scans to follow"

    def __init__(
        self,
        ask: Ask,
        odometry: str,
        poses: np.ndarray | None,
        config: TrackerConfig | None,
        initial_pose: np.ndarray | None,
    ) -> None:
        if odometry in ("poses", "registered") and poses is None:
            raise InputError("the drive has no poses to use as odometry", "odometry")
        self.odometry, self.poses = odometry, poses
        self.lidar = None
        self.ahead: StepsAhead | None = None
        self.steps = ScanSteps() if odometry == "registered" else None
        if odometry == "kiss-icp":
            from pnvlad_service.data.sources.odometry import LidarOdometry

            self.lidar = LidarOdometry()
        config = tracker_config(config, odometry)
        self.localizer = DriveLocalizer(ask, config, initial_pose=initial_pose)
        self.points: np.ndarray | None = None
        self.covariance: np.ndarray | None = None
        self.step: Any = None
        # With a worker: the scan after each one asked, and the scans handed to it already.
        self.after: dict[int, int] = {}
        self.pending: dict[int, tuple[np.ndarray, Future[np.ndarray | None]]] = {}

    def go_ahead(self, order: Sequence[int], ahead: bool | None) -> None:
        """With ``ahead`` (None: with :data:`AHEAD_MIN_SCANS` scans or more in ``order`` and
        two cores), take the refined steps in a worker, each scan's while the one before it in
        ``order`` (the scans to be asked, in order) is localised."""
        if ahead is None:
            ahead = len(order) >= AHEAD_MIN_SCANS and (os.cpu_count() or 1) >= 2
        if ahead and self.steps is not None:
            # One thread in the worker: this process's registrations take both cores in
            # turn, and the worker fills the gaps (G runs on one).
            one = replace(self.steps.config.registration, threads=1)
            self.ahead, self.steps = StepsAhead(replace(self.steps.config, registration=one)), None
            self.after = dict(itertools.pairwise(order))

    def close(self) -> None:
        if self.ahead is not None:
            self.ahead.close()

    def fill(self, drive: Any, i: int, row: DriveRow) -> np.ndarray | None:
        t0 = time.perf_counter()
        odo = None
        if self.ahead is not None:
            # This scan's step was taken while the last scan was localised; the next scan's is
            # taken while this one is.
            points, stepped = self.pending.pop(i, None) or self._hand_over(drive, i)
            if i in self.after:
                self.pending[self.after[i]] = self._hand_over(drive, self.after[i])
            t1 = time.perf_counter()
            odo = stepped.result()
        else:
            points = drive.scan(i)
            t1 = time.perf_counter()
            if self.odometry == "poses":
                assert self.poses is not None
                odo = self.poses[i]
            elif self.steps is not None:
                assert self.poses is not None
                odo = self.steps.update(points, self.poses[i])
            elif self.lidar is not None:
                try:
                    odo = self.lidar.update(points)
                except InputError:
                    odo = None
        self.points = points
        t2 = time.perf_counter()
        step = self.step = self.localizer.step(DriveScan(i, row.timestamp, points, odo))
        # A registered pose's covariance is its registration's (weighed with the odometry's);
        # a fix found by search and a pose carried on by the odometry have none.
        self.covariance = step.covariance if step.how == "registered" else None
        row.state, row.verified, row.how = step.state, step.verified, step.how
        row.event = step.event
        row.fitness, row.sigma_m, row.confidence = step.fitness, step.sigma_m, step.confidence
        row.anchor, row.reason = step.anchor, step.reason
        row.read_ms, row.odometry_ms = (t1 - t0) * 1e3, (t2 - t1) * 1e3
        row.step_ms = step.seconds * 1e3
        if step.reply is not None:
            row.correction_m = step.reply.correction_m
            _timings(row, step.reply)
        return step.pose

    def _hand_over(self, drive: Any, i: int) -> tuple[np.ndarray, Future[np.ndarray | None]]:
        """Scan ``i`` read and handed to the worker: (its points, the future of its pose)."""
        assert self.ahead is not None and self.poses is not None
        points = drive.scan(i)
        return points, self.ahead.submit(points, self.poses[i])

    def postfix(self, row: DriveRow) -> dict[str, str]:
        if row.pose_error_m is not None and row.verified:
            return {"state": str(row.state), "error": f"{row.pose_error_m:.2f} m"}
        return {"state": str(row.state)}


def _timings(row: DriveRow, reply: Reply) -> None:
    row.asked = reply.mode
    row.stages_ms = dict(reply.timings_ms)
    row.server_ms = row.stages_ms.get("total")


def run_drive(
    drive: Any,
    ask: Ask,
    policy: Policy = TRACKED,
    *,
    every: int | None = None,
    odometry: str = "poses",
    truth: np.ndarray | None = None,
    config: TrackerConfig | None = None,
    positions: Any = None,
    truth_of_map: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    windows: Windows | None = None,
    initial_pose: np.ndarray | None = None,
    progress: bool = True,
    outputs: Outputs | Sequence[Sink] = (),
    ahead: bool | None = None,
) -> list[DriveRow]:
    """Scans 0, ``every``, 2 * ``every``, ... of ``drive`` asked by ``policy``
    (``every`` default: 1 tracked, 10 per-scan): one :class:`~.rows.DriveRow` a scan.

    ``odometry`` (tracked): ``poses`` (the drive's ``poses``), ``registered`` (their steps
    refined by registering each scan onto the one before it, :mod:`.scan_steps`), ``kiss-icp``
    (:class:`~pnvlad_service.data.sources.odometry.LidarOdometry` on the scans, extra
    ``odometry``) or ``none`` (constant velocity); ``config``, ``initial_pose``: the
    :class:`~.tracking.DriveLocalizer`'s; ``windows`` (per-scan): ask with accumulated
    windows; ``truth``: float64 [T, 4, 4] sensor -> UTM of every scan of ``drive`` (NaN: no
    truth for that scan), for the errors; ``positions``: the map's
    :class:`~..prior.MapPositions` (``off_map_m``); ``truth_of_map``: :func:`~.maps.map_truth`
    (``map_error_m``); ``ahead`` (tracked, ``registered``): take each scan's refined step in a
    worker process while the scan before it is localised (the same steps; None: with
    :data:`AHEAD_MIN_SCANS` scans or more and two cores)."""
    from pnvlad_service.progress import tqdm

    every = (1 if policy == TRACKED else 10) if every is None else every
    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "every")
    stamps = np.asarray(drive.timestamps, dtype=np.int64)
    runner: _PerScan | _Tracked
    if policy == PER_SCAN:
        runner = _PerScan(ask, windows)
    elif policy == TRACKED:
        runner = _Tracked(ask, odometry, getattr(drive, "poses", None), config, initial_pose)
    else:
        raise InputError(f"must be per-scan or tracked, got {policy!r}", "policy")
    if len(stamps) == 0:
        raise InputError(runner.nothing, getattr(drive, "name", "drive"))
    if truth is not None and len(truth) != len(stamps):
        raise InputError(f"{len(truth)} true poses for {len(stamps)} scans", "truth")
    driven = None if truth is None else _driven(truth[:, :3, 3])
    order = range(0, len(stamps), every)
    if isinstance(runner, _Tracked):
        runner.go_ahead(order, ahead)
    sinks = outputs if isinstance(outputs, Outputs) else Outputs(outputs)
    if sinks is not outputs:
        sinks.start(None)
    rows: list[DriveRow] = []
    bar = tqdm(order, desc=runner.desc, unit=runner.unit, disable=None if progress else True)
    try:
        for i in bar:
            since_s = float(stamps[i] - stamps[0]) / 1e6
            row = DriveRow(scan=i, timestamp=int(stamps[i]), time_s=since_s)
            pose = runner.fill(drive, i, row)
            if pose is not None:
                _pose_columns(row, pose, runner.covariance)
            known = truth is not None and np.isfinite(truth[i]).all()
            if known:
                _errors(row, pose, truth[i], truth_of_map)
                row.driven_m = None if driven is None else float(driven[i])
                if positions is not None:
                    row.off_map_m = positions.nearest_m(row.true_northing, row.true_easting)
            rows.append(row)
            if sinks:
                sinks.step(_step(row, pose, runner, truth[i] if known else None))
            bar.set_postfix(runner.postfix(row), refresh=False)
    finally:
        runner.close()
        bar.close()
    if sinks is not outputs:
        sinks.close()
    return rows


def _pose_columns(row: DriveRow, pose: np.ndarray, covariance: np.ndarray | None) -> None:
    """The pose's columns: UTM northing, easting, height; yaw, roll, pitch (degrees); the
    covariance's 21 values."""
    row.pose_northing, row.pose_easting = float(pose[1, 3]), float(pose[0, 3])
    row.pose_height = float(pose[2, 3])
    row.pose_yaw_deg = yaw_of(pose)
    roll, pitch, _ = roll_pitch_yaw(pose[:3, :3])
    row.pose_roll_deg, row.pose_pitch_deg = math.degrees(roll), math.degrees(pitch)
    row.covariance = None if covariance is None else upper_triangle(covariance)


def _step(
    row: DriveRow, pose: np.ndarray | None, runner: _PerScan | _Tracked, true: np.ndarray | None
) -> DriveStep:
    """The scan as the outputs say it (:class:`DriveStep`), from its row."""
    return DriveStep(
        scan=row.scan, stamp_ns=row.timestamp * 1000, state=row.state, event=row.event,
        reason=row.reason, how=row.how, verified=row.verified, pose=pose,
        covariance=runner.covariance if pose is not None else None, truth=true,
        points=runner.points, pose_error_m=row.pose_error_m,
        pose_yaw_error_deg=row.pose_yaw_error_deg, sigma_m=row.sigma_m, fitness=row.fitness,
        confidence=row.confidence,
    )  # fmt: skip


def _driven(xyz: np.ndarray) -> np.ndarray:
    """Metres driven to each pose (a step to or from a pose without truth counts 0)."""
    steps = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(np.nan_to_num(steps, nan=0.0))]


def _errors(
    row: DriveRow,
    pose: np.ndarray | None,
    true: np.ndarray,
    truth_of_map: dict[str, tuple[np.ndarray, np.ndarray]] | None,
) -> None:
    """The truth's columns, the top-1 match's error, the pose's errors against the truth and
    (``truth_of_map``) against where the map itself puts the scan."""
    row.true_northing, row.true_easting = float(true[1, 3]), float(true[0, 3])
    row.true_yaw_deg = yaw_of(true)
    if row.northing is not None and row.easting is not None:
        row.error_m = math.hypot(row.northing - row.true_northing, row.easting - row.true_easting)
    if pose is None:
        return
    row.pose_error_m = math.hypot(pose[1, 3] - true[1, 3], pose[0, 3] - true[0, 3])
    row.pose_yaw_error_deg = abs(wrap_deg(yaw_of(pose) - row.true_yaw_deg))
    known = None if truth_of_map is None or row.anchor is None else truth_of_map.get(row.anchor)
    if known is not None:
        on_map, true_anchor = known
        there = on_map @ np.linalg.inv(true_anchor) @ true  # where the map itself puts the scan
        row.map_error_m = math.hypot(pose[1, 3] - there[1, 3], pose[0, 3] - there[0, 3])
        row.map_yaw_error_deg = abs(wrap_deg(yaw_of(pose) - yaw_of(there)))
