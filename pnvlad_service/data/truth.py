"""The true pose of a submap's frame: where the simulator says the accumulated cloud really is.

A submap is accumulated from a window of scans, each placed with its *recorded* pose (with the
simulated GNSS/INS error); the frame sidecar's true-pose columns say which rigid motion lays
that cloud onto where its scans truly were (:func:`frame_truth`). ``pnvlad synth`` records it
(through :func:`..prepare.prepare_drive`) and ``pnvlad synth --refresh-truth`` rewrites it
(:func:`refresh_truth`); verification measures its pose errors against it
(docs/VERIFY.md "Measured against the truth").
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from pnvlad_service.data.accumulate import travelled_distance, used_scans
from pnvlad_service.data.cuts import Cut, Layout, resolve_geometry, submap_cuts
from pnvlad_service.data.drive import Drive, snap_m
from pnvlad_service.data.frames import frames_path, read_frames_csv, write_frames_csv
from pnvlad_service.data.motion import drive_motion, motion_columns
from pnvlad_service.errors import InputError


def drive_true_poses(drive: Drive, n: int) -> np.ndarray | None:
    """The drive's true sensor poses (float64 [T, 4, 4]) where it knows them (the simulator,
    before its GNSS/INS error), else ``None``."""
    true = getattr(drive, "true_poses", None)
    if true is None:
        return None
    true = np.asarray(true, dtype=np.float64)
    if true.shape != (n, 4, 4) or not np.isfinite(true).all():
        raise InputError(f"true_poses must be finite [{n}, 4, 4], got {true.shape}", "drive")
    return true


#: Where :func:`frame_truth` samples each scan of a window: a grid in the sensor's plane,
#: +-15 m every 3 m, where most of a submap's points lie.
_TRUTH_GRID = np.stack(
    [g.ravel() for g in np.meshgrid(np.arange(-15.0, 15.1, 3.0), np.arange(-15.0, 15.1, 3.0))]
    + [np.zeros(121)],
    axis=1,
)


def frame_truth(
    poses: np.ndarray,
    true: np.ndarray,
    cut: Cut,
    origin: np.ndarray,
    use: np.ndarray | None = None,
) -> np.ndarray:
    """float64 [4, 4]: the true pose of the local frame (UTM axes at ``origin``) of the
    submap cut at ``cut``, from the drive's recorded ``poses`` and ``true`` poses [T, 4, 4];
    ``use`` (bool [T]): the scans accumulated (default all).

    The submap is accumulated from the window's scans, each placed with its recorded pose, so
    each scan is off by its own error. The frame's truth is the one rigid motion that best
    lays the window, as accumulated, onto where its scans really were: the least-squares
    (Kabsch) fit of a grid of points about each scan's sensor (``_TRUTH_GRID``) placed with
    the recorded pose in the local frame onto the same points placed with the true pose. Not
    the centre scan's truth alone: a GNSS/INS error that drifts along the window bends the
    cloud, and a drift across the window's length fits as a turn. On the benchmark preset
    the registration of true matches is 0.49 m (median) from the centre-scan truth and 0.30 m
    from this one (docs/VERIFY.md); the grid fit is within 0.1 m and 0.2 degrees of the same
    fit over the scans' real points."""
    idx = np.arange(cut.first, cut.last + 1)
    if use is not None and use[idx].any():
        idx = idx[use[idx]]
    rec, tru = poses[idx], true[idx]  # [W, 4, 4]
    g = _TRUTH_GRID
    local = (g @ rec[:, :3, :3].transpose(0, 2, 1) + (rec[:, None, :3, 3] - origin)).reshape(-1, 3)
    world = (g @ tru[:, :3, :3].transpose(0, 2, 1) + tru[:, None, :3, 3]).reshape(-1, 3)
    ca, cb = local.mean(axis=0), world.mean(axis=0)
    u, _, vt = np.linalg.svd((local - ca).T @ (world - cb))
    rot = vt.T @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = cb - rot @ ca
    return out


def true_columns(
    poses: np.ndarray, true: np.ndarray, cut: Cut, origin: np.ndarray, use: np.ndarray | None
) -> tuple[np.ndarray, float]:
    """The sidecar's true position [3] and yaw (degrees) of :func:`frame_truth`."""
    t = frame_truth(poses, true, cut, origin, use)
    return t[:3, 3].copy(), math.degrees(math.atan2(t[1, 0], t[0, 0]))


def refresh_truth(
    run_dir: str | Path,
    poses: np.ndarray,
    true: np.ndarray,
    stamps: np.ndarray,
    *,
    layout: Layout = "oxford",
    min_scan_spacing_m: float = 0.05,
    scan_step: int = 1,
) -> int:
    """Rewrite the true-pose columns of a prepared run's frame sidecars (every kind of ``layout``
    that has one) with :func:`frame_truth`, from the drive's recorded ``poses``, ``true`` poses and
    ``stamps``, cut as :func:`~.prepare.prepare_drive` cut it (same ``layout`` and scan options),
    and the keyframes' motion columns with :func:`~.motion.drive_motion`'s; the rest of each
    row is kept. Returns the rows rewritten. A row that the drive does not
    reproduce (no cut at its timestamp, or another origin) is refused, naming the sidecar, and
    nothing is written."""
    run_dir = Path(run_dir)
    travelled = travelled_distance(poses)
    use = used_scans(travelled, min_scan_spacing_m, scan_step)
    motion = drive_motion(stamps, poses)
    updates = []
    for kind in ("train", "test", "keyframe"):
        _, csv_name, window, _, stride = resolve_geometry(layout, kind, None, None, None)
        sidecar = frames_path(run_dir / csv_name)
        if not sidecar.is_file():
            continue
        cuts = {int(stamps[c.scan]): c for c in submap_cuts(travelled, window, stride)}
        rows = []
        for f in read_frames_csv(sidecar):
            cut = cuts.get(f.timestamp)
            origin = None if cut is None else snap_m(poses[cut.scan, :3, 3])
            if cut is None or not np.allclose(origin, f.origin, atol=1e-6):
                raise InputError(
                    f"the row of timestamp {f.timestamp} is not a submap of this drive (made "
                    "by another version or other options?)",
                    sidecar,
                )
            pos, yaw = true_columns(poses, true, cut, origin, use)
            moving = f.motion
            if kind == "keyframe":
                moving = motion_columns(motion[cut.scan])
            rows.append(replace(f, true_position=pos, true_yaw_deg=yaw, motion=moving))
        updates.append((sidecar, rows))
    for sidecar, rows in updates:  # only once every sidecar of the run checked out
        write_frames_csv(sidecar, rows)
    return sum(len(r) for _, r in updates)
