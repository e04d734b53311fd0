"""A folder of scans plus a CSV of poses as a drive: :class:`CsvDrive`. The CSV holds planar
poses (northing, easting, a yaw or compass heading, optional height, roll and pitch) or full
sensor-to-world matrices; scans are read by any reader :mod:`pnvlad_service.io.readers` knows."""

from __future__ import annotations

import csv
import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pnvlad_service.data.drive import snap_m
from pnvlad_service.data.sources.returns import NoReturnCount
from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_scan

log = logging.getLogger(__name__)


def _rpy_matrices(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """float64 [T, 3, 3] rotations R = Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in radians [T]."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    r = np.empty((len(yaw), 3, 3))
    r[:, 0, 0] = cy * cp
    r[:, 0, 1] = cy * sp * sr - sy * cr
    r[:, 0, 2] = cy * sp * cr + sy * sr
    r[:, 1, 0] = sy * cp
    r[:, 1, 1] = sy * sp * sr + cy * cr
    r[:, 1, 2] = sy * sp * cr - cy * sr
    r[:, 2, 0] = -sp
    r[:, 2, 1] = cp * sr
    r[:, 2, 2] = cp * cr
    return r


_INT_STEM = re.compile(r"^-?\d+$")
_MATRIX12 = [f"r{r}{c}" for r in range(3) for c in range(4)]
_MATRIX16 = [f"r{r}{c}" for r in range(4) for c in range(4)]


def _angle_column(
    columns: dict[str, np.ndarray], names: Sequence[str], path: Path, required: bool
) -> tuple[str | None, np.ndarray | None]:
    """The one angle column among ``names`` (``*_deg`` / ``*_rad``), converted to radians."""
    present = [n for n in names if n in columns]
    if len(present) > 1:
        raise InputError(f"give only one of the columns {', '.join(present)}", path)
    if not present:
        if required:
            raise InputError(f"missing a heading column: one of {', '.join(names)}", path)
        return None, None
    name = present[0]
    values = columns[name]
    return name, np.radians(values) if name.endswith("_deg") else values


def _read_pose_table(path: Path) -> tuple[list[str], np.ndarray, dict[str, np.ndarray]]:
    """The pose CSV's numbers, in file order: (header, timestamps int64 [T], the other columns
    by name as float64 [T], every value finite)."""
    with open(path, encoding="utf-8", newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputError("empty file (expected a header row)", path) from None
        rows = [r for r in reader if any(c.strip() for c in r)]
    if "timestamp" not in header:
        raise InputError(f"no 'timestamp' column (header: {','.join(header)})", path)
    if len(set(header)) != len(header):
        raise InputError("duplicate column names in the header", path)
    if not rows:
        raise InputError("no pose rows", path)
    stamps_list: list[int] = []
    numeric: dict[str, list[float]] = {h: [] for h in header if h != "timestamp"}
    for lineno, row in enumerate(rows, start=2):
        if len(row) != len(header):
            raise InputError(f"row {lineno}: {len(row)} fields for {len(header)} columns", path)
        for h, cell in zip(header, row, strict=True):
            cell = cell.strip()
            try:
                if h == "timestamp":
                    stamps_list.append(int(cell))
                else:
                    v = float(cell)
                    if not math.isfinite(v):
                        raise ValueError
                    numeric[h].append(v)
            except ValueError:
                kind = "an integer (microseconds)" if h == "timestamp" else "a finite number"
                raise InputError(
                    f"row {lineno}, column {h}: {cell!r} is not {kind}", path
                ) from None
    stamps = np.asarray(stamps_list, dtype=np.int64)
    return header, stamps, {h: np.asarray(v, dtype=np.float64) for h, v in numeric.items()}


def _matrix_poses(cols: dict[str, np.ndarray], t_count: int, path: Path) -> np.ndarray:
    """float64 [T, 4, 4] from the columns ``r00 .. r23`` (optionally ``r30 .. r33``)."""
    poses = np.tile(np.eye(4), (t_count, 1, 1))
    m = np.stack([cols[c] for c in _MATRIX12], axis=1).reshape(t_count, 3, 4)
    poses[:, :3, :4] = m
    if all(c in cols for c in _MATRIX16):
        bottom = np.stack([cols[f"r3{c}"] for c in range(4)], axis=1)
        if not np.allclose(bottom, [0.0, 0.0, 0.0, 1.0]):
            raise InputError("r30..r33 must be 0, 0, 0, 1 (a rigid transform)", path)
    det = np.linalg.det(poses[:, :3, :3])
    bad = np.nonzero(np.abs(det - 1.0) > 1e-3)[0]
    if len(bad):
        raise InputError(
            f"row {int(bad[0]) + 2}: r00..r22 is not a rotation (determinant {det[bad[0]]:.4f})",
            path,
        )
    return poses


def _planar_poses(cols: dict[str, np.ndarray], t_count: int, path: Path) -> np.ndarray:
    """float64 [T, 4, 4] from ``northing``, ``easting``, a yaw or heading, optional ``height``,
    roll and pitch (rotation Rz(yaw) Ry(pitch) Rx(roll))."""
    _, yaw = _angle_column(cols, ("yaw_deg", "yaw_rad"), path, required=False)
    hname, heading = _angle_column(cols, ("heading_deg", "heading_rad"), path, required=yaw is None)
    if yaw is not None and hname is not None:
        raise InputError("give either a yaw_* or a heading_* column, not both", path)
    if yaw is None:
        assert heading is not None
        yaw = np.pi / 2 - heading
    zeros = np.zeros(t_count)
    _, roll = _angle_column(cols, ("roll_deg", "roll_rad"), path, required=False)
    _, pitch = _angle_column(cols, ("pitch_deg", "pitch_rad"), path, required=False)
    poses = np.tile(np.eye(4), (t_count, 1, 1))
    poses[:, :3, :3] = _rpy_matrices(
        zeros if roll is None else roll, zeros if pitch is None else pitch, yaw
    )
    poses[:, 0, 3] = cols["easting"]
    poses[:, 1, 3] = cols["northing"]
    poses[:, 2, 3] = cols.get("height", zeros)
    return poses


def _read_pose_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A pose CSV (see :class:`CsvDrive`): (timestamps int64 [T] µs, poses float64 [T, 4, 4]
    sensor-to-world, translations snapped), sorted by time; ``InputError`` naming the file."""
    path = Path(path)
    header, stamps, cols = _read_pose_table(path)
    if all(c in cols for c in _MATRIX12):
        poses = _matrix_poses(cols, len(stamps), path)
    elif "northing" in cols and "easting" in cols:
        poses = _planar_poses(cols, len(stamps), path)
    else:
        raise InputError(
            "need columns northing,easting and a heading (yaw_deg, yaw_rad, heading_deg or "
            "heading_rad), or a full pose r00..r23; header: " + ",".join(header),
            path,
        )
    poses[:, :3, 3] = snap_m(poses[:, :3, 3])
    order = np.argsort(stamps, kind="stable")
    stamps, poses = stamps[order], poses[order]
    dup = np.nonzero(np.diff(stamps) == 0)[0]
    if len(dup):
        raise InputError(f"timestamp {int(stamps[dup[0]])} appears more than once", path)
    return stamps, poses


