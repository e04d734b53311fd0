"""benchmarks/scale_between_runs.py end to end on a hand-made tree: the scale ratios of one place
on two drives, worked out by hand."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from pnvlad_service.data.frames import SubmapFrame, write_frames_csv

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "scale_between_runs.py"


def _run(area: Path, name: str, north: list[float], scales: list[float], truth: bool) -> None:
    d = area / name
    d.mkdir(parents=True)
    csv = d / "pointcloud_locations_20m.csv"
    csv.write_text(
        "timestamp,northing,easting\n" + "".join(f"{k},{n},600000.0\n" for k, n in enumerate(north))
    )
    frames = []
    for k, (n, s) in enumerate(zip(north, scales, strict=True)):
        at = np.array([600000.0, n, 0.0])
        frames.append(
            SubmapFrame(
                timestamp=k,
                # The recorded position is 30 m off when the truth is given: the truth must win.
                origin=at + ([30.0, 0.0, 0.0] if truth else 0.0),
                centre=np.zeros(3),
                scale=s,
                true_position=at if truth else None,
                true_yaw_deg=0.0 if truth else None,
            )
        )
    write_frames_csv(d / "pointcloud_locations_20m.frames.csv", frames)


def test_ratios_of_one_place_on_two_drives(tmp_path: Path) -> None:
    area = tmp_path / "tree" / "town"
    # Places 0, 100 and 200 m north; run b drives them 2 m off and a fourth 50 m beyond.
    _run(area, "a", [0.0, 100.0, 200.0], [10.0, 20.0, 30.0], truth=True)
    _run(area, "b", [2.0, 102.0, 202.0, 250.0], [11.0, 20.0, 60.0, 5.0], truth=False)
    (area / "c").mkdir()  # a run without submaps is skipped
    out = tmp_path / "f.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(tmp_path / "tree"), "--json", str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    f = json.loads(out.read_text())["tree/town"]
    # a -> b: 1.1, 1.0, 2.0; b -> a: the same three (250 m has no place within 5 m).
    assert f["pairs"] == 6
    assert f["submaps"] == 7
    assert f["ratio p50"] == 1.1
    assert f["ratio p90"] == 2.0
    assert f["beyond 1.03 %"] == round(100 * 4 / 6, 1)
    assert f["beyond 1.25 %"] == round(100 * 2 / 6, 1)
    assert f["scale m p50"] == 20.0
    assert "| tree/town | 7 |" in done.stdout


def test_a_tree_without_sidecars_is_one_line_error(tmp_path: Path) -> None:
    (tmp_path / "town" / "a").mkdir(parents=True)
    done = subprocess.run(
        [sys.executable, str(SCRIPT), str(tmp_path)], capture_output=True, text=True
    )
    assert done.returncode == 2
    assert done.stderr.startswith("error: ") and str(tmp_path) in done.stderr
