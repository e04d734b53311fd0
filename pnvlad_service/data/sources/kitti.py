"""KITTI-odometry sequence folders as drives: :class:`KittiSequence`, with
:func:`read_kitti_calib` and :func:`kitti_poses_to_world` (camera-0 poses to Velodyne-to-world
poses, z up, UTM metres, translations snapped by :func:`~pnvlad_service.data.drive.snap_m`)."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from pnvlad_service.data.drive import place_in_utm
from pnvlad_service.data.sources.returns import NoReturnCount
from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_scan

log = logging.getLogger(__name__)

#: KITTI's nominal rotation from the Velodyne frame (x forward, y left, z up) to the camera
#: frame (x right, y down, z forward): camera = R @ velodyne. Used when calib.txt is absent.
KITTI_VELO_TO_CAM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

#: Scan rate assumed for a KITTI sequence without times.txt (Hz).
KITTI_DEFAULT_RATE_HZ = 10.0


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
    Translations are snapped to :data:`~pnvlad_service.data.drive.SNAP_M` before the origin is
    added, so the result minus the origin does not depend on the origin's magnitude.
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
    return place_in_utm(local, origin_ne, yaw_deg)


class KittiSequence:
    """A KITTI-odometry style sequence folder as a :class:`~pnvlad_service.data.drive.Drive`.

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
        self.no_returns = NoReturnCount()

    def __len__(self) -> int:
        return len(self.files)

    def scan(self, i: int) -> np.ndarray:
        """Scan ``i``: float32 [N, 3], Velodyne frame, metres (reflectance dropped), read by
        the ``kitti`` reader of :mod:`pnvlad_service.io.readers`, missing returns written as
        points at the origin dropped (and counted in ``no_returns``)."""
        points, dropped = read_scan(self.files[i], "kitti")
        self.no_returns.add(dropped, self.files[i])
        return points
