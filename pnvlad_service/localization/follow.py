"""A drive followed by the :class:`~.tracking.DriveLocalizer`, scan by scan, into rows
(``pnvlad localize --rosbag``, which follows by default); their CSV, the summary and a PNG are
made in :mod:`.follow_report`, whose names are also imported from here.

:func:`follow_drive` feeds the scans of a drive (any object with ``timestamps`` and
``scan(i)``; ``poses`` when it has a pose stream) to the localiser with the odometry the caller
chose (the drive's poses, KISS-ICP on the scans, or none) and returns one :class:`FollowRow` a
scan: the state, the pose, how sure it is, and, with the drive's true poses, its errors. With
the map's positions each row also says how far the truth is from the nearest map entry (off
the map or not); with the map's own truth (:func:`map_truth`: a ``pnvlad synth`` tree records
each entry's true pose) it says how far the pose is from where the map itself would put the
scan, which is all a localiser can reach on a map built from GNSS/INS poses.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.follow_report import (
    COLUMNS,
    GOOD_DEG,
    GOOD_M,
    JUMP_M,
    OFF_MAP_M,
    WRONG_POSE_M,
    FollowRow,
    FollowSummary,
    plot_follow,
    read_follow_csv,
    stage_means,
    summarise_follow,
    write_follow_csv,
)
from pnvlad_service.localization.tracking import (
    Ask,
    DriveLocalizer,
    DriveScan,
    TrackerConfig,
    wrap_deg,
    yaw_of,
)

__all__ = [
    "COLUMNS",
    "GOOD_DEG",
    "GOOD_M",
    "JUMP_M",
    "OFF_MAP_M",
    "WRONG_POSE_M",
    "FollowRow",
    "FollowSummary",
    "Odometry",
    "follow_drive",
    "map_truth",
    "plot_follow",
    "read_follow_csv",
    "stage_means",
    "summarise_follow",
    "write_follow_csv",
]

Odometry = Literal["poses", "kiss-icp", "none"]


def map_truth(bundle: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """``submap_id`` -> (its pose on the map, its true pose), both float64 [4, 4] local frame ->
    UTM, for every entry of the bundle at ``bundle`` whose tree (the manifest's ``indexed``
    roots) is here and records true poses (``pnvlad synth`` trees); ``None`` when none does."""
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.bundle import METADATA_FILE, Metadata
    from pnvlad_service.index.manifest import Manifest

    bundle = Path(bundle)
    manifest = Manifest.read(bundle)
    meta = Metadata.load(bundle / METADATA_FILE)
    frames: dict[str, Any] = {}
    for entry in manifest.indexed:
        root = Path(str(entry.get("root", "")))
        if not root.is_dir():
            continue
        try:
            frames.update(BenchmarkTree(root).frames_by_path())
        except InputError:
            continue
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    roots = [Path(str(e.get("root", ""))) for e in manifest.indexed]
    for sid, rel in zip(meta.submap_id, meta.path, strict=True):
        for root in roots:
            f = frames.get(str((root / str(rel)).resolve()))
            if f is not None and f.true_pose is not None:
                out[str(sid)] = (f.map_pose, f.true_pose)
                break
    return out or None


def follow_drive(
    drive: Any,
    ask: Ask,
    *,
    every: int = 1,
    odometry: Odometry = "poses",
    truth: np.ndarray | None = None,
    config: TrackerConfig | None = None,
    positions: Any = None,
    truth_of_map: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    initial_pose: np.ndarray | None = None,
    progress: bool = True,
) -> list[FollowRow]:
    """Follow scans 0, ``every``, 2 * ``every``, ... of ``drive`` with a
    :class:`~.tracking.DriveLocalizer` asking ``ask``: one :class:`FollowRow` a scan.

    ``odometry``: ``poses`` (the drive's ``poses``, a pose topic or /tf), ``kiss-icp``
    (:class:`~pnvlad_service.data.sources.odometry.LidarOdometry` on the scans, extra
    ``odometry``) or ``none`` (constant velocity); ``truth``: float64 [T, 4, 4] sensor -> UTM
    of every scan of ``drive`` (errors); ``positions``: the map's
    :class:`~.prior.MapPositions` (``off_map_m``); ``truth_of_map``: :func:`map_truth`
    (``map_error_m``)."""
    from pnvlad_service.progress import tqdm

    if every < 1:
        raise InputError(f"must be >= 1, got {every}", "every")
    stamps = np.asarray(drive.timestamps, dtype=np.int64)
    if len(stamps) == 0:
        raise InputError("no scans to follow", getattr(drive, "name", "drive"))
    poses = getattr(drive, "poses", None)
    if odometry == "poses" and poses is None:
        raise InputError("the drive has no poses to use as odometry", "odometry")
    lidar = None
    if odometry == "kiss-icp":
        from pnvlad_service.data.sources.odometry import LidarOdometry

        lidar = LidarOdometry()
    if truth is not None and len(truth) != len(stamps):
        raise InputError(f"{len(truth)} true poses for {len(stamps)} scans", "truth")
    loc = DriveLocalizer(ask, config, initial_pose=initial_pose)
    driven = None if truth is None else _driven(truth[:, :3, 3])
    rows: list[FollowRow] = []
    bar = tqdm(range(0, len(stamps), every), desc="follow", unit="scan",
               disable=None if progress else True)  # fmt: skip
    for i in bar:
        t0 = time.perf_counter()
        points = drive.scan(i)
        t1 = time.perf_counter()
        odo = None
        if odometry == "poses":
            odo = poses[i]
        elif lidar is not None:
            try:
                odo = lidar.update(points)
            except InputError:
                odo = None
        t2 = time.perf_counter()
        step = loc.step(DriveScan(i, int(stamps[i]), points, odo))
        row = FollowRow(
            scan=i,
            timestamp=int(stamps[i]),
            time_s=float(stamps[i] - stamps[0]) / 1e6,
            state=step.state,
            verified=step.verified,
            how=step.how,
            event=step.event,
            fitness=step.fitness,
            sigma_m=step.sigma_m,
            confidence=step.confidence,
            anchor=step.anchor,
            read_ms=(t1 - t0) * 1e3,
            odometry_ms=(t2 - t1) * 1e3,
            step_ms=step.seconds * 1e3,
            reason=step.reason,
        )
        if step.answer is not None:
            row.correction_m = (step.answer.get("prior") or {}).get("correction_m")
            row.asked = step.answer.get("mode", "search")
            row.stages_ms = dict(step.answer.get("timings_ms") or {})
            row.server_ms = row.stages_ms.get("total")
        if step.pose is not None:
            row.pose_northing = float(step.pose[1, 3])
            row.pose_easting = float(step.pose[0, 3])
            row.pose_yaw_deg = yaw_of(step.pose)
        if truth is not None and np.isfinite(truth[i]).all():  # NaN: no truth for this scan
            _errors(row, step.pose, truth[i], truth_of_map)
            row.driven_m = float(driven[i]) if driven is not None else None
            if positions is not None:
                row.off_map_m = positions.nearest_m(row.true_northing, row.true_easting)
        rows.append(row)
        if row.pose_error_m is not None and row.verified:
            bar.set_postfix(state=row.state, error=f"{row.pose_error_m:.2f} m", refresh=False)
        else:
            bar.set_postfix(state=row.state, refresh=False)
    bar.close()
    return rows


def _driven(xyz: np.ndarray) -> np.ndarray:
    """Metres driven to each pose (a step to or from a pose without truth counts 0)."""
    steps = np.linalg.norm(np.diff(xyz[:, :2], axis=0), axis=1)
    return np.r_[0.0, np.cumsum(np.nan_to_num(steps, nan=0.0))]


def _errors(
    row: FollowRow,
    pose: np.ndarray | None,
    true: np.ndarray,
    truth_of_map: dict[str, tuple[np.ndarray, np.ndarray]] | None,
) -> None:
    row.true_northing = float(true[1, 3])
    row.true_easting = float(true[0, 3])
    row.true_yaw_deg = yaw_of(true)
    if pose is None:
        return
    row.pose_error_m = float(np.hypot(*(pose[:2, 3] - true[:2, 3])))
    row.pose_yaw_error_deg = abs(wrap_deg(yaw_of(pose) - row.true_yaw_deg))
    known = None if truth_of_map is None or row.anchor is None else truth_of_map.get(row.anchor)
    if known is not None:
        on_map, true_anchor = known
        there = on_map @ np.linalg.inv(true_anchor) @ true  # where the map itself puts the scan
        row.map_error_m = float(np.hypot(*(pose[:2, 3] - there[:2, 3])))
        row.map_yaw_error_deg = abs(wrap_deg(yaw_of(pose) - yaw_of(there)))
