"""The follow command on real KITTI 00 scans in KITTI's own format (`pnvlad localize --kitti`):
the shared frames are too few to measure a drive (docs/TRACKING.md), so this shows that the
pipeline takes them - a keyframe map made from frame 52 (`pnvlad data prepare --kitti`,
`pnvlad index build --layout keyframe`) and a two-scan drive of frames 94 and 95 (33 m on,
consecutive) followed against it, its truth KITTI's recorded poses placed as the map's frame;
frame 94 is too far from 52 to be verified. Then frame 4501 (the revisit, 3 m from 52) twice,
a robot standing still: a fix, then a registration near the prediction. The model is random:
with a one-entry map retrieval is trivial; what runs is the search, the verification, the fix,
the registration near the prediction and the CSV."""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.localization.drive.rows import COLUMNS
from tests.index.helpers import make_checkpoint
from tests.kitti00 import TR_LINE, pose_line, velodyne_pose

pytest.importorskip("small_gicp")

ORIGIN_NE = (5_735_000.0, 620_000.0)
YAW_DEG = 30.0


def placed(folder: Path, i: int) -> np.ndarray:
    """Frame ``i`` of KITTI 00 in the map's frame: frame 52 at ``ORIGIN_NE`` facing
    ``YAW_DEG`` (as `pnvlad data prepare --kitti` places the first scan of its folder)."""
    c, s = math.cos(math.radians(YAW_DEG)), math.sin(math.radians(YAW_DEG))
    place = np.eye(4)
    place[:2, :2] = [[c, -s], [s, c]]
    place[:2, 3] = ORIGIN_NE[1], ORIGIN_NE[0]
    return place @ np.linalg.inv(velodyne_pose(folder, 52)) @ velodyne_pose(folder, i)


def sequence(base: Path, real_scans: Path, frames: list[int]) -> Path:
    seq = base / f"seq{'-'.join(map(str, frames))}"
    if seq.exists():
        seq = seq.with_name(seq.name + "-again")
    (seq / "velodyne").mkdir(parents=True)
    for k, i in enumerate(frames):
        os.symlink(real_scans / f"kitti00_{i:06d}.bin", seq / "velodyne" / f"{k:06d}.bin")
    (seq / "poses.txt").write_text("".join(pose_line(real_scans, i) + "\n" for i in frames))
    (seq / "times.txt").write_text("".join(f"{0.1 * k:.1f}\n" for k in range(len(frames))))
    (seq / "calib.txt").write_text(TR_LINE + "\n")
    return seq


def run_cli(args: list[str]) -> str:
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, (args[:3], res.output, res.exception)
    return res.stdout


@pytest.mark.real_scans
def test_a_kitti_drive_is_followed(real_scans: Path, tmp_path: Path) -> None:
    model = make_checkpoint(tmp_path / "model")
    tree = tmp_path / "tree"
    origin = f"{ORIGIN_NE[0]},{ORIGIN_NE[1]}"
    run_cli(["data", "prepare", "--kitti", str(sequence(tmp_path, real_scans, [52])),
             "--kind", "keyframe", "--origin", origin, "--yaw", str(YAW_DEG),
             "--out", str(tree / "kitti" / "run52")])  # fmt: skip
    bundle = tmp_path / "map.index"
    run_cli(["index", "build", "-m", str(model), "-r", str(tree), "--layout", "keyframe",
             "-o", str(bundle)])  # fmt: skip
    drives = {}
    for frames in ([94, 95], [4501, 4501]):
        first = placed(real_scans, frames[0])  # the drive's folder starts there
        yaw = math.degrees(math.atan2(first[1, 0], first[0, 0]))
        out = tmp_path / f"follow{frames[0]}"
        stdout = run_cli(["localize", "--kitti", str(sequence(tmp_path, real_scans, frames)),
                          "--index", str(bundle), "-m", str(model), "--confirm", "1",
                          "--origin", f"{float(first[1, 3])!r},{float(first[0, 3])!r}",
                          "--yaw", repr(yaw), "--out", str(out), "--no-progress"])  # fmt: skip
        lines = stdout.strip().splitlines()
        assert lines[0] == f"wrote {out}.csv, {out}.png" and lines[1] == "odometry: registered"
        assert lines[-1].startswith("follow: 2 scans in ")
        with open(f"{out}.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        print(frames, " | ".join(f"{r['state']} {r['how']} {r['pose_error_m']} {r['reason']}"
                                 for r in rows))  # fmt: skip
        assert [int(r["scan"]) for r in rows] == [0, 1]
        assert [int(r["timestamp"]) for r in rows] == [0, 100_000]
        for r, frame in zip(rows, frames, strict=True):  # the truth: the poses file, placed
            want = placed(real_scans, frame)
            assert float(r["true_northing"]) == pytest.approx(want[1, 3], abs=1e-3)
            assert float(r["true_easting"]) == pytest.approx(want[0, 3], abs=1e-3)
            if r["verified"] == "true":  # KITTI's recorded poses are good to about 0.25 m here
                assert float(r["pose_error_m"]) < 1.0, r
        assert rows[0]["asked"] == "search"
        drives[frames[0]] = rows
    still = drives[4501]
    assert [(r["state"], r["how"], r["asked"]) for r in still] == [
        ("tracking", "fix", "search"),
        ("tracking", "registered", "prior"),
    ]
    # --mode per-scan asks with each scan of a KITTI sequence alone, the rows those of a bag
    # asked scan by scan; --per-scan without --mode follows a KITTI sequence, as it always did.
    first = placed(real_scans, 4501)
    place = ["--origin", f"{float(first[1, 3])!r},{float(first[0, 3])!r}", "--yaw",
             repr(math.degrees(math.atan2(first[1, 0], first[0, 0]))), "--index", str(bundle),
             "-m", str(model), "--no-progress", "--no-plot"]  # fmt: skip
    seq = str(sequence(tmp_path, real_scans, [4501, 4501]))
    out = tmp_path / "per-scan"
    lines = run_cli(["localize", "--mode", "per-scan", "--kitti", seq, "--every", "1", *place,
                     "--out", str(out)]).strip().splitlines()  # fmt: skip
    assert lines[0] == f"wrote {out}.csv" and lines[-1].startswith("replay: 2 of 2 queries")
    with open(f"{out}.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == COLUMNS["per-scan"] and [r["status"] for r in rows] == ["ok"] * 2
    assert float(rows[0]["true_northing"]) == pytest.approx(first[1, 3], abs=1e-3)
    lines = run_cli(["localize", "--per-scan", "--kitti", seq, *place,
                     "--out", str(tmp_path / "old")]).strip().splitlines()  # fmt: skip
    assert lines[1] == "odometry: registered" and lines[-1].startswith("follow: 2 scans in ")
