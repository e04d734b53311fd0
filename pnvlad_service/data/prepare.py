"""A recorded drive -> one benchmark run: submaps cut along the trajectory, filtered by G.

A *drive* is a sequence of LiDAR scans with their poses (the :class:`Drive` protocol). This
module accumulates the scans of a stretch of trajectory in the world frame, cuts a submap every
``stride`` metres of travelled distance, runs the filter G
(:mod:`pnvlad_service.data.preprocess`) on each and writes the benchmark's files (see
docs/PREPARE.md and BENCHMARK_FORMAT.md)::

    <out_run_dir>/pointcloud_20m_10overlap/<timestamp>.bin   training layout, every 10 m
    <out_run_dir>/pointcloud_locations_20m_10overlap.csv
    <out_run_dir>/pointcloud_20m/<timestamp>.bin             test layout, every 20 m
    <out_run_dir>/pointcloud_locations_20m.csv

Conventions (docs/ARCHITECTURE.md): world frame x = easting, y = northing, z = up, UTM metres;
timestamps are integer microseconds. Translations are snapped to a 2**-26 m (15 nm) grid so
that adding a UTM origin and subtracting the submap centre are exact in float64: the same drive
placed at northing 0 or 5.7e6 gives byte-identical submaps.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text

if TYPE_CHECKING:
    from pnvlad_service.data.preprocess import GConfig

log = logging.getLogger(__name__)

Layout = Literal["oxford", "inhouse"]
Kind = Literal["train", "test"]

#: Points in a benchmark submap and its size on disk (float64 x 3, no header).
SUBMAP_POINTS = 4096
SUBMAP_BYTES = SUBMAP_POINTS * 3 * 8

#: Grid (metres) that translations are snapped to: 2**-26 m, about 15 nanometres. Any UTM
#: coordinate (< 2**24 m) on this grid has at most 50 significant bits, so sums and differences
#: of such coordinates are exact in float64.
SNAP_M = 2.0**-26

#: KITTI's nominal rotation from the Velodyne frame (x forward, y left, z up) to the camera
#: frame (x right, y down, z forward): camera = R @ velodyne. Used when calib.txt is absent.
KITTI_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: Scan rate assumed for a KITTI sequence without times.txt (Hz).
KITTI_DEFAULT_RATE_HZ = 10.0


@dataclass(frozen=True)
class Geometry:
    """Default geometry of one benchmark layout for one kind of submap.

    ``stride_m``: distance travelled between submaps; ``window_m``: stretch of trajectory
    accumulated; ``box_m``: side of the square crop around the submap (``None``: no crop).
    Folder and CSV names come from :data:`pnvlad_service.data.tree.LAYOUTS`.
    """

    stride_m: float
    window_m: float
    box_m: float | None


#: (layout, kind) -> default geometry, as BENCHMARK_FORMAT.md describes the two layouts.
GEOMETRY: dict[tuple[str, str], Geometry] = {
    ("oxford", "train"): Geometry(stride_m=10.0, window_m=20.0, box_m=None),
    ("oxford", "test"): Geometry(stride_m=20.0, window_m=20.0, box_m=None),
    ("inhouse", "train"): Geometry(stride_m=10.0, window_m=25.0, box_m=25.0),
    ("inhouse", "test"): Geometry(stride_m=25.0, window_m=25.0, box_m=25.0),
}


# --------------------------------------------------------------------------------------------
# Drives


@runtime_checkable
class Drive(Protocol):
    """A recorded (or simulated) drive: LiDAR scans with their poses, in time order.

    - ``name``: a short name for messages (e.g. the sequence folder).
    - ``timestamps``: int64 [T], microseconds, strictly increasing (they name the submap files).
    - ``poses``: float64 [T, 4, 4], sensor-to-world transforms; world x = easting,
      y = northing, z = up, UTM metres.
    - ``len(drive)``: T.
    - ``scan(i)``: the points of scan ``i``, [N, 3] float32 or float64, sensor frame, metres.
    """

    name: str
    timestamps: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int: ...

    def scan(self, i: int) -> np.ndarray: ...


def snap_m(values: np.ndarray | float) -> np.ndarray:
    """Round metres (float64, any shape) to the :data:`SNAP_M` grid (exact for |x| < 2**26 m)."""
    return np.round(np.asarray(values, dtype=np.float64) / SNAP_M) * SNAP_M


def yaw_matrix(yaw_rad: float) -> np.ndarray:
    """float64 [3, 3] rotation about z (up) by ``yaw_rad``, counter-clockwise seen from above."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


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


