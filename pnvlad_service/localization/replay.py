"""Replaying a drive against the localisation service: one query every Nth scan, a CSV and a map.

:func:`replay` sends scans of a drive (a :class:`~pnvlad_service.data.sources.rosbag.RosbagClouds`
or any object with ``timestamps`` and ``scan(i)``; with ``poses`` too, each answer gets its error)
to an ``ask`` function (a raw scan -> the service's JSON answer: ``LocalizeClient.localize`` with
``preprocess=True``, or a local ``Localizer``) and returns one :class:`ReplayRow` a query.
:func:`write_replay_csv` writes them, :func:`summarise` gives the summary line's figures and
:func:`plot_replay` the PNG (extra ``plot``): the map's submap positions in grey, the drive's
trajectory, the answers coloured by whether they were verified, and each answer's error in
metres along the drive. A refused query (too few points left by G, ...) is a row with its
reason, not the end of the replay.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.fileio import atomic_open, atomic_write_rows

#: Errors beyond this many metres are counted apart in the summary (a wrong place).
FAR_M = 25.0
#: A verified pose farther than this from the truth is a wrong verified pose.
WRONG_POSE_M = 5.0


@dataclass
class ReplayRow:
    """One query: the scan, the service's top-1 match and its answer-level verification and
    pose (``None`` fields where it gave none), and, where the drive has poses, the truth and
    the errors: ``error_m`` of the top-1 entry's position, ``pose_error_m`` /
    ``pose_yaw_error_deg`` of the verified pose."""

    scan: int
    timestamp: int
    time_s: float
    status: str = "ok"
    submap: int | None = None
    run: str | None = None
    kind: str | None = None
    northing: float | None = None
    easting: float | None = None
    distance: float | None = None
    verified: bool | None = None
    confidence: float | None = None
    pose_northing: float | None = None
    pose_easting: float | None = None
    pose_yaw_deg: float | None = None
    true_northing: float | None = None
    true_easting: float | None = None
    true_yaw_deg: float | None = None
    error_m: float | None = None
    pose_error_m: float | None = None
    pose_yaw_error_deg: float | None = None

    @property
    def answered(self) -> bool:
        return self.northing is not None


#: The CSV's columns, in order: :class:`ReplayRow`'s fields.
COLUMNS = tuple(ReplayRow.__dataclass_fields__)


def replay(
    drive: Any,
    ask: Callable[[np.ndarray], dict[str, Any]],
    *,
    every: int = 10,
    refused: tuple[type[BaseException], ...] = (InputError,),
    progress: bool = True,
    window: Any = None,
) -> list[ReplayRow]:
    """Ask ``ask`` about scans 0, ``every``, 2 * ``every``, ... of ``drive``.

    With ``window`` (:class:`Windows`) every scan is taken into it and each query is the last
    stretch of the drive laid together, asked as ``ask(points, "window")``.

    ``ask(points)`` returns the service's answer (``{"matches": [{"timestamp", "run",
    "northing", "easting", "distance", ...}, ...], "verified", "verification": {"confidence",
    ...}, "pose": {"northing", "easting", "yaw_deg", ...}}``); an exception of a ``refused``
    type makes a row whose ``status`` is its message. With ``drive.poses`` (float64 [T, 4, 4],
    UTM) each answer gets the scan's true position and heading and its errors.
    """
    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "every")
    from pnvlad_service.progress import tqdm

    stamps = np.asarray(drive.timestamps, dtype=np.int64)
    if len(stamps) == 0:
        raise InputError("no scans to replay", getattr(drive, "name", "drive"))
    poses = getattr(drive, "poses", None)
    rows = []
    indices = range(0, len(stamps), every)
    bar = tqdm(indices, desc="replay", unit="query", disable=not progress)
    for i in bar:
        row = ReplayRow(scan=i, timestamp=int(stamps[i]), time_s=float(stamps[i] - stamps[0]) / 1e6)
        if poses is not None:
            row.true_northing = float(poses[i, 1, 3])
            row.true_easting = float(poses[i, 0, 3])
            row.true_yaw_deg = math.degrees(math.atan2(poses[i, 1, 0], poses[i, 0, 0]))
        try:
            if window is None:
                answer = ask(drive.scan(i))
            else:
                answer = ask(window.through(drive, i), "window")
        except refused as exc:
            row.status = f"refused: {getattr(exc, 'detail', None) or exc}"
            rows.append(row)
            continue
        fill_row(row, answer)
        rows.append(row)
        if row.error_m is not None:
            bar.set_postfix(error=f"{row.error_m:.1f} m", refresh=False)
    bar.close()
    return rows


class Windows:
    """The windows of a replay with accumulated queries: every scan of the drive up to the one
    asked about goes into a :class:`~pnvlad_service.data.accumulate.WindowAccumulator` of
    ``window_m`` metres (the code ``pnvlad data prepare`` lays submaps with), posed by the
    drive's ``poses`` (a pose topic, /tf) or, with ``odometry``, by LiDAR odometry on the scans
    (KISS-ICP, extra ``odometry``); the window is asked about in the newest scan's axes, its
    scans laid as the map's were (``map_record``: the bundle manifest's ``map`` entry, see
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


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def fill_row(row: ReplayRow, answer: dict[str, Any]) -> None:
    """``row``'s answer fields from the service's answer, and its errors where the truth is
    known: the top-1 match, the answer-level ``verified`` and ``confidence``, the ``pose``."""
    matches = answer.get("matches") or []
    if not matches:
        row.status = "no match"
        return
    top = matches[0]
    row.submap = int(top["timestamp"])
    row.run = str(top.get("run", ""))
    row.kind = top.get("kind")
    row.northing = float(top["northing"])
    row.easting = float(top["easting"])
    row.distance = None if top.get("distance") is None else float(top["distance"])
    row.verified = answer.get("verified")
    confidence = (answer.get("verification") or {}).get("confidence")
    row.confidence = None if confidence is None else float(confidence)
    pose = answer.get("pose")
    if pose:
        row.pose_northing = float(pose["northing"])
        row.pose_easting = float(pose["easting"])
        row.pose_yaw_deg = float(pose["yaw_deg"])
    if row.true_northing is None or row.true_easting is None:
        return
    row.error_m = math.hypot(row.northing - row.true_northing, row.easting - row.true_easting)
    if row.pose_northing is not None and row.pose_easting is not None:
        row.pose_error_m = math.hypot(
            row.pose_northing - row.true_northing, row.pose_easting - row.true_easting
        )
        if row.pose_yaw_deg is not None and row.true_yaw_deg is not None:
            row.pose_yaw_error_deg = abs(_wrap_deg(row.pose_yaw_deg - row.true_yaw_deg))


