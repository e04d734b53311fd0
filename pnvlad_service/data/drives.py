"""Recorded drives: LiDAR scans with their poses, one class per source, all with one face.

A *drive* is anything that satisfies the :class:`Drive` protocol (``name``, ``timestamps``,
``poses``, ``len()``, ``scan(i)``); :func:`pnvlad_service.data.prepare.prepare_drive` cuts any
of them into benchmark submaps. The sources here:

- :class:`KittiSequence`: a KITTI-odometry sequence folder (velodyne/*.bin, poses.txt, optional
  times.txt and calib.txt), with :func:`read_kitti_calib` and :func:`kitti_poses_to_world`;
- :class:`CsvDrive`: a folder of scans in any format :mod:`pnvlad_service.io.readers` knows,
  plus a CSV of planar or full poses.

(:class:`pnvlad_service.data.rosbag.RosbagDrive` reads ROS bags (extra ``rosbag``);
:class:`pnvlad_service.synth.runs.SimulatedDrive` is the synthetic city's.)

Conventions (docs/ARCHITECTURE.md): world frame x = easting, y = northing, z = up, UTM metres;
timestamps are integer microseconds. Translations are snapped to a 2**-26 m (15 nm) grid
(:func:`snap_m`) so that adding a UTM origin and subtracting a submap centre are exact in
float64.
"""

from __future__ import annotations

import csv
import logging
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_points

log = logging.getLogger(__name__)

#: Grid (metres) that translations are snapped to: 2**-26 m, about 15 nanometres. Any UTM
#: coordinate (< 2**24 m) on this grid has at most 50 significant bits, so sums and differences
#: of such coordinates are exact in float64.
SNAP_M = 2.0**-26

#: KITTI's nominal rotation from the Velodyne frame (x forward, y left, z up) to the camera
#: frame (x right, y down, z forward): camera = R @ velodyne. Used when calib.txt is absent.
KITTI_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: Scan rate assumed for a KITTI sequence without times.txt (Hz).
KITTI_DEFAULT_RATE_HZ = 10.0


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
    velo = tr_inv @ p @ tr  # Velodyne i -> Velodyne frame of the poses file's identity
    # Re-based on the first scan, so that it sits at the origin facing ``yaw_deg`` even when the
    # poses file does not start at the identity (a sequence cut from a longer one).
    local = np.linalg.inv(velo[0]) @ velo
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
        """Scan ``i``: float32 [N, 3], Velodyne frame, metres (reflectance dropped), read by
        the ``kitti`` reader of :mod:`pnvlad_service.io.readers`."""
        return read_points(self.files[i], "kitti")


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
        stamps, poses = _read_pose_csv(path)
        files = _scan_files(self.dir)
        keep = self._match(stamps, files, path, skip_missing)
        if keep is not None:
            stamps, poses = stamps[keep], poses[keep]
        self.timestamps = stamps
        self.poses = poses
        self.files = [files[int(t)] for t in stamps]

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
        """Scan ``i`` through :func:`pnvlad_service.io.readers.read_points`: [N, 3] metres."""
        return read_points(self.files[i], self.reader)


def check_drive(drive: Drive) -> tuple[np.ndarray, np.ndarray]:
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
