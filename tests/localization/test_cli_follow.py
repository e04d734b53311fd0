"""`pnvlad localize --rosbag` following a drive (the default) against a real `pnvlad serve` on
127.0.0.1 and against a bundle in this process: the tiny city's held-out run as a bag with its
odometry (/odom) and truth (/ground_truth), a keyframe map of the other runs; the CSV's columns
and the summary line recomputed from it; the options' refusals."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.localization.drive.report import GOOD_DEG, GOOD_M, WRONG_POSE_M
from pnvlad_service.localization.drive.rows import COLUMNS
from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server

SCANS = 30


class FirstScans:
    def __init__(self, drive, n: int) -> None:
        self.drive, self.name = drive, drive.name
        self.timestamps, self.poses = drive.timestamps[:n], drive.poses[:n]
        self.true_poses = drive.true_poses[:n]

    def __len__(self) -> int:
        return len(self.timestamps)

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(i)


@pytest.fixture(scope="module")
def bag(tiny_maps: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    pytest.importorskip("rosbags")
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    drive = simulated_drive(get_preset("tiny"), 0, 0, 3)  # the tiny fixture's run 0, held out
    assert drive.name == tiny_maps["query_run"]
    east, north = (float(v) for v in drive.world.origin)
    sub = FirstScans(drive, SCANS)
    path = tmp_path_factory.mktemp("follow") / "run0"
    write_drive_bag(sub, path, origin_ne=(north, east), truth=sub.true_poses)
    return {"bag": path, "origin": f"{north!r},{east!r}", "truth": sub.true_poses}


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def number(text: str) -> float | None:
    return float(text) if text else None


def check_line(line: str, rows: list[dict[str, str]]) -> None:
    """The summary's figures, recomputed from the CSV."""
    first = next((k for k, r in enumerate(rows) if r["verified"] == "true"), None)
    assert first is not None, "no fix in the drive"
    after = rows[first:]
    ver = [r for r in after if r["verified"] == "true"]
    assert f"first fix at scan {rows[first]['scan']} (" in line
    assert f"{100 * len(ver) / len(after):.1f} % of the scans after it verified" in line
    errors = [float(r["pose_error_m"]) for r in ver]
    yaws = [float(r["pose_yaw_error_deg"]) for r in ver]
    assert f"pose error median {np.median(errors):.2f} m / {np.median(yaws):.2f} deg" in line
    good = sum(e <= GOOD_M and y <= GOOD_DEG for e, y in zip(errors, yaws, strict=True))
    assert f"{100 * good / len(after):.1f} % within 1 m and 2 deg" in line
    assert f"{sum(e > WRONG_POSE_M for e in errors)} verified poses more than 5 m off" in line
    relocalised = sum(r["event"] == "relocalised" for r in rows)
    lost = sum(r["event"] == "lost" for r in rows)
    assert f"{relocalised} relocalisations, lost {lost} times" in line