def write_replay_csv(rows: Sequence[ReplayRow], path: str | Path) -> Path:
    """The rows as a CSV (atomically), one column a :class:`ReplayRow` field (:data:`COLUMNS`):
    the scan, the top-1 match, ``verified``, ``confidence``, the pose, the truth, the errors."""
    return atomic_write_rows(rows, COLUMNS, path)


@dataclass(frozen=True)
class ReplaySummary:
    """The summary line's figures. The error figures are ``None`` without poses; ``verified``
    is ``None`` when the service gives no verification; pose errors are the verified poses'."""

    queries: int
    answered: int
    within: int | None
    median_error_m: float | None
    beyond_m: int | None
    verified: int | None
    median_pose_error_m: float | None = None
    median_pose_yaw_deg: float | None = None
    wrong_verified: int | None = None
    far_m: float = FAR_M

    def line(self) -> str:
        text = f"replay: {self.answered} of {self.queries} queries answered"
        if self.within is not None:
            text += f", {self.within} within {self.far_m:g} m"
        if self.verified is not None:
            text += f", {self.verified} verified"
        if self.median_error_m is not None:
            text += f"; median error {self.median_error_m:.1f} m, {self.beyond_m} beyond "
            text += f"{self.far_m:g} m"
        elif self.beyond_m is None:
            text += " (no poses in the bag: errors unknown)"
        if self.median_pose_error_m is not None:
            text += (
                f"; verified poses {self.median_pose_error_m:.2f} m / "
                f"{self.median_pose_yaw_deg or 0.0:.2f} deg off (median), "
                f"{self.wrong_verified} more than {WRONG_POSE_M:g} m off"
            )
        return text