def _scan_files(scans_dir: Path) -> dict[int, Path]:
    """Timestamp -> file of every ``<timestamp>.<ext>`` in ``scans_dir`` (hidden files skipped,
    other names ignored with a warning); two files for one timestamp raise ``InputError``."""
    files: dict[int, Path] = {}
    ignored = 0
    for f in sorted(scans_dir.iterdir()):
        if f.name.startswith(".") or not f.is_file():
            continue
        if not _INT_STEM.match(f.stem):
            ignored += 1
            continue
        ts = int(f.stem)
        if ts in files:
            raise InputError(f"two scan files for timestamp {ts}: {files[ts].name}, {f.name}", f)
        files[ts] = f
    if ignored:
        log.warning("%s: ignored %d file(s) not named <timestamp>.<ext>", scans_dir, ignored)
    return files


class CsvDrive:
    """A folder of scans plus a CSV of poses, as a :class:`~pnvlad_service.data.drive.Drive`.

    The CSV (comma-separated, header row) has a ``timestamp`` column (integer microseconds) and
    either a planar pose or a full matrix:

    - planar: ``northing``, ``easting`` (UTM metres) and the heading as exactly one of
      ``yaw_deg`` / ``yaw_rad`` (the sensor's x axis, counter-clockwise from east: 0 = east,
      90 deg = north) or ``heading_deg`` / ``heading_rad`` (compass: clockwise from north,
      0 = north, 90 deg = east); optional ``height`` (metres, default 0) and ``roll_deg`` /
      ``roll_rad``, ``pitch_deg`` / ``pitch_rad`` (default 0). Rotation = Rz(yaw) Ry(pitch)
      Rx(roll).
    - full: ``r00 .. r23`` (12 columns: the top 3x4 of the sensor-to-world matrix, row ``r``,
      column ``c``; ``r03`` = easting, ``r13`` = northing, ``r23`` = height) or ``r00 .. r33``.

    Scan ``i`` is the file ``<timestamp>.<ext>`` in ``scans_dir`` (any suffix ``read_points``
    knows; ``reader`` forces one, see :mod:`pnvlad_service.io.readers`). A row without a file or a
    file without a row raises :class:`InputError`, unless ``skip_missing`` (then both are
    dropped with a warning). Rows are sorted by timestamp.
    """

    def __init__(
        self,
        scans_dir: str | Path,
        poses_csv: str | Path,
        *,
        reader: str | None = None,
        skip_missing: bool = False,
        name: str | None = None,
    ) -> None:
        self.dir = Path(scans_dir)
        self.reader = reader
        path = Path(poses_csv)
        if not self.dir.is_dir():
            raise InputError("scan folder not found", self.dir)
        if not path.is_file():
            raise InputError("pose CSV not found", path)
        self.name = name or self.dir.name
        stamps, poses = _read_pose_csv(path)
        files = _scan_files(self.dir)
        keep = self._match(stamps, files, path, skip_missing)
        if keep is not None:
            stamps, poses = stamps[keep], poses[keep]
        self.timestamps = stamps
        self.poses = poses
        self.files = [files[int(t)] for t in stamps]
        self.no_returns = NoReturnCount()

    @staticmethod
    def _match(
        stamps: np.ndarray, files: dict[int, Path], path: Path, skip_missing: bool
    ) -> np.ndarray | None:
        """Pair CSV rows with scan files: ``None`` when they match one to one, else (with
        ``skip_missing``) bool [T], the rows that have a file; ``InputError`` otherwise."""
        row_set = set(stamps.tolist())
        no_file = [int(t) for t in stamps if int(t) not in files]
        no_row = sorted(t for t in files if t not in row_set)
        if not (no_file or no_row):
            return None
        parts = []
        if no_file:
            shown = ", ".join(str(t) for t in no_file[:5])
            parts.append(f"{len(no_file)} row(s) without a scan file (timestamps {shown})")
        if no_row:
            shown = ", ".join(files[t].name for t in no_row[:5])
            parts.append(f"{len(no_row)} scan file(s) without a CSV row ({shown})")
        message = "; ".join(parts)
        if not skip_missing:
            src = path if no_file else files[no_row[0]]
            raise InputError(f"{message} (pass --skip-missing to drop them)", src)
        log.warning("%s: %s; dropped", path, message)
        keep = np.array([int(t) in files for t in stamps], dtype=bool)
        if not keep.any():
            raise InputError("no CSV row has a scan file", path)
        return keep

    def __len__(self) -> int:
        return len(self.files)

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i`` through :func:`pnvlad_service.io.readers.read_scan`: [N, 3] metres,
        missing returns written as points at the origin dropped (counted in ``no_returns``)."""
        points, dropped = read_scan(self.files[i], self.reader)
        self.no_returns.add(dropped, self.files[i])
        return points
