"""Raw single scans as queries: the ``raw_scans`` layout of a run folder.

A robot localises the scan its sensor just made, not a 20 m submap. ``pnvlad synth`` and
``pnvlad data prepare --scans`` keep, beside the benchmark's submaps, the raw scan at each
test submap's place (the scan whose timestamp names the submap), so that single scans can be
evaluated as queries at the same places and against the same ground truth::

    <run>/raw_scans/<timestamp>.bin   one scan as the sensor made it: float32 x, y, z,
                                      intensity (KITTI's .bin), sensor frame, metres
    <run>/raw_scans.csv               timestamp,northing,easting,height,yaw_deg,pitch_deg,
                                      roll_deg: the scan's recorded (GNSS/INS) pose, sensor to
                                      UTM; then true_northing ... true_roll_deg where the
                                      drive knows its true poses (the simulator)

The benchmark's own tools ignore both (they read only the layouts' folders and CSVs). Angles
are intrinsic z-y'-x'' (yaw about up, then pitch, then roll), degrees; yaw 0 faces east,
counter-clockwise positive (the ENU frame of docs/ARCHITECTURE.md).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_open, atomic_write_text, read_csv_text

RAW_FOLDER = "raw_scans"
RAW_CSV = "raw_scans.csv"

_POSE = ("northing", "easting", "height", "yaw_deg", "pitch_deg", "roll_deg")
COLUMNS = ("timestamp", *_POSE)
TRUE_COLUMNS = tuple(f"true_{c}" for c in _POSE)


def pose_values(pose: np.ndarray) -> list[float]:
    """northing, easting, height (m) and yaw, pitch, roll (degrees) of a sensor-to-world
    pose float64 [4, 4] (x = easting, y = northing, z = up)."""
    from scipy.spatial.transform import Rotation

    pose = np.asarray(pose, dtype=np.float64)
    yaw, pitch, roll = Rotation.from_matrix(pose[:3, :3]).as_euler("ZYX", degrees=True)
    return [float(v) for v in (pose[1, 3], pose[0, 3], pose[2, 3], yaw, pitch, roll)]


def pose_matrix(values: Sequence[float]) -> np.ndarray:
    """The float64 [4, 4] pose of :func:`pose_values`' six numbers."""
    from scipy.spatial.transform import Rotation

    north, east, height, yaw, pitch, roll = (float(v) for v in values)
    out = np.eye(4)
    out[:3, :3] = Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()
    out[:3, 3] = (east, north, height)
    return out


@dataclass(frozen=True)
class RawScan:
    """One raw scan of a run: its file, timestamp (µs), recorded pose and, from the simulator,
    its true pose (float64 [4, 4] sensor to UTM world; ``None`` where unknown)."""

    path: Path
    timestamp: int
    pose: np.ndarray
    true_pose: np.ndarray | None = None

    @property
    def northing(self) -> float:
        return float(self.pose[1, 3])

    @property
    def easting(self) -> float:
        return float(self.pose[0, 3])


def write_scan(path: str | Path, points: np.ndarray) -> None:
    """One scan as KITTI's ``.bin`` (float32 x, y, z, intensity; intensity 0 when ``points``
    has only x, y, z), atomically. ``InputError`` for anything but finite [N, 3+] points."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3 or len(pts) == 0:
        raise InputError(f"expected points [N, 3] or [N, 4], got {pts.shape}", path)
    out = np.zeros((len(pts), 4), dtype="<f4")
    with np.errstate(over="ignore", invalid="ignore"):  # too large for float32: refused below
        out[:, : min(4, pts.shape[1])] = pts[:, :4]
    if not np.isfinite(out).all():
        raise InputError("a scan to write holds NaN or infinite values", path)
    with atomic_open(path, "wb") as fh:
        fh.write(out.tobytes())


def write_raw_scans_csv(
    path: str | Path, rows: Sequence[tuple[int, np.ndarray, np.ndarray | None]]
) -> None:
    """``raw_scans.csv`` from ``(timestamp µs, recorded pose [4, 4], true pose or None)``
    rows, atomically; the true columns are written when every row has a true pose."""
    with_truth = bool(rows) and all(t is not None for _, _, t in rows)
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow([*COLUMNS, *(TRUE_COLUMNS if with_truth else ())])
    for stamp, pose, true in rows:
        values = pose_values(pose) + (pose_values(true) if with_truth else [])  # type: ignore[arg-type]
        out.writerow([int(stamp), *(repr(v) for v in values)])
    atomic_write_text(path, buf.getvalue())


def has_raw_scans(run_dir: str | Path) -> bool:
    """Whether a run folder lists raw scans (``raw_scans.csv``)."""
    return (Path(run_dir) / RAW_CSV).is_file()


def read_raw_scans(run_dir: str | Path) -> list[RawScan]:
    """The raw scans a run folder lists, in CSV order. ``InputError`` naming the file and line
    for a missing column, a value that is not a finite number, a listed scan without its file."""
    run_dir = Path(run_dir)
    path = run_dir / RAW_CSV
    lines = read_csv_text(path, "raw scans CSV", "utf-8-sig").splitlines()
    reader = csv.reader(lines)
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}; expected {COLUMNS}", path)
    col = {c: header.index(c) for c in header}
    truth = all(c in col for c in TRUE_COLUMNS)
    out = []
    for lineno, rec in enumerate(reader, start=2):
        if not rec or all(not f.strip() for f in rec):
            continue
        try:
            stamp = int(rec[col["timestamp"]])
            values = [float(rec[col[c]]) for c in _POSE]
            true = [float(rec[col[c]]) for c in TRUE_COLUMNS] if truth else None
        except (ValueError, IndexError):
            raise InputError(f"line {lineno}: a missing or non-numeric value", path) from None
        if not all(math.isfinite(v) for v in values + (true or [])):
            raise InputError(f"line {lineno}: a value is not finite", path)
        scan = run_dir / RAW_FOLDER / f"{stamp}.bin"
        if not scan.is_file():
            raise InputError(f"line {lineno}: no scan file {RAW_FOLDER}/{scan.name}", path)
        out.append(
            RawScan(scan, stamp, pose_matrix(values), None if true is None else pose_matrix(true))
        )
    return out
