"""The frame sidecar of a synthetic tree: its metres are the accumulated cloud's, and its true
poses put two runs' submaps of one place on top of each other, where the recorded (GNSS/INS)
positions do not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
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


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rigid 4x4 that best maps points ``a`` [N, 3] onto ``b`` (least squares)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, cb - r @ ca
    return out


def test_the_true_pose_best_lays_the_windows_scans_where_they_were_cast(tiny: Path) -> None:
    """The frame's truth is the rigid motion that best maps the window's points, placed with
    the recorded (noisy) poses in the local frame, onto where the simulator cast them: found
    here by least squares over the scans' points (Kabsch), independently of frame_truth's
    grid of points. It fits them better than the centre scan's true pose alone does."""
    from pnvlad_service.data.accumulate import travelled_distance
    from pnvlad_service.data.cuts import submap_cuts

    tree = BenchmarkTree(tiny)
    run = tree.runs("business")[0]
    drive = simulated_drive(get_preset("tiny"), 0, 0, seed=3)
    assert drive.name == run
    k = 3
    frame = tree.frames("business", run, "train")[k]
    cut = next(
        c
        for c in submap_cuts(travelled_distance(drive.poses), 20.0, 10.0)
        if drive.timestamps[c.scan] == frame.timestamp
    )
    local, truly = [], []
    for i in range(cut.first, cut.last + 1):
        p = drive.scan(i).astype(np.float64)[::7]
        est, true = drive.poses[i], drive.true_poses[i]
        local.append(p @ est[:3, :3].T + (est[:3, 3] - frame.origin))
        truly.append(p @ true[:3, :3].T + true[:3, 3])
    local, truly = np.concatenate(local), np.concatenate(truly)
    best = _kabsch(local, truly)
    assert np.linalg.norm(frame.true_pose[:3, 3] - best[:3, 3]) < 0.1
    dyaw = np.degrees(np.arctan2(best[1, 0], best[0, 0])) - frame.true_yaw_deg
    assert abs(dyaw) < 0.2

    def residual(t: np.ndarray) -> float:  # RMS, what the least squares minimise
        return float(np.sqrt(np.mean(np.sum((local @ t[:3, :3].T + t[:3, 3] - truly) ** 2, 1))))

    i = cut.scan
    shift = np.eye(4)
    shift[:3, 3] = frame.origin
    centre = drive.true_poses[i] @ np.linalg.inv(drive.poses[i]) @ shift
    assert residual(best) <= residual(frame.true_pose) < residual(centre)


def test_refresh_truth_restores_the_sidecars(tiny: Path, tmp_path: Path) -> None:
    """A tree whose true columns hold another truth and whose keyframes lack their motion (an
    older pnvlad's) gets back exactly what generation writes; a sidecar the drive does not
    reproduce is refused, nothing written."""
    import shutil
    from dataclasses import replace

    from pnvlad_service.data.frames import read_frames_csv, write_frames_csv
    from pnvlad_service.errors import InputError
    from pnvlad_service.synth.generate import refresh_truth

    copy = tmp_path / "t"
    shutil.copytree(tiny, copy)
    tree = BenchmarkTree(copy)
    sides = [
        frames_path(tree.csv_path("business", r, kind))
        for r in tree.runs("business")
        for kind in ("train", "test", "keyframe")
    ]
    before = {p: p.read_text() for p in sides}
    for p in sides:  # another truth: every true position 1 m east; the keyframes unmoving
        rows = read_frames_csv(p)
        for f in rows:
            f.true_position[0] += 1.0  # the array itself is mutable
        write_frames_csv(p, [replace(f, motion=None) for f in rows])
    assert all(p.read_text() != before[p] for p in sides)
    n = refresh_truth(copy, progress=False)
    assert n == sum(len(read_frames_csv(p)) for p in sides)
    assert all(p.read_text() == before[p] for p in sides)
    # A row at a timestamp the drive has no submap at: refused, the sidecars untouched.
    rows = read_frames_csv(sides[0])
    rows[0] = replace(rows[0], timestamp=rows[0].timestamp + 1)
    write_frames_csv(sides[0], rows)
    broken = sides[0].read_text()
    with pytest.raises(InputError, match="not a submap of this drive"):
        refresh_truth(copy, progress=False)
    assert sides[0].read_text() == broken and sides[1].read_text() == before[sides[1]]


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


def test_keyframes_carry_the_motion_the_recorded_poses_give(tiny: Path) -> None:
    # Each keyframe's heading, speed and yaw rate: the recording's poses differentiated
    # (data.motion), close to the simulator's own drive (its heading with the GNSS/INS error,
    # its speed, the yaw rate it swept the scans with); accumulated submaps carry none.
    import math

    tree = BenchmarkTree(tiny)
    run = tree.runs("business")[0]
    drive = simulated_drive(get_preset("tiny"), 0, 0, seed=3)
    frames = tree.frames("business", run, "keyframe")
    assert frames and all(f.motion is not None for f in frames)
    assert all(f.motion is None for f in tree.frames("business", run, "train"))
    at = np.searchsorted(drive.timestamps, [f.timestamp for f in frames])
    got = np.stack([f.sweep_motion for f in frames])
    recorded_yaw = np.arctan2(drive.poses[at, 1, 0], drive.poses[at, 0, 0])
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 0] - recorded_yaw))), 0, atol=1e-9)
    assert np.median(np.abs(got[:, 1] - drive.speed)) < 0.05 * drive.speed
    rate_error = np.abs(got[:, 2] - drive._yaw_rate[at])
    assert np.median(rate_error) < math.radians(1.0)
    assert np.abs(drive._yaw_rate[at]).max() > math.radians(10)  # the drive does turn
