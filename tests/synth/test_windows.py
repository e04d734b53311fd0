"""Accumulated queries on the synthetic city (pnvlad_service.synth.windows): each query place's
window is the scans of the last 20 m of the run before it, laid with the run's poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.splits import load_splits
from pnvlad_service.errors import InputError
from pnvlad_service.evaluation.scan_queries import scan_query_set
from pnvlad_service.io.readers import read_points
from pnvlad_service.synth.generate import simulated_drive
from pnvlad_service.synth.windows import drives_of, window_queries, window_start


def test_window_start_is_the_first_scan_within_the_window() -> None:
    poses = np.tile(np.eye(4), (10, 1, 1))
    poses[:, 0, 3] = [0, 1, 2, 5, 9, 14, 20, 27, 35, 44]  # metres along x
    assert window_start(poses, 9, 20.0) == 7  # back to 24 m: the scans at 27, 35 and 44 m
    assert window_start(poses, 9, 24.0) == 6 and window_start(poses, 9, 23.9) == 7
    assert window_start(poses, 2, 100.0) == 0 and window_start(poses, 5, 0.0) == 5


def test_recorded_windows_lie_behind_their_query_in_the_worlds_axes(
    tiny: Path, tmp_path: Path
) -> None:
    qs = scan_query_set(tiny, load_splits(tiny / "splits.json"))
    out = window_queries(qs, tiny, tmp_path, poses="recorded", window_m=20.0, progress=False)
    # the scans laid as the map's windows were: the tiny preset keeps 3,000 points a scan
    assert out.window == {
        "poses": "recorded",
        "frame": "enu",
        "window_m": 20.0,
        "max_points_per_scan": 3000,
        "min_scan_spacing_m": 0.05,
    }
    assert [len(s) for s in out.scans] == [len(s) for s in qs.scans] and out.drift_m == []
    spec, a, k, seed = drives_of(tiny)[("business", qs.runs[0].name)]
    drive = simulated_drive(spec, a, k, seed)
    for scan, window in zip(qs.scans[0][:3], out.scans[0][:3], strict=True):
        assert window.timestamp == scan.timestamp and window.path != scan.path
        i = int(np.flatnonzero(drive.timestamps == scan.timestamp)[0])
        first = window_start(drive.poses, i, 20.0)
        pts = read_points(window.path, "kitti")
        # Every scan of the window, each cut to the sensor's range: more points than the raw
        # scan alone, about the newest scan's recorded position (the cloud's origin).
        assert len(pts) > len(read_points(scan.path, "kitti")) * min(i - first + 1, 2) * 0.5
        assert len(pts) <= 3000 * (i - first + 1)  # at most the map's points a scan
        heading = drive.poses[i, :2, 0]
        behind = -(pts[:, :2] @ heading)
        assert np.percentile(behind, 60) > 0  # more of the window lies behind than ahead


def test_windows_need_a_synth_tree(tiny: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny, copy)
    (copy / "synth.json").unlink()
    qs = scan_query_set(copy, load_splits(copy / "splits.json"))
    with pytest.raises(InputError, match=r"synth\.json"):
        window_queries(qs, copy, tmp_path / "w", progress=False)
    with pytest.raises(InputError, match="recorded or odometry"):
        window_queries(qs, tiny, tmp_path / "w", poses="gps", progress=False)  # type: ignore[arg-type]