def summarise(rows: Sequence[ReplayRow], far_m: float = FAR_M) -> ReplaySummary:
    """How many were answered, within ``far_m`` of the truth, verified; the median error of
    the top-1 places and of the verified poses, and the verified poses more than
    :data:`WRONG_POSE_M` off."""
    answered = [r for r in rows if r.answered]
    errors = [r.error_m for r in answered if r.error_m is not None]
    flags = [r.verified for r in answered if r.verified is not None]
    has_poses = any(r.true_northing is not None for r in rows)
    ver = [r for r in answered if r.verified and r.pose_error_m is not None]
    yaws = [r.pose_yaw_error_deg for r in ver if r.pose_yaw_error_deg is not None]
    return ReplaySummary(
        queries=len(rows),
        answered=len(answered),
        within=sum(e <= far_m for e in errors) if has_poses else None,
        median_error_m=float(np.median(errors)) if errors else None,
        beyond_m=sum(e > far_m for e in errors) if has_poses else None,
        verified=sum(bool(f) for f in flags) if flags else None,
        median_pose_error_m=float(np.median([r.pose_error_m for r in ver])) if ver else None,
        median_pose_yaw_deg=float(np.median(yaws)) if yaws else None,
        wrong_verified=sum(r.pose_error_m > WRONG_POSE_M for r in ver) if ver else None,
        far_m=far_m,
    )


def style_track_axes(ax: Any, title: str) -> None:
    """A drive's map panel (replay and follow figures): metres east and north, equal scales."""
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)


def save_track_figure(fig: Any, plt: Any, path: str | Path) -> Path:
    """Lay out, write as PNG (atomically) and close a replay or follow figure."""
    fig.tight_layout()
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, dpi=110, format="png")
    plt.close(fig)
    return path


def plot_replay(
    rows: Sequence[ReplayRow],
    path: str | Path,
    *,
    map_ne: np.ndarray | None = None,
    trajectory_ne: np.ndarray | None = None,
    title: str = "",
    far_m: float = FAR_M,
) -> Path:
    """The replay as a PNG: a map (easting right, northing up) and, with poses, the errors.

    ``map_ne``: float [M, 2] (northing, easting) of the map's submaps, in grey;
    ``trajectory_ne``: float [T, 2] of the drive's poses, a line. Answers are dots coloured by
    verification (green verified, red rejected, blue when the service does not verify), with a
    thin line to where the scan really was when that is known.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise MissingDependencyError("matplotlib", "plot", "The replay figure") from None
    has_errors = any(r.error_m is not None for r in rows)
    fig, axes = plt.subplots(
        1, 2 if has_errors else 1, figsize=(13 if has_errors else 7, 6), squeeze=False
    )
    ax = axes[0, 0]
    if map_ne is not None and len(map_ne):
        m = np.asarray(map_ne, dtype=np.float64)
        ax.scatter(m[:, 1], m[:, 0], s=6, c="0.75", label=f"map ({len(m)} submaps)", zorder=1)
    if trajectory_ne is not None and len(trajectory_ne):
        t = np.asarray(trajectory_ne, dtype=np.float64)
        ax.plot(t[:, 1], t[:, 0], "-", c="0.2", lw=1.0, label="drive (bag poses)", zorder=2)
    groups = [
        ("verified", "tab:green", lambda r: r.verified is True),
        ("not verified", "tab:red", lambda r: r.verified is False),
        ("answer", "tab:blue", lambda r: r.verified is None),
    ]
    answered = [r for r in rows if r.answered]
    for label, colour, pick in groups:
        sel = [r for r in answered if pick(r)]
        if not sel:
            continue
        for r in sel:
            if r.true_easting is not None:
                ax.plot(
                    [r.true_easting, r.easting],
                    [r.true_northing, r.northing],
                    "-",
                    c=colour,
                    lw=0.6,
                    alpha=0.6,
                    zorder=3,
                )
        e = [r.easting for r in sel]
        n = [r.northing for r in sel]
        ax.scatter(e, n, s=18, c=colour, label=f"{label} ({len(sel)})", zorder=4)
    style_track_axes(ax, title or "replay")
    if has_errors:
        ax2 = axes[0, 1]
        for label, colour, pick in groups:
            sel = [r for r in answered if pick(r) and r.error_m is not None]
            if sel:
                ax2.scatter([r.time_s for r in sel], [r.error_m for r in sel], s=14, c=colour,
                            label=label)  # fmt: skip
        ax2.axhline(far_m, c="0.4", ls="--", lw=0.8, label=f"{far_m:g} m")
        ax2.set_yscale("symlog", linthresh=1.0)
        ax2.set_ylim(bottom=0.0)  # errors are distances: no negative half of the axis
        ax2.set_xlabel("time in the bag (s)")
        ax2.set_ylabel("error of the top-1 submap (m)")
        s = summarise(rows, far_m)
        ax2.set_title(
            f"median {s.median_error_m:.1f} m, {s.beyond_m} of {s.answered} beyond {far_m:g} m"
            if s.median_error_m is not None
            else "errors"
        )
        ax2.legend(loc="best", fontsize=8)
    return save_track_figure(fig, plt, path)