def _read_matrix_rows(path: Path, width: int, what: str) -> np.ndarray:
    """float64 [rows, width] from a whitespace-separated text file; InputError on bad lines."""
    rows: list[list[float]] = []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            parts = line.split()
            if len(parts) != width:
                raise InputError(
                    f"line {lineno}: expected {width} numbers ({what}), found {len(parts)}", path
                )
            try:
                values = [float(p) for p in parts]
            except ValueError:
                raise InputError(f"line {lineno}: not a number in {line.strip()!r}", path) from None
            if not all(math.isfinite(v) for v in values):
                raise InputError(f"line {lineno}: NaN or infinite value", path)
            rows.append(values)
    if not rows:
        raise InputError(f"no {what} found", path)
    return np.asarray(rows, dtype=np.float64)


def read_kitti_calib(path: str | Path) -> np.ndarray:
    """The Velodyne-to-camera-0 transform ``Tr`` of a KITTI ``calib.txt``: float64 [4, 4].

    Reads the line ``Tr: r00 r01 r02 t0 r10 ... t2`` (odometry) or ``Tr_velo_to_cam:`` (raw).
    """
    path = Path(path)
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            key, _, rest = line.partition(":")
            if key.strip() in ("Tr", "Tr_velo_to_cam"):
                try:
                    values = [float(v) for v in rest.split()]
                except ValueError:
                    raise InputError(f"bad number in line {line.strip()!r}", path) from None
                if len(values) != 12 or not all(math.isfinite(v) for v in values):
                    raise InputError("the Tr line must hold 12 finite numbers", path)
                tr = np.eye(4)
                tr[:3, :4] = np.asarray(values).reshape(3, 4)
                return tr
    raise InputError("no 'Tr:' line (Velodyne-to-camera transform) found", path)


def kitti_poses_to_world(
    cam_poses: np.ndarray,
    velo_to_cam: np.ndarray | None = None,
    *,
    origin_ne: tuple[float, float] = (0.0, 0.0),
    yaw_deg: float = 0.0,
) -> np.ndarray:
    """Convert KITTI camera-0 poses to Velodyne-to-world poses with z up, in UTM metres.

    ``cam_poses``: float64 [T, 3, 4] or [T, 4, 4], camera ``i`` to camera-0-of-frame-0, KITTI
    camera frame (x right, y down, z forward). ``velo_to_cam``: float64 [4, 4] (``Tr`` of
    calib.txt); ``None`` uses :data:`KITTI_VELO_TO_CAM` with no offset. The local world frame is
    the Velodyne frame of the first scan (x forward, y left, z up), rotated by ``yaw_deg``
    (counter-clockwise from east: 0 = the car starts facing east, 90 = north) and shifted so that
    the first scan sits at ``origin_ne`` = (northing, easting) UTM metres, height 0.

    Returns float64 [T, 4, 4], sensor (Velodyne) to world, x = easting, y = northing, z = up.
    Translations are snapped to :data:`SNAP_M` before the origin is added, so the result minus
    the origin does not depend on the origin's magnitude.
    """
    cam = np.asarray(cam_poses, dtype=np.float64)
    if cam.ndim != 3 or cam.shape[1:] not in ((3, 4), (4, 4)):
        raise InputError(f"camera poses must be [T, 3, 4], got {cam.shape}", "poses")
    t_count = cam.shape[0]
    p = np.tile(np.eye(4), (t_count, 1, 1))
    p[:, :3, :4] = cam[:, :3, :4]
    if velo_to_cam is None:
        tr = np.eye(4)
        tr[:3, :3] = KITTI_VELO_TO_CAM
    else:
        tr = np.asarray(velo_to_cam, dtype=np.float64)
    tr_inv = np.linalg.inv(tr)
    local = tr_inv @ p @ tr  # Velodyne i -> Velodyne frame of scan 0
    place = np.eye(4)
    place[:3, :3] = yaw_matrix(math.radians(yaw_deg))
    world = place @ local
    origin = snap_m(np.array([origin_ne[1], origin_ne[0], 0.0]))
    world[:, :3, 3] = snap_m(world[:, :3, 3]) + origin
    return world


