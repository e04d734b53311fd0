"""The aligned map written as a tree of its own, the recorded one left as it was.

For each run the solved poses of its nodes give a correction ``D`` (float64 [4, 4]) of each
node's laid frame: ``aligned = laid @ D`` (``D`` = the true frame in the laid one: a turn and
a shift about the node's origin, UTM axes). Each entry of the run (keyframes, test and
training submaps) takes the correction interpolated at its timestamp between the two nodes
about it, and is re-laid by it: its points turned by the correction's rotation about its own
origin, its origin moved by the shift, then normalised again (``metres = centre + scale *
points``, exactly the metres before, turned and moved). A keyframe is one scan: re-laid whole,
it is what G would give of the scan laid with the aligned pose, up to G's voxel grid turning
with it. A submap is a window of scans laid by their recorded poses: re-laid whole by the
correction at its centre, the error between its own scans stays (the GNSS/INS walk's change
over the window, decimetres over 20 m).

The out tree has the in tree's layout, so ``pnvlad index build`` builds from it unchanged; each
run also gets ``aligned_poses.csv`` (the nodes' recorded and aligned poses side by side). The
tree is written under a temporary name and renamed when whole (``atomic_directory``).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pnvlad_service.data.drive import snap_m
from pnvlad_service.data.frames import SubmapFrame, frames_path, write_frames_csv
from pnvlad_service.data.scans import RAW_CSV, RAW_FOLDER, read_raw_scans, write_raw_scans_csv
from pnvlad_service.data.tree import KINDS, BenchmarkTree, write_locations_csv
from pnvlad_service.fileio import atomic_directory, atomic_write_rows
from pnvlad_service.io.submap import SUBMAP_BOUND, read_submap, write_submap
from pnvlad_service.mapping.graph import _log_rot
from pnvlad_service.mapping.nodes import MapNodes, RunNodes

log = logging.getLogger(__name__)

ALIGNED_POSES = "aligned_poses.csv"
POSE_COLUMNS = (
    "timestamp",
    "recorded_easting",
    "recorded_northing",
    "recorded_height",
    "aligned_easting",
    "aligned_northing",
    "aligned_height",
    "aligned_yaw_deg",
    "correction_m",
)


def _exp_rot(w: np.ndarray) -> np.ndarray:
    """The rotation of angle-axis ``w`` [3] (Rodrigues)."""
    theta = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + K
    return np.eye(3) + math.sin(theta) / theta * K + (1 - math.cos(theta)) / theta**2 * K @ K


def corrections(laid: np.ndarray, aligned: np.ndarray) -> np.ndarray:
    """float64 [N, 6]: each node's correction ``inv(laid) @ aligned`` as (shift [3] metres,
    angle-axis [3] radians)."""
    out = np.zeros((len(laid), 6))
    for k, (a, b) in enumerate(zip(laid, aligned, strict=True)):
        d = np.linalg.inv(a) @ b
        out[k] = np.r_[d[:3, 3], _log_rot(d[:3, :3])]
    return out


def correction_at(stamps: np.ndarray, corr: np.ndarray, t: int) -> np.ndarray:
    """float64 [4, 4]: the correction at timestamp ``t``, linear between the nodes about it
    (the first or last node's outside them)."""
    v = np.array([np.interp(float(t), stamps.astype(np.float64), corr[:, i]) for i in range(6)])
    out = np.eye(4)
    out[:3, :3] = _exp_rot(v[3:])
    out[:3, 3] = v[:3]
    return out


def relaid_frame(
    frame: SubmapFrame, points: np.ndarray, d: np.ndarray
) -> tuple[SubmapFrame, np.ndarray]:
    """An entry's frame row and normalised points re-laid by its correction ``d`` [4, 4]: the
    frame keeps UTM axes, at the moved origin; the points are turned, and shrunk where a turn
    took one past the submap's bound (the scale grows alike, so the metres are exact)."""
    R = d[:3, :3]
    turned = np.asarray(points, dtype=np.float64) @ R.T
    m = max(1.0, float(np.abs(turned).max()) / SUBMAP_BOUND)
    origin = snap_m(frame.origin + d[:3, 3])
    turn = math.degrees(math.atan2(R[1, 0], R[0, 0]))
    true_yaw = None
    if frame.true_yaw_deg is not None:
        true_yaw = frame.true_yaw_deg - turn
    motion = None
    if frame.motion is not None:  # the sensor's heading turns with the points
        motion = frame.motion + np.array([turn, 0.0, 0.0])
    row = SubmapFrame(
        frame.timestamp,
        origin,
        R @ frame.centre,
        frame.scale * m,
        frame.frame,
        frame.true_position,
        true_yaw,
        motion,
    )
    return row, turned / m


def _relay_kind(
    tree: BenchmarkTree,
    out: Path,
    dataset: str,
    run: str,
    kind: str,
    stamps: np.ndarray,
    corr: np.ndarray,
) -> int:
    """One kind of entries of one run re-laid into ``out``; how many."""
    layout = tree.layout(dataset, run)
    frames = tree.frames(dataset, run, kind)  # type: ignore[arg-type]
    if frames is None:
        return 0
    src = tree.root / dataset / run
    dst = out / dataset / run
    (dst / layout.folder(kind)).mkdir(parents=True, exist_ok=True)  # type: ignore[arg-type]
    rows = []
    for f in frames:
        name = f"{layout.folder(kind)}/{f.timestamp}.bin"  # type: ignore[arg-type]
        d = correction_at(stamps, corr, f.timestamp)
        row, pts = relaid_frame(f, read_submap(src / name), d)
        write_submap(dst / name, pts)
        rows.append(row)
    csv = dst / layout.csv(kind)  # type: ignore[arg-type]
    write_frames_csv(frames_path(csv), rows)
    write_locations_csv(csv, [(r.timestamp, float(r.origin[1]), float(r.origin[0])) for r in rows])
    return len(rows)


def _relay_raw(src: Path, dst: Path, stamps: np.ndarray, corr: np.ndarray) -> None:
    """The raw scans (linked, or copied) with their recorded poses corrected."""
    if not (src / RAW_CSV).is_file():
        return
    (dst / RAW_FOLDER).mkdir(parents=True, exist_ok=True)
    rows = []
    for scan in read_raw_scans(src):
        target = dst / RAW_FOLDER / scan.path.name
        try:
            os.link(scan.path, target)
        except OSError:
            shutil.copy2(scan.path, target)
        laid = np.eye(4)
        laid[:3, 3] = scan.pose[:3, 3]
        d = correction_at(stamps, corr, scan.timestamp)
        rows.append((scan.timestamp, laid @ d @ np.linalg.inv(laid) @ scan.pose, scan.true_pose))
    write_raw_scans_csv(dst / RAW_CSV, rows)


def _copy_plain_files(src: Path, dst: Path) -> None:
    """The plain and hidden files beside a tree's folders (splits, regions, prepare
    records, synth.json), copied."""
    dst.mkdir(parents=True, exist_ok=True)
    for p in src.iterdir():
        if p.is_file() and not p.name.endswith(".csv"):
            shutil.copy2(p, dst / p.name)


def _pose_rows(run: RunNodes, aligned: np.ndarray) -> list[SimpleNamespace]:
    """The rows of a run's ``aligned_poses.csv``: each node's recorded and aligned pose."""
    axes = ("easting", "northing", "height")
    rows = []
    for t, a, b in zip(run.stamps, run.poses, aligned, strict=True):
        row = SimpleNamespace(timestamp=int(t))
        for i, k in enumerate(axes):
            setattr(row, f"recorded_{k}", float(a[i, 3]))
            setattr(row, f"aligned_{k}", float(b[i, 3]))
        row.aligned_yaw_deg = math.degrees(math.atan2(b[1, 0], b[0, 0]))
        row.correction_m = float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
        rows.append(row)
    return rows


def write_aligned_tree(
    root: str | Path,
    out: str | Path,
    nodes: MapNodes,
    aligned: np.ndarray,
    overwrite: bool = False,
) -> dict[str, int]:
    """The tree at ``root`` re-laid by the ``aligned`` node poses [N, 4, 4] into ``out``
    (see the module doc). Returns how many entries of each kind were re-laid."""
    tree = BenchmarkTree(root)
    counts = dict.fromkeys(KINDS, 0)
    by_name = {
        r.name: (r, aligned[s : s + len(r)])
        for s, r in zip(nodes.starts(), nodes.runs, strict=True)
    }
    with atomic_directory(out, overwrite=overwrite) as tmp:
        _copy_plain_files(tree.root, tmp)
        for dataset in tree.datasets:
            _copy_plain_files(tree.root / dataset, tmp / dataset)
            for run in tree.runs(dataset):
                node_run, poses = by_name[f"{dataset}/{run}"]
                corr = corrections(node_run.poses, poses)
                _copy_plain_files(tree.root / dataset / run, tmp / dataset / run)
                for kind in KINDS:
                    if tree.has(dataset, run, kind):
                        counts[kind] += _relay_kind(
                            tree, tmp, dataset, run, kind, node_run.stamps, corr
                        )
                _relay_raw(tree.root / dataset / run, tmp / dataset / run, node_run.stamps, corr)
                atomic_write_rows(
                    _pose_rows(node_run, poses), POSE_COLUMNS, tmp / dataset / run / ALIGNED_POSES
                )
    log.info("aligned tree -> %s (%s)", out, counts)
    return counts