def test_follow_a_bag_against_a_real_server(tiny_maps: dict, bag: dict, tmp_path: Path) -> None:
    port = free_port()
    # A random model: every keyframe a candidate, so that verification finds the place, and a
    # low threshold (the two answers that must agree guard the fix); the tiny city's sparse
    # sensor leaves sigma over 1 m in places: not checked.
    env = {"PNVLAD_RERANK": "100", "PNVLAD_VERIFY_THRESHOLD": "0.04", "PNVLAD_PRIOR_MAX_SIGMA": "0"}
    proc = start_server(tiny_maps["keys"], port, env)
    try:
        out = tmp_path / "run0"
        args = ["localize", "--rosbag", str(bag["bag"]), "--cloud-topic", "/points",
                "--pose-topic", "/odom", "--truth-topic", "/ground_truth",
                "--origin", bag["origin"], "--url", f"http://127.0.0.1:{port}",
                "--map", str(tiny_maps["keys"]), "--out", str(out)]  # fmt: skip
        res = CliRunner().invoke(app, args)
    finally:
        stop_server(proc)
    assert res.exit_code == 0, res.output
    lines = res.stdout.strip().splitlines()
    assert lines[0] == f"wrote {out}.csv, {out}.png" and lines[1] == "odometry: registered"
    rows = read_rows(Path(f"{out}.csv"))
    assert tuple(rows[0]) == COLUMNS["tracked"]
    assert [int(r["scan"]) for r in rows] == list(range(SCANS))
    assert {r["state"] for r in rows} <= {"searching", "tracking", "lost"}
    truth = bag["truth"]
    for r in rows:  # the truth from /ground_truth, the errors from the columns
        t = truth[int(r["scan"])]
        assert float(r["true_easting"]) == pytest.approx(t[0, 3], abs=1e-6)
        if r["pose_easting"]:
            e = math.hypot(float(r["pose_easting"]) - t[0, 3], float(r["pose_northing"]) - t[1, 3])
            assert float(r["pose_error_m"]) == pytest.approx(e, abs=1e-5)
        if r["verified"] == "true":
            assert float(r["pose_error_m"]) < WRONG_POSE_M
            assert r["how"] in ("fix", "registered") and r["anchor"].startswith("business/")
        if r["asked"] == "prior":
            assert r["state"] in ("tracking", "lost") and r["server_ms"]
    tracked = [r for r in rows if r["how"] == "registered"]
    assert len(tracked) >= SCANS // 2, [(r["confidence"], r["fitness"], r["reason"]) for r in rows]
    assert len({r["anchor"].rsplit("/", 1)[0] for r in tracked}) == 1  # one drive's frame
    assert all(number(r["map_error_m"]) is not None for r in tracked)  # the tree's own truth
    check_line(lines[-1], rows)
    assert any(ln.startswith("stages, tracking (") for ln in lines)
    png = Path(f"{out}.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000


def test_follow_here_and_the_options_refused(tiny_maps: dict, bag: dict, tmp_path: Path) -> None:
    base = ["localize", "--rosbag", str(bag["bag"]), "--cloud-topic", "/points",
            "--index", str(tiny_maps["keys"]), "--origin", bag["origin"]]  # fmt: skip
    out = tmp_path / "here"
    # No odometry asked for: constant velocity; no truth: no errors.
    res = CliRunner().invoke(app, [*base, "--odometry", "none", "--out", str(out), "--no-plot",
                                   "--no-progress", "--confirm", "1"])  # fmt: skip
    assert res.exit_code == 0, res.output
    rows = read_rows(Path(f"{out}.csv"))
    assert len(rows) == SCANS and all(r["pose_error_m"] == "" for r in rows)
    assert res.stdout.splitlines()[1] == "odometry: none"
    assert not Path(f"{out}.png").exists()
    kitti = ["localize", "--kitti", str(tmp_path), "--index", str(tiny_maps["keys"])]
    cases = [
        (
            [*base, "--odometry", "wheels"],
            "--odometry: must be auto, poses, registered, kiss-icp or none",
        ),
        ([*base, "--odometry", "poses"], "--odometry: the drive has no poses"),
        ([*base, "--odometry", "registered"], "--odometry: the drive has no poses"),
        ([*base, "--confirm", "0"], "--confirm: confirm and failures must be at least 1"),
        ([*base, "--radius", "-2"], "--radius: radius_m must be > 0"),
        ([*base, "--per-scan", "--radius", "5"], "--radius: applies to following"),
        ([*base, "--per-scan", "--no-fuse"], "--fuse: applies to following"),
        ([*base, "--kitti", str(tmp_path)], "--kitti: give --rosbag or --kitti, not both"),
        ([*kitti, "--cloud-topic", "/points"], "--cloud-topic: applies to --rosbag only"),
        (kitti, "no velodyne/*.bin scans found"),
    ]
    for args, message in cases:
        res = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "bad"), "--no-progress"])
        assert res.exit_code == 2, (args, res.output)
        errors = [line for line in res.output.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and message in errors[0], (args, res.output)
    assert not list(tmp_path.glob("bad*"))
    # A single scan is not followed: --no-fuse is refused as --fuse is.
    for flag in ("--fuse", "--no-fuse"):
        res = CliRunner().invoke(app, ["localize", str(tmp_path / "scan.bin"), "--index",
                                       str(tiny_maps["keys"]), flag])  # fmt: skip
        assert res.exit_code == 2 and "error: --fuse: applies to --rosbag only" in res.output


def same_rows(a: list[dict[str, str]], b: list[dict[str, str]]) -> bool:
    """The rows alike but for the times (and a registration's last digits)."""
    timed = {"read_ms", "odometry_ms", "step_ms", "server_ms"}
    if len(a) != len(b) or (a and list(a[0]) != list(b[0])):
        return False
    for x, y in zip(a, b, strict=True):
        for k in x:
            if k in timed or x[k] == y[k]:
                continue
            if not (x[k] and y[k] and math.isclose(float(x[k]), float(y[k]), rel_tol=1e-9)):
                return False
    return True


def test_the_modes_old_and_new_spellings(tiny_maps: dict, bag: dict, tmp_path: Path) -> None:
    """--mode follow / --mode per-scan make the rows the old spellings (nothing, --follow,
    --per-scan) make; a mode that contradicts the other options is refused."""
    base = ["localize", "--rosbag", str(bag["bag"]), "--cloud-topic", "/points",
            "--pose-topic", "/odom", "--origin", bag["origin"], "--index", str(tiny_maps["keys"]),
            "--every", "5", "--no-plot", "--no-progress"]  # fmt: skip
    spellings = {
        "tracked": ([], ["--mode", "follow"], ["--follow", "--mode", "follow"]),
        "per-scan": (["--per-scan"], ["--mode", "per-scan"]),
    }
    for policy, ways in spellings.items():
        tables = []
        for k, extra in enumerate(ways):
            out = tmp_path / f"{policy}{k}"
            res = CliRunner().invoke(app, [*base, *extra, "--out", str(out)])
            assert res.exit_code == 0, (extra, res.output)
            tables.append(read_rows(Path(f"{out}.csv")))
        assert tuple(tables[0][0]) == COLUMNS[policy] and len(tables[0]) == SCANS // 5
        assert all(same_rows(tables[0], t) for t in tables[1:]), policy
    cases = [
        (["--mode", "follow", "--per-scan"], "--per-scan: contradicts --mode follow"),
        (["--mode", "per-scan", "--follow"], "--follow: contradicts --mode per-scan"),
        (["--mode", "scan"], "--rosbag: --mode scan asks with a SCAN file, not a drive"),
        (["--mode", "drive"], "--mode: must be scan, follow or per-scan, got 'drive'"),
        (["--mode", "per-scan", "--radius", "5"], "--radius: applies to following"),
    ]
    for extra, message in cases:
        res = CliRunner().invoke(app, [*base, *extra, "--out", str(tmp_path / "bad")])
        errors = [line for line in res.output.splitlines() if line.startswith("error: ")]
        assert res.exit_code == 2 and len(errors) == 1 and message in errors[0], res.output
    assert not list(tmp_path.glob("bad*"))