class KittiSequence:
    """A KITTI-odometry style sequence folder as a :class:`Drive`.

    ``seq_dir/velodyne/*.bin`` (float32 x, y, z, reflectance per point, sorted by name),
    ``poses.txt`` (or ``poses``: 12 numbers a line, the camera-0 pose 3x4 row-major, one line a
    scan), optional ``times.txt`` (seconds, one line a scan; without it scans are assumed
    :data:`KITTI_DEFAULT_RATE_HZ` apart from 0) and optional ``calib.txt`` (``Tr``: Velodyne to
    camera; without it :data:`KITTI_VELO_TO_CAM`, no offset). ``origin_ne`` (northing, easting)
    and ``yaw_deg`` place the local poses in UTM (see :func:`kitti_poses_to_world`);
    ``time_offset_us`` is added to every timestamp (microseconds).
    """

    def __init__(
        self,
        seq_dir: str | Path,
        *,
        poses: str | Path | None = None,
        times: str | Path | None = None,
        calib: str | Path | None = None,
        origin_ne: tuple[float, float] = (0.0, 0.0),
        yaw_deg: float = 0.0,
        time_offset_us: int = 0,
    ) -> None:
        self.dir = Path(seq_dir)
        if not self.dir.is_dir():
            raise InputError("not a directory (expected a KITTI sequence folder)", self.dir)
        self.name = self.dir.name
        velo = self.dir / "velodyne"
        self.files = sorted(velo.glob("*.bin")) if velo.is_dir() else []
        if not self.files:
            raise InputError("no velodyne/*.bin scans found", velo)
        poses_path = Path(poses) if poses is not None else self.dir / "poses.txt"
        if not poses_path.is_file():
            raise InputError("pose file not found (pass it with --poses)", poses_path)
        cam = _read_matrix_rows(poses_path, 12, "a 3x4 camera pose").reshape(-1, 3, 4)
        if len(cam) != len(self.files):
            raise InputError(
                f"{len(cam)} poses for {len(self.files)} scans in {velo}: one line per scan needed",
                poses_path,
            )
        calib_path = Path(calib) if calib is not None else self.dir / "calib.txt"
        if calib_path.is_file():
            tr = read_kitti_calib(calib_path)
        else:
            if calib is not None:
                raise InputError("calibration file not found", calib_path)
            log.info(
                "%s: no calib.txt, using KITTI's nominal Velodyne-to-camera rotation", self.dir
            )
            tr = None
        self.poses = kitti_poses_to_world(cam, tr, origin_ne=origin_ne, yaw_deg=yaw_deg)
        times_path = Path(times) if times is not None else self.dir / "times.txt"
        if times_path.is_file():
            sec = _read_matrix_rows(times_path, 1, "a time in seconds")[:, 0]
            if len(sec) != len(self.files):
                raise InputError(
                    f"{len(sec)} times for {len(self.files)} scans: one line per scan needed",
                    times_path,
                )
            stamps = np.round(sec * 1e6).astype(np.int64)
        else:
            if times is not None:
                raise InputError("times file not found", times_path)
            log.warning(
                "%s: no times.txt, assuming scans %.0f Hz apart from t = 0",
                self.dir,
                KITTI_DEFAULT_RATE_HZ,
            )
            stamps = np.round(np.arange(len(self.files)) * 1e6 / KITTI_DEFAULT_RATE_HZ)
            stamps = stamps.astype(np.int64)
        self.timestamps = stamps + np.int64(time_offset_us)

    def __len__(self) -> int:
        return len(self.files)

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i``: float32 [N, 3], Velodyne frame, metres (reflectance dropped)."""
        path = self.files[i]
        raw = np.fromfile(path, dtype="<f4")
        if raw.size == 0 or raw.size % 4:
            raise InputError(
                f"{path.stat().st_size} bytes is not a whole number of KITTI points (16 bytes)",
                path,
            )
        return raw.reshape(-1, 4)[:, :3]


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


class CsvDrive:
    """A folder of scans plus a CSV of poses, as a :class:`Drive`.

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
        stamps, poses = self._read_csv(path)

        files: dict[int, Path] = {}
        ignored = 0
        for f in sorted(self.dir.iterdir()):
            if f.name.startswith(".") or not f.is_file():
                continue
            if not _INT_STEM.match(f.stem):
                ignored += 1
                continue
            ts = int(f.stem)
            if ts in files:
                raise InputError(
                    f"two scan files for timestamp {ts}: {files[ts].name}, {f.name}", f
                )
            files[ts] = f
        if ignored:
            log.warning("%s: ignored %d file(s) not named <timestamp>.<ext>", self.dir, ignored)
        row_set = set(stamps.tolist())
        no_file = [int(t) for t in stamps if int(t) not in files]
        no_row = sorted(t for t in files if t not in row_set)
        if no_file or no_row:
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
            stamps, poses = stamps[keep], poses[keep]
            if len(stamps) == 0:
                raise InputError("no CSV row has a scan file", path)
        self.timestamps = stamps
        self.poses = poses
        self.files = [files[int(t)] for t in stamps]

    @staticmethod
    def _read_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
        """Parse the pose CSV: (timestamps int64 [T], poses float64 [T, 4, 4]) sorted by time."""
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
        cols = {h: np.asarray(v, dtype=np.float64) for h, v in numeric.items()}
        t_count = len(stamps)
        poses = np.tile(np.eye(4), (t_count, 1, 1))
        if all(c in cols for c in _MATRIX12):
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
                    f"row {int(bad[0]) + 2}: r00..r22 is not a rotation (determinant "
                    f"{det[bad[0]]:.4f})",
                    path,
                )
        elif "northing" in cols and "easting" in cols:
            _, yaw = _angle_column(cols, ("yaw_deg", "yaw_rad"), path, required=False)
            hname, heading = _angle_column(
                cols, ("heading_deg", "heading_rad"), path, required=yaw is None
            )
            if yaw is not None and hname is not None:
                raise InputError("give either a yaw_* or a heading_* column, not both", path)
            if yaw is None:
                assert heading is not None
                yaw = np.pi / 2 - heading
            zeros = np.zeros(t_count)
            _, roll = _angle_column(cols, ("roll_deg", "roll_rad"), path, required=False)
            _, pitch = _angle_column(cols, ("pitch_deg", "pitch_rad"), path, required=False)
            poses[:, :3, :3] = _rpy_matrices(
                zeros if roll is None else roll, zeros if pitch is None else pitch, yaw
            )
            poses[:, 0, 3] = cols["easting"]
            poses[:, 1, 3] = cols["northing"]
            poses[:, 2, 3] = cols.get("height", zeros)
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

    def __len__(self) -> int:
        return len(self.files)

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i`` through :func:`pnvlad_service.io.readers.read_points`: [N, 3] metres."""
        from pnvlad_service.io.readers import read_points

        return read_points(self.files[i], self.reader)


# --------------------------------------------------------------------------------------------
# Cutting a trajectory into submaps


def travelled_distance(poses: np.ndarray) -> np.ndarray:
    """Cumulative horizontal distance along the trajectory: float64 [T] metres, starting at 0.

    ``poses``: float64 [T, 4, 4] sensor-to-world; only x (easting) and y (northing) count.
    """
    xy = np.asarray(poses, dtype=np.float64)[:, :2, 3]
    steps = np.hypot(np.diff(xy[:, 0]), np.diff(xy[:, 1]))
    return np.concatenate([[0.0], np.cumsum(steps)])


def spaced_scans(travelled: np.ndarray, min_spacing_m: float) -> np.ndarray:
    """bool [T]: scans at least ``min_spacing_m`` of travel after the previous one kept.

    Scan 0 is always kept; with ``min_spacing_m`` = 0 every scan is. The choice depends on the
    whole drive, not on a window, so every window uses the same scans (each read once).
    """
    d = np.asarray(travelled, dtype=np.float64)
    keep = np.zeros(len(d), dtype=bool)
    last = -math.inf
    for i, value in enumerate(d.tolist()):
        if value - last >= min_spacing_m:
            keep[i] = True
            last = value
    return keep


@dataclass(frozen=True)
class Cut:
    """One submap position along the trajectory.

    ``distance_m``: travelled distance of the window centre; ``scan``: index of the scan whose
    travelled distance is nearest to it (ties: the earlier scan): it gives the submap's
    timestamp and position; ``first``/``last``: the scans of the window (inclusive).
    """

    distance_m: float
    scan: int
    first: int
    last: int


def submap_cuts(travelled: np.ndarray, window_m: float, stride_m: float) -> list[Cut]:
    """Where to cut submaps: a window of ``window_m`` every ``stride_m`` metres travelled.

    Window ``k`` is centred at distance ``window_m / 2 + k * stride_m`` and holds the scans whose
    travelled distance lies within ``window_m / 2`` of it (inclusive); only whole windows are cut
    (centre + window_m / 2 <= total distance). A cut whose centre scan is the same as the previous
    cut's (a gap in the scans longer than the stride) is dropped.
    """
    if not (window_m > 0 and stride_m > 0):
        raise InputError("window and stride must be positive (metres)", "window_m/stride_m")
    d = np.asarray(travelled, dtype=np.float64)
    if d.ndim != 1 or len(d) == 0 or np.any(np.diff(d) < 0):
        raise InputError("travelled distances must be a non-decreasing [T] array", "travelled")
    half = window_m / 2.0
    total = float(d[-1])
    cuts: list[Cut] = []
    k = 0
    while True:
        s = half + k * stride_m
        k += 1
        if s + half > total:
            break
        j = int(np.searchsorted(d, s, side="left"))  # first scan with d >= s
        if j == len(d) or (j > 0 and s - d[j - 1] <= d[j] - s):
            j = int(np.searchsorted(d, d[j - 1], side="left"))  # nearer below: its first scan
        first = int(np.searchsorted(d, s - half, side="left"))
        last = int(np.searchsorted(d, s + half, side="right")) - 1
        if cuts and cuts[-1].scan == j:
            log.warning("no scan near %.1f m of travel (gap in the drive); submap skipped", s)
            continue
        cuts.append(Cut(distance_m=s, scan=j, first=first, last=last))
    return cuts


# --------------------------------------------------------------------------------------------
# Preparing a run


@dataclass
class LayoutResult:
    """What :func:`prepare_run` did for one layout folder."""

    kind: str
    folder: Path
    csv: Path
    submaps: int = 0
    written: int = 0
    resumed: int = 0
    failed: int = 0


@dataclass
class PrepareResult:
    """Summary of a prepare call: one :class:`LayoutResult` per kind, scans read, seconds."""

    out_run_dir: Path
    layouts: list[LayoutResult] = field(default_factory=list)
    scans_read: int = 0
    seconds: float = 0.0

    def submaps_per_second(self) -> float:
        """Submaps written per second of wall time (0 when nothing was written)."""
        n = sum(r.written for r in self.layouts)
        return n / self.seconds if self.seconds > 0 else 0.0


def _check_drive(drive: Drive) -> tuple[np.ndarray, np.ndarray]:
    """Validate a drive's arrays: (timestamps int64 [T], poses float64 [T, 4, 4])."""
    name = getattr(drive, "name", "drive")
    stamps = np.asarray(drive.timestamps)
    poses = np.asarray(drive.poses, dtype=np.float64)
    if stamps.ndim != 1 or not np.issubdtype(stamps.dtype, np.integer):
        raise InputError(f"timestamps must be int64 [T], got {stamps.dtype} {stamps.shape}", name)
    stamps = stamps.astype(np.int64)
    t_count = len(drive)
    if len(stamps) != t_count or poses.shape != (t_count, 4, 4):
        raise InputError(
            f"{t_count} scans but {len(stamps)} timestamps and poses of shape {poses.shape}", name
        )
    if t_count == 0:
        raise InputError("the drive has no scans", name)
    if np.any(np.diff(stamps) <= 0):
        i = int(np.nonzero(np.diff(stamps) <= 0)[0][0]) + 1
        raise InputError(f"timestamps must increase strictly (scan {i}: {stamps[i]})", name)
    if not np.all(np.isfinite(poses)):
        raise InputError("a pose holds NaN or infinite values", name)
    return stamps, poses


