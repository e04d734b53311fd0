"""The frame sidecar of a synthetic tree: its metres are the accumulated cloud's, and its true
poses put two runs' submaps of one place on top of each other, where the recorded (GNSS/INS)
positions do not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pnvlad_service.data.frames import frames_path
from pnvlad_service.data.tree import BenchmarkTree, check_tree
from pnvlad_service.io.submap import read_submap
from pnvlad_service.synth.generate import get_preset, simulated_drive


def _metric(tree: BenchmarkTree, run: str, k: int) -> tuple[np.ndarray, object]:
    sub = tree.submaps("business", run, "train")[k]
    frame = tree.frames("business", run, "train")[k]
    return frame.local_m(read_submap(tree.root / sub.path)), frame


def test_every_run_has_a_sidecar_with_true_poses(tiny: Path) -> None:
    tree = BenchmarkTree(tiny)
    for run in tree.runs("business"):
        for kind in ("train", "test"):
            frames = tree.frames("business", run, kind)
            subs = tree.submaps("business", run, kind)
            assert [f.timestamp for f in frames] == [s.timestamp for s in subs]
            assert all(f.true_pose is not None and f.scale > 0 for f in frames)
            # The map position of the frame is the CSV's (northing, easting), to the mm grid.
            for f, s in zip(frames, subs, strict=True):
                assert abs(f.origin[0] - s.easting) < 1e-3 and abs(f.origin[1] - s.northing) < 1e-3


def test_the_true_pose_is_the_centre_scans_true_sensor_pose(tiny: Path) -> None:
    tree = BenchmarkTree(tiny)
    run = tree.runs("business")[0]
    drive = simulated_drive(get_preset("tiny"), 0, 0, seed=3)
    assert drive.name == run
    k = 3
    frame = tree.frames("business", run, "train")[k]
    i = int(np.flatnonzero(drive.timestamps == frame.timestamp)[0])
    p = drive.scan(i).astype(np.float64)
    est = drive.poses[i]
    local = p @ est[:3, :3].T + (est[:3, 3] - frame.origin)
    yaw = drive.true_yaw[i]
    r = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    t = np.array([*(drive.world.origin[:2] + drive.true_xy[i]), drive.true_z[i]])
    truly = p @ r.T + t
    mapped = local @ frame.true_pose[:3, :3].T + frame.true_pose[:3, 3]
    assert np.abs(mapped - truly).max() < 1e-6


def test_the_metres_are_the_accumulated_cloud(tiny: Path) -> None:
    tree = BenchmarkTree(tiny)
    run = tree.runs("business")[0]
    pts, frame = _metric(tree, run, 3)
    drive = simulated_drive(get_preset("tiny"), 0, 0, seed=3)
    i = int(np.flatnonzero(drive.timestamps == frame.timestamp)[0])
    est = drive.poses[i]
    raw = drive.scan(i).astype(np.float64) @ est[:3, :3].T + (est[:3, 3] - frame.origin)
    # Every point G kept is an average of nearby raw points of the window; the centre scan
    # alone already lies under most of them.
    d, _ = cKDTree(raw).query(pts)
    assert np.median(d) < 0.5, np.median(d)
    assert 5.0 < abs(frame.scale) < 40.0


def test_true_poses_overlay_two_runs_where_the_map_poses_do_not(tiny: Path) -> None:
    tree = BenchmarkTree(tiny)
    runs = tree.runs("business")
    a_pts, a = _metric(tree, runs[0], 5)
    others = tree.submaps("business", runs[1], "train")
    k = int(
        np.argmin([np.hypot(s.northing - a.origin[1], s.easting - a.origin[0]) for s in others])
    )
    b_pts, b = _metric(tree, runs[1], k)

    def spread(t_a: np.ndarray, t_b: np.ndarray) -> float:
        rel = np.linalg.inv(t_a) @ t_b  # b's local frame -> a's
        moved = b_pts @ rel[:3, :3].T + rel[:3, 3]
        return float(np.median(cKDTree(a_pts).query(moved)[0]))

    true_fit = spread(a.true_pose, b.true_pose)
    map_fit = spread(a.map_pose, b.map_pose)
    assert true_fit < 0.35, true_fit
    assert map_fit > true_fit


def test_check_tree_flags_a_bad_sidecar(tiny: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "t"
    shutil.copytree(tiny, copy)
    tree = BenchmarkTree(copy)
    run = tree.runs("business")[0]
    side = frames_path(tree.csv_path("business", run, "test"))
    lines = side.read_text().splitlines()
    side.write_text("\n".join(lines[:-1]) + "\n")  # one row short
    report = check_tree(copy)
    assert not report.ok
    assert any(side.name in p.path and "rows where the locations CSV has" in p.message
               for p in report.problems)  # fmt: skip
