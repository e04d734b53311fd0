"""Accumulated queries on the synthetic city: the last stretch of a run before each query place,
laid together as a robot with poses would (``pnvlad eval --queries windows``).

A robot that has poses (a bag's pose topic, /tf) or estimates them (LiDAR odometry) can ask
with more than its newest scan: the scans of its last ``window_m`` of driving, accumulated by
:class:`~pnvlad_service.data.accumulate.WindowAccumulator` exactly as ``pnvlad data prepare``
accumulates a submap. A ``pnvlad synth`` tree keeps only the raw scans at its query places, so
the scans before them are cast again here from ``synth.json`` (the same city, route and seeds:
the very scans the submaps were made of).

Each window replaces the raw scan of a :class:`~pnvlad_service.evaluation.scan_queries.
ScanQuerySet` (same places, same ground truth): its points written as a KITTI ``.bin`` about the
newest scan, in the world's axes from the recorded poses (``frame="enu"``, what the map's
submaps have) or in the newest scan's axes (``frame="sensor"``, for odometry's own frame).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pnvlad_service.data.accumulate import WindowAccumulator
from pnvlad_service.data.scans import RawScan, write_scan
from pnvlad_service.errors import InputError
from pnvlad_service.synth.generate import (
    SynthPreset,
    preset_of_tree,
    run_name,
    simulated_drive,
)

log = logging.getLogger(__name__)

PoseSource = Literal["recorded", "odometry"]

#: Odometry windows are cast at this many scans to each of the tree's (2: every 1.25 m on the
#: benchmark preset, 8 a second at 10 m/s; at the tree's 2.5 m KISS-ICP lost the motion in
#: the city's straight streets).
ODOMETRY_SPACING_DIV = 2
#: Metres odometry runs before a window starts, so that it enters it at speed.
ODOMETRY_WARM_UP_M = 10.0


def drives_of(root: Path) -> dict[tuple[str, str], tuple[SynthPreset, int, int, int]]:
    """(area, run folder) -> (preset, area index, run index, seed) of a ``pnvlad synth`` tree,
    from its ``synth.json``. :class:`InputError` for a tree ``pnvlad synth`` did not make."""
    spec, seed = preset_of_tree(root, "windows are cast again from a pnvlad synth tree")
    return {
        (area.name, run_name(a, k, seed)[0]): (spec, a, k, seed)
        for a, area in enumerate(spec.areas)
        for k in range(spec.runs)
    }


def window_queries(
    qs: Any,
    root: str | Path,
    out_dir: str | Path,
    *,
    poses: PoseSource = "recorded",
    window_m: float = 20.0,
    frame: Literal["enu", "sensor"] | None = None,
    progress: bool = True,
) -> Any:
    """``qs`` (a :class:`~pnvlad_service.evaluation.scan_queries.ScanQuerySet` of a synth tree)
    with each query's raw scan replaced by the window of scans that ends with it (the scans of
    the last ``window_m`` of travel), written under ``out_dir``. ``poses``: ``recorded`` (the
    run's GNSS/INS poses, as a bag's pose topic) or ``odometry`` (KISS-ICP, extra
    ``odometry``, over scans twice as dense as the tree's, :data:`ODOMETRY_SPACING_DIV`, started
    :data:`ODOMETRY_WARM_UP_M` before the window: a robot's odometry runs all along, and from a
    standstill in a street canyon it may not find the motion at all); ``frame``: the window's axes
    (default ``enu`` with recorded poses, ``sensor`` with odometry, whose axes mean nothing on a
    map). The copy's ``window`` says how it was made and its ``drift_m`` lists, with odometry,
    each window's error (m) in where it lays its oldest scan, seen from its newest, against the
    truth."""
    from pnvlad_service.progress import tqdm

    if poses not in ("recorded", "odometry"):
        raise InputError(f"must be recorded or odometry, got {poses!r}", "poses")
    frame = frame or ("enu" if poses == "recorded" else "sensor")
    root, out_dir = Path(root), Path(out_dir)
    accumulation = map_accumulation(qs)
    drives = drives_of(root)
    total = sum(len(s) for s in qs.scans)
    bar = tqdm(total=total, desc=f"windows ({poses} poses)", unit="query", disable=not progress)
    scans_out: list[list[RawScan]] = []
    drift: list[float] = []
    for run, scans in zip(qs.runs, qs.scans, strict=True):
        key = (run.area, run.name)
        if key not in drives:
            raise InputError(f"run {run.name} of {run.area} is not in synth.json", root)
        spec, a, k, seed = drives[key]
        drive = simulated_drive(spec, a, k, seed)
        index = {int(t): i for i, t in enumerate(drive.timestamps)}
        if poses == "odometry":  # the same route, scans at every half step: index i -> 2 i
            dense = spec.model_copy(
                update={"scan_spacing": spec.scan_spacing / ODOMETRY_SPACING_DIV}
            )
            drive = simulated_drive(dense, a, k, seed)
            index = {t: ODOMETRY_SPACING_DIV * i for t, i in index.items()}
        out: list[RawScan] = []
        for s in scans:
            i = index.get(s.timestamp)
            if i is None:
                raise InputError(f"no scan of the drive at {s.timestamp}", run.name)
            first = window_start(drive.true_poses, i, window_m)
            warm = window_start(drive.true_poses, first, ODOMETRY_WARM_UP_M)
            if poses == "recorded":
                warm = first
            clouds = [drive.scan(j) for j in range(warm, i + 1)]
            laid = _laid_poses(drive, warm, i, clouds, poses)[first - warm :]
            acc = WindowAccumulator.laid_as(accumulation, window_m, frame)
            for pts, pose in zip(clouds[first - warm :], laid, strict=True):
                acc.add(pts, pose)
            path = out_dir / run.area / run.name / f"{s.timestamp}.bin"
            path.parent.mkdir(parents=True, exist_ok=True)
            write_scan(path, acc.cloud())
            if poses == "odometry":
                est = np.linalg.inv(laid[-1]) @ laid[0]
                true = drive.true_poses
                ref = np.linalg.inv(true[i]) @ true[first]
                drift.append(float(math.dist(est[:3, 3], ref[:3, 3])))
            out.append(replace(s, path=path))
            bar.update()
        scans_out.append(out)
    bar.close()
    window = {"poses": poses, "frame": frame, "window_m": window_m, **accumulation}
    return replace(qs, scans=scans_out, g_frames={}, window=window, drift_m=drift)


def map_accumulation(qs: Any) -> dict[str, Any]:
    """How the map's windows laid each scan (its first database run's prepare record; empty
    where none is recorded): an accumulated query lays its scans the same way."""
    from pnvlad_service.data.run_folder import recorded_accumulation

    first = Path(qs.runs[0].db_paths[0])
    return recorded_accumulation(first.parents[1], first.parent.name) or {}


def _laid_poses(
    drive: Any, first: int, last: int, clouds: list[np.ndarray], poses: PoseSource
) -> list[np.ndarray]:
    """The poses the window's scans are laid with: recorded, or from odometry over them."""
    if poses == "recorded":
        return [drive.poses[j] for j in range(first, last + 1)]
    from pnvlad_service.data.sources.odometry import LidarOdometry

    odometry = LidarOdometry(max_range=drive.lidar.max_range)
    return [odometry.update(pts) for pts in clouds]


def window_start(poses: np.ndarray, i: int, window_m: float) -> int:
    """The first scan no more than ``window_m`` of travel before scan ``i`` (by ``poses``)."""
    xy = poses[: i + 1, :2, 3]
    travelled = np.r_[0.0, np.cumsum(np.hypot(*np.diff(xy, axis=0).T))]
    return int(np.flatnonzero(travelled[-1] - travelled <= window_m)[0])