def _target_points(config: Any) -> int:
    """Points per submap the filter G is configured for."""
    for attr in ("num_points", "points", "target_points", "n_points"):
        value = getattr(config, attr, None)
        if isinstance(value, int) and value > 0:
            return value
    return SUBMAP_POINTS


def _config_dump(config: Any) -> Any:
    if config is None:
        return None
    dump = getattr(config, "model_dump", None)
    return dump(mode="json") if callable(dump) else repr(config)


class _ScanCache:
    """Scans of the sliding window, in the sensor frame, read once each.

    Holds float64 [N, 3] arrays keyed by scan index; :meth:`evict_before` drops the scans that
    the windows have passed, so memory is bounded by one window, not the drive.
    """

    def __init__(
        self,
        drive: Drive,
        *,
        seed: int,
        max_points_per_scan: int | None,
        max_range_m: float | None,
    ) -> None:
        self.drive = drive
        self.seed = seed
        self.max_points = max_points_per_scan
        self.max_range = max_range_m
        self.scans: dict[int, np.ndarray] = {}
        self.reads = 0

    def get(self, i: int) -> np.ndarray:
        if i not in self.scans:
            self.scans[i] = self._load(i)
        return self.scans[i]

    def _load(self, i: int) -> np.ndarray:
        name = getattr(self.drive, "name", "drive")
        pts = np.asarray(self.drive.scan(i))
        self.reads += 1
        if pts.ndim != 2 or pts.shape[1] < 3:
            raise InputError(f"scan {i}: expected points [N, 3], got shape {pts.shape}", name)
        pts = pts[:, :3]
        finite = np.isfinite(pts)
        if not finite.all():
            pts = pts[finite.all(axis=1)]
        if self.max_range is not None:
            sq = np.einsum("ij,ij->i", pts, pts, dtype=np.float64)
            pts = pts[sq <= self.max_range**2]
        if self.max_points is not None and len(pts) > self.max_points:
            rng = np.random.default_rng([self.seed, i])
            pts = pts[np.sort(rng.choice(len(pts), self.max_points, replace=False))]
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        return pts

    def evict_before(self, first: int) -> None:
        for i in [i for i in self.scans if i < first]:
            del self.scans[i]


def accumulate(
    poses: np.ndarray,
    scans: dict[int, np.ndarray] | Sequence[np.ndarray],
    indices: Sequence[int],
    centre: np.ndarray,
    box_m: float | None = None,
) -> np.ndarray:
    """Scans moved into a local world frame centred on ``centre``: float64 [M, 3] metres.

    ``poses``: float64 [T, 4, 4] sensor-to-world; ``scans[i]``: [N_i, 3] sensor frame;
    ``centre``: float64 [3] world position (UTM). The result has UTM axes (x east, y north,
    z up) and origin ``centre``; translations are snapped and subtracted in float64 before the
    points are added, so large UTM coordinates lose no precision. ``box_m`` keeps only points
    with |x| and |y| <= box_m / 2 (a square, axis-aligned in UTM).
    """
    c = snap_m(centre)
    parts = []
    for i in indices:
        pts = scans[i]
        if len(pts) == 0:
            continue
        r = poses[i, :3, :3]
        offset = snap_m(poses[i, :3, 3]) - c
        parts.append(pts @ r.T + offset)
    out = np.concatenate(parts) if parts else np.empty((0, 3))
    if box_m is not None:
        half = box_m / 2.0
        out = out[(np.abs(out[:, 0]) <= half) & (np.abs(out[:, 1]) <= half)]
    return out


def _resolve(
    layout: str,
    kind: str,
    window_m: float | None,
    box_m: float | None,
    stride_m: float | None,
) -> tuple[str, str, float, float | None, float]:
    """(folder, csv name, window, box, stride) for one layout and kind, defaults filled in."""
    from pnvlad_service.data.tree import LAYOUTS

    if layout not in LAYOUTS or (layout, kind) not in GEOMETRY:
        raise InputError(
            f"unknown layout/kind {layout!r}/{kind!r} (layouts: {', '.join(LAYOUTS)}; kinds: "
            "train, test)",
            "layout",
        )
    geo = GEOMETRY[(layout, kind)]
    window = geo.window_m if window_m is None else float(window_m)
    box = geo.box_m if box_m is None else (None if box_m <= 0 else float(box_m))
    stride = geo.stride_m if stride_m is None else float(stride_m)
    for value, what in ((window, "window_m"), (stride, "stride_m")):
        if not (math.isfinite(value) and value > 0):
            raise InputError(f"must be a positive number of metres, got {value}", what)
    if box is not None and not math.isfinite(box):
        raise InputError(f"must be a finite number of metres, got {box}", "box_m")
    names = LAYOUTS[layout]
    return names.folder(kind), names.csv(kind), window, box, stride


def prepare_drive(
    drive: Drive,
    out_run_dir: str | Path,
    *,
    layout: Layout = "oxford",
    kinds: Sequence[Kind] = ("train", "test"),
    window_m: float | None = None,
    box_m: float | None = None,
    strides_m: dict[str, float] | None = None,
    g_config: GConfig | None = None,
    seed: int = 0,
    max_points_per_scan: int | None = 10_000,
    max_range_m: float | None = None,
    scan_step: int = 1,
    min_scan_spacing_m: float = 0.05,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> PrepareResult:
    """Cut one drive into submaps for several kinds (default: train and test) in one pass.

    Every scan is read once (windows slide forward over a cache); a window shared by two kinds
    (the test cuts are every other train cut with the default strides) runs G once and is
    written to both folders. Arguments as :func:`prepare_run`; ``strides_m`` maps a kind to its
    stride (default: the layout's, 10 m train and 20 m test for oxford, 10 m and 25 m inhouse).

    Returns a :class:`PrepareResult`. Raises :class:`InputError` on a bad drive or arguments,
    ``FileExistsError`` when an output folder already holds submaps and neither ``resume`` nor
    ``overwrite`` is given.
    """
    from pnvlad_service.data.preprocess import GConfig, filter_g
    from pnvlad_service.data.tree import write_locations_csv
    from pnvlad_service.io.submap import write_submap

    started = time.perf_counter()
    out = Path(out_run_dir)
    stamps, poses = _check_drive(drive)
    config = g_config if g_config is not None else GConfig()
    if scan_step < 1:
        raise InputError(f"must be >= 1, got {scan_step}", "scan_step")
    if not (math.isfinite(min_scan_spacing_m) and min_scan_spacing_m >= 0):
        raise InputError(f"must be >= 0 metres, got {min_scan_spacing_m}", "min_scan_spacing_m")
    if max_points_per_scan is not None and max_points_per_scan < 1:
        raise InputError(f"must be >= 1, got {max_points_per_scan}", "max_points_per_scan")
    if not kinds:
        raise InputError("no kind of submap asked for", "kinds")
    strides = strides_m or {}
    n_bytes = _target_points(config) * 24
    travelled = travelled_distance(poses)
    use = spaced_scans(travelled, min_scan_spacing_m)
    use[np.arange(len(use)) % scan_step != 0] = False

    # Plan: for each kind its cuts; windows are keyed by their centre distance.
    resolved = [
        (kind, *_resolve(layout, kind, window_m, box_m, strides.get(kind)))
        for kind in dict.fromkeys(kinds)
    ]
    plans: list[tuple[LayoutResult, float | None, list[Cut]]] = []
    jobs: dict[tuple[float, float], dict[str, Any]] = {}
    for kind, folder, csv_name, window, box, stride in resolved:
        res = LayoutResult(kind=kind, folder=out / folder, csv=out / csv_name)
        cuts = submap_cuts(travelled, window, stride)
        res.submaps = len(cuts)
        plans.append((res, box, cuts))
        for cut in cuts:
            key = (round(cut.distance_m, 6), window)
            job = jobs.setdefault(key, {"cut": cut, "box": box, "targets": []})
            if job["box"] != box:
                raise InputError("kinds sharing a window must share the box", "box_m")
            job["targets"].append((res, res.folder / f"{stamps[cut.scan]}.bin"))
    # Only now, with every argument checked, touch the output folders.
    manifests: list[tuple[LayoutResult, dict[str, Any]]] = []
    for (res, box, _), (kind, _, _, window, _, stride) in zip(plans, resolved, strict=True):
        manifest = {
            "format": "pnvlad-prepare",
            "version": 1,
            "drive": getattr(drive, "name", "drive"),
            "scans": len(stamps),
            "layout": layout,
            "kind": kind,
            "window_m": window,
            "box_m": box,
            "stride_m": stride,
            "seed": seed,
            "max_points_per_scan": max_points_per_scan,
            "max_range_m": max_range_m,
            "scan_step": scan_step,
            "min_scan_spacing_m": min_scan_spacing_m,
            "g_config": _config_dump(config),
        }
        manifests.append((res, manifest))
    for check_only in (True, False):  # refuse before touching anything
        for res, manifest in manifests:
            _claim_output(
                res, manifest, out, resume=resume, overwrite=overwrite, check_only=check_only
            )

    cache = _ScanCache(
        drive, seed=seed, max_points_per_scan=max_points_per_scan, max_range_m=max_range_m
    )
    failed: set[tuple[str, int]] = set()
    order = sorted(jobs.values(), key=lambda j: (j["cut"].first, j["cut"].distance_m))
    from tqdm.auto import tqdm

    bar = tqdm(order, desc=f"prepare {out.name}", unit="submap", disable=None if progress else True)
    for job in bar:
        cut: Cut = job["cut"]
        todo = []
        for res, path in job["targets"]:
            if resume and path.is_file() and path.stat().st_size == n_bytes:
                res.resumed += 1
            else:
                todo.append((res, path))
        if not todo:
            continue
        cache.evict_before(cut.first)
        indices = [i for i in range(cut.first, cut.last + 1) if use[i]]
        if cut.first <= cut.scan <= cut.last and cut.scan not in indices:
            indices.append(cut.scan)
        scans = {i: cache.get(i) for i in indices}
        local = accumulate(poses, scans, indices, poses[cut.scan, :3, 3], job["box"])
        try:
            if len(local) == 0:
                raise InputError("no points in the window", f"scan {cut.scan}")
            submap = filter_g(local, config, seed=seed + cut.scan)
        except InputError as exc:
            log.warning(
                "submap at %.1f m (timestamp %d) skipped: %s",
                cut.distance_m,
                stamps[cut.scan],
                exc,
            )
            for res, _ in todo:
                res.failed += 1
                failed.add((res.kind, cut.scan))
            continue
        for res, path in todo:
            write_submap(path, submap)
            res.written += 1
    bar.close()

    for res, _, cuts in plans:
        rows = [
            (int(stamps[c.scan]), float(poses[c.scan, 1, 3]), float(poses[c.scan, 0, 3]))
            for c in cuts
            if (res.kind, c.scan) not in failed
        ]
        write_locations_csv(res.csv, rows)
        log.info(
            "%s: %d submaps (%d written, %d already there, %d failed) -> %s",
            res.folder,
            len(rows),
            res.written,
            res.resumed,
            res.failed,
            res.csv.name,
        )
    return PrepareResult(
        out_run_dir=out,
        layouts=[p[0] for p in plans],
        scans_read=cache.reads,
        seconds=time.perf_counter() - started,
    )


def _claim_output(
    res: LayoutResult,
    manifest: dict[str, Any],
    out: Path,
    *,
    resume: bool,
    overwrite: bool,
    check_only: bool = False,
) -> None:
    """Check (resume) or reset (overwrite) a layout folder and record the run's parameters.

    The parameters go to ``<out>/.prepare-<folder>.json``; ``resume`` refuses to continue a
    folder made with other parameters. The locations CSV is removed before any submap is
    written, so a CSV on disk always describes a finished run.
    """
    manifest_path = out / f".prepare-{res.folder.name}.json"
    existing = sorted(res.folder.glob("*.bin")) if res.folder.is_dir() else []
    if resume:
        if manifest_path.is_file():
            try:
                old = json.loads(manifest_path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                old = None
            if isinstance(old, dict) and old != manifest:
                diff = sorted(
                    k for k in manifest.keys() | old.keys() if old.get(k) != manifest.get(k)
                )
                raise InputError(
                    f"cannot resume: {res.folder} was prepared with other parameters "
                    f"({', '.join(diff)}); pass the same options or --overwrite",
                    manifest_path,
                )
        elif existing and not check_only:
            log.warning("%s: no record of the previous parameters; resuming anyway", res.folder)
    elif (existing or res.csv.exists()) and not overwrite:
        raise FileExistsError(
            f"{res.folder}: already holds {len(existing)} submaps or {res.csv.name} exists (pass "
            "--resume to finish an interrupted run or --overwrite to start again)"
        )
    if check_only:
        return
    if not resume:
        for f in existing:
            f.unlink()
    if res.csv.exists():  # rewritten at the end; until then no CSV describes the folder
        res.csv.unlink()
    res.folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(manifest_path, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def prepare_run(
    drive: Drive,
    out_run_dir: str | Path,
    *,
    window_m: float | None = None,
    box_m: float | None = None,
    stride_m: float | None = None,
    layout: Layout = "oxford",
    kind: Kind = "train",
    g_config: GConfig | None = None,
    seed: int = 0,
    max_points_per_scan: int | None = 10_000,
    max_range_m: float | None = None,
    scan_step: int = 1,
    min_scan_spacing_m: float = 0.05,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> PrepareResult:
    """Cut one drive into the submaps of one layout folder and write its locations CSV.

    - ``window_m``: travelled distance accumulated per submap (default: the layout's, 20 m
      oxford, 25 m inhouse), centred on the submap position.
    - ``box_m``: side of a square crop (UTM-aligned) around the submap position (default: none
      for oxford, 25 m for inhouse; 0 disables it).
    - ``stride_m``: distance travelled between submaps (default: 10 m train; 20 m test oxford,
      25 m test inhouse).
    - ``g_config`` / ``seed``: the filter G's settings; submap ``k`` uses ``seed`` + the index of
      its centre scan, so results do not depend on the order submaps are made in.
    - ``max_points_per_scan`` (random subset per scan, seeded by scan index), ``max_range_m``
      (drop points farther from the sensor), ``scan_step`` (every k-th scan) and
      ``min_scan_spacing_m`` (skip scans less than this far along the trajectory from the last
      one used: a car waiting at a light adds one scan, not hundreds) keep the
      accumulation fast on dense drives.
    - ``resume``: keep submaps already on disk with the right size (same parameters required);
      ``overwrite``: remove what the folder holds first.

    A submap is named by the timestamp of its centre scan and tagged, in the CSV, with that
    scan's position (northing, easting); the CSV is written last, atomically.
    """
    return prepare_drive(
        drive,
        out_run_dir,
        layout=layout,
        kinds=(kind,),
        window_m=window_m,
        box_m=box_m,
        strides_m=None if stride_m is None else {kind: stride_m},
        g_config=g_config,
        seed=seed,
        max_points_per_scan=max_points_per_scan,
        max_range_m=max_range_m,
        scan_step=scan_step,
        min_scan_spacing_m=min_scan_spacing_m,
        resume=resume,
        overwrite=overwrite,
        progress=progress,
    )
