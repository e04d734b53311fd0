"""A drive asked scan by scan (localization/drive/runner.py, policy ``per-scan``) with a
stand-in service: the rows, their CSV, the summary and the PNG; then `pnvlad localize --rosbag
--per-scan` against a real server on 127.0.0.1 and against a bundle in this process."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.plot import plot_drive
from pnvlad_service.localization.drive.report import summarise
from pnvlad_service.localization.drive.rows import COLUMNS, POSE_COLUMNS, read_rows, write_rows
from pnvlad_service.localization.drive.runner import run_drive
from pnvlad_service.localization.drive.service import Place, Reply


class LineDrive:
    """Scans 1 s apart along northing, 10 m apart, each scan's first point x = its index."""

    def __init__(self, n: int, poses: bool = True) -> None:
        self.name = "line"
        self.timestamps = np.arange(n, dtype=np.int64) * 1_000_000 + 5_000_000
        self.poses = None
        if poses:
            self.poses = np.tile(np.eye(4), (n, 1, 1))
            self.poses[:, 1, 3] = 5_735_000.0 + 10.0 * np.arange(n)
            self.poses[:, 0, 3] = 620_000.0

    def __len__(self) -> int:
        return len(self.timestamps)

    def scan(self, i: int) -> np.ndarray:
        return np.full((100, 3), float(i), dtype=np.float32)


def pose_at(northing: float, easting: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = [easting, northing]
    return out


def fake_service(points: np.ndarray, prior=None, kind: str = "scan") -> Reply:
    """Answers scan i as the server does: a submap 3 m east of it (scan 4: 40 m off, scan 6:
    refused, scan 8: no match); scans 0 and 4 verified, with a pose 0.5 m north of the truth
    and turned 2 degrees (scan 4's: 40 m off, a wrong verified pose)."""
    assert prior is None and kind == "scan"
    i = int(points[0, 0])
    if i == 6:
        raise InputError("only 3 points left after G", "points")
    if i == 8:
        return Reply()
    north = 5_735_000.0 + 10.0 * i + (40.0 if i == 4 else 0.0)
    top = Place("x", 1000 + i, "r0", "keyframe", north, 620_003.0, 0.25 * i)
    verified = i % 4 == 0
    return Reply(
        verified=verified,
        pose=pose_at(north + 0.5, 620_000.0, 2.0) if verified else None,
        top=top,
        confidence=0.3 if verified else 0.01,
        timings_ms={"total": 2.0},
    )


def per_scan(drive: LineDrive, every: int) -> list:
    return run_drive(drive, fake_service, "per-scan", every=every, truth=drive.poses,
                     progress=False)  # fmt: skip


def test_per_scan_rows_csv_and_summary(tmp_path: Path) -> None:
    drive = LineDrive(10)
    rows = per_scan(drive, 2)
    assert [r.scan for r in rows] == [0, 2, 4, 6, 8]
    assert [r.status for r in rows[:3]] == ["ok", "ok", "ok"]
    assert rows[3].status == "refused: only 3 points left after G"
    assert rows[4].status == "no match"
    assert rows[1].error_m == pytest.approx(3.0)
    assert rows[2].error_m == pytest.approx(math.hypot(40.0, 3.0))
    # verified and the pose are the answer's (not its top match's, which has neither)
    assert [r.verified for r in rows] == [True, False, True, None, None]
    assert [r.confidence for r in rows] == [0.3, 0.01, 0.3, None, None]
    assert rows[0].pose_error_m == pytest.approx(0.5)
    assert rows[0].pose_yaw_error_deg == pytest.approx(2.0)
    assert rows[1].pose_northing is None and rows[1].pose_error_m is None
    assert rows[2].pose_error_m == pytest.approx(40.5)
    assert rows[0].kind == "keyframe"
    assert [r.asked for r in rows] == ["search", "search", "search", None, "search"]
    s = summarise(rows, "per-scan")
    assert (s.scans, s.answered, s.within, s.verified, s.beyond_m) == (5, 3, 2, 2, 1)
    assert s.median_place_error_m == pytest.approx(3.0)
    assert s.median_error_m == pytest.approx(np.median([0.5, 40.5]))
    assert s.wrong == 1
    assert s.line() == (
        "replay: 3 of 5 queries answered, 2 within 25 m, 2 verified; median error 3.0 m, 1 "
        "beyond 25 m; verified poses 20.50 m / 2.00 deg off (median), 1 more than 5 m off"
    )

    path = write_rows(rows, tmp_path / "answers.csv", "per-scan")
    with open(path, newline="") as fh:
        table = list(csv.DictReader(fh))
    assert list(table[0])[:21] == ["scan", "timestamp", "time_s", "status", "submap", "run", "kind",
                              "northing", "easting", "distance", "verified", "confidence",
                              "pose_northing", "pose_easting", "pose_yaw_deg", "true_northing",
                              "true_easting", "true_yaw_deg", "error_m", "pose_error_m",
                              "pose_yaw_error_deg"]  # fmt: skip
    assert tuple(table[0]) == COLUMNS["per-scan"] == (*COLUMNS["per-scan"][:21], *POSE_COLUMNS)
    assert table[1]["timestamp"] == "7000000" and table[1]["time_s"] == "2.0"
    assert table[1]["submap"] == "1002" and table[1]["verified"] == "false"
    assert table[0]["verified"] == "true" and float(table[0]["pose_error_m"]) == 0.5
    assert table[1]["pose_northing"] == "" and table[3]["verified"] == ""
    assert float(table[2]["error_m"]) == pytest.approx(math.hypot(40.0, 3.0))
    assert table[3]["northing"] == "" and table[3]["status"].startswith("refused")
    # The summary's figures follow from the CSV alone, and the CSV reads back to the rows.
    errors = sorted(float(r["error_m"]) for r in table if r["error_m"])
    assert s.median_place_error_m == pytest.approx(float(np.median(errors)))
    again = read_rows(path)
    assert [(a.status, a.verified, a.submap) for a in again] == [
        (r.status, r.verified, r.submap) for r in rows
    ]
    assert summarise(again, "per-scan").line() == s.line()


def test_per_scan_without_poses_and_bad_every(tmp_path: Path) -> None:
    rows = per_scan(LineDrive(3, poses=False), 1)
    assert all(r.error_m is None and r.true_northing is None for r in rows)
    s = summarise(rows, "per-scan")
    assert s.median_place_error_m is None and s.beyond_m is None and s.within is None
    assert s.median_error_m is None
    assert (
        s.line()
        == "replay: 3 of 3 queries answered, 1 verified (no poses in the bag: errors unknown)"
    )
    with pytest.raises(InputError, match=">= 1"):
        run_drive(LineDrive(3), fake_service, "per-scan", every=0)
    with pytest.raises(InputError, match="no scans to replay"):
        run_drive(LineDrive(0), fake_service, "per-scan")
    with pytest.raises(InputError, match="policy: must be per-scan or tracked"):
        run_drive(LineDrive(3), fake_service, "sometimes")  # type: ignore[arg-type]


def test_the_per_scan_png(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    drive = LineDrive(10)
    rows = per_scan(drive, 1)
    map_ne = np.c_[5_735_000.0 + 10.0 * np.arange(12), np.full(12, 620_003.0)]
    out = plot_drive(rows, tmp_path / "replay.png", "per-scan", map_ne=map_ne,
                     trajectory_ne=drive.poses[:, [1, 0], 3], title="line")  # fmt: skip
    data = out.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    assert not list(tmp_path.glob("*.tmp"))
    # Without poses: the map panel only.
    rows = per_scan(LineDrive(4, poses=False), 1)
    assert plot_drive(rows, tmp_path / "b.png", "per-scan").stat().st_size > 5_000


# --------------------------------------------------------------------------------------------
# `pnvlad localize --rosbag` against a real server on 127.0.0.1


class FirstScans:
    """The first ``n`` scans of a drive."""

    def __init__(self, drive, n: int) -> None:
        self.drive, self.name = drive, drive.name
        self.timestamps, self.poses = drive.timestamps[:n], drive.poses[:n]

    def __len__(self) -> int:
        return len(self.timestamps)

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(i)


@pytest.fixture(scope="module")
def city(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The tiny synthetic city, a (random) model's bundle of it, and run 0 as a ROS bag."""
    pytest.importorskip("rosbags")
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag
    from pnvlad_service.index import build as ix
    from pnvlad_service.synth.generate import generate, get_preset, simulated_drive
    from tests.index.helpers import make_checkpoint

    base = tmp_path_factory.mktemp("replay")
    generate("tiny", base / "tree", seed=0, workers=1, progress=False)
    ckpt = make_checkpoint(base / "ckpt")
    ix.build_bundle(base / "map.index", ckpt, base / "tree", progress=False)
    drive = simulated_drive(get_preset("tiny"), 0, 0, 0)
    east, north = (float(v) for v in drive.world.origin)
    bag = write_drive_bag(FirstScans(drive, 24), base / "run0.bag", origin_ne=(north, east))
    return {"base": base, "bundle": base / "map.index", "ckpt": ckpt, "bag": bag,
            "origin": f"{north!r},{east!r}", "drive": drive}  # fmt: skip


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def check_summary(line: str, rows: list[dict[str, str]]) -> None:
    """The summary line's figures, recomputed from the CSV."""
    errors = [float(r["error_m"]) for r in rows if r["error_m"]]
    answered = sum(1 for r in rows if r["northing"])
    verified = sum(r["verified"] == "true" for r in rows)
    expected = (
        f"replay: {answered} of {len(rows)} queries answered, "
        f"{sum(e <= 25.0 for e in errors)} within 25 m, {verified} verified; median error "
        f"{float(np.median(errors)):.1f} m, {sum(e > 25.0 for e in errors)} beyond 25 m"
    )
    posed = [float(r["pose_error_m"]) for r in rows if r["verified"] == "true"]
    if posed:
        yaws = [float(r["pose_yaw_error_deg"]) for r in rows if r["verified"] == "true"]
        expected += (
            f"; verified poses {float(np.median(posed)):.2f} m / "
            f"{float(np.median(yaws)):.2f} deg off (median), "
            f"{sum(e > 5.0 for e in posed)} more than 5 m off"
        )
    assert line == expected


def test_replay_a_bag_against_a_real_server(city: dict, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from tests.index.helpers import free_port
    from tests.server.test_app import start_server, stop_server

    port = free_port()
    proc = start_server(city["bundle"], port)
    try:
        out = tmp_path / "replay" / "run0"
        args = ["localize", "--rosbag", str(city["bag"]), "--cloud-topic", "/points",
                "--per-scan", "--pose-topic", "/odom", "--origin", city["origin"], "--every", "5",
                "--url", f"http://127.0.0.1:{port}", "--map", str(city["bundle"]),
                "--out", str(out)]  # fmt: skip
        res = CliRunner().invoke(app, args)
    finally:
        stop_server(proc)
    assert res.exit_code == 0, res.output
    lines = res.stdout.strip().splitlines()
    assert lines[-2] == f"wrote {out}.csv, {out}.png"
    rows = read_csv(Path(f"{out}.csv"))
    drive = city["drive"]
    assert [int(r["scan"]) for r in rows] == [0, 5, 10, 15, 20]
    assert [int(r["timestamp"]) for r in rows] == drive.timestamps[[0, 5, 10, 15, 20]].tolist()
    assert all(r["status"] == "ok" and r["submap"] for r in rows)
    for r in rows:  # the bag's poses, placed back in UTM; errors from the columns
        i = int(r["scan"])
        assert float(r["true_northing"]) == pytest.approx(drive.poses[i, 1, 3], abs=1e-6)
        assert float(r["true_easting"]) == pytest.approx(drive.poses[i, 0, 3], abs=1e-6)
        dn = float(r["northing"]) - float(r["true_northing"])
        de = float(r["easting"]) - float(r["true_easting"])
        assert float(r["error_m"]) == pytest.approx(math.hypot(dn, de))
    check_summary(lines[-1], rows)
    png = Path(f"{out}.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000

    # The same bag searched in this process (--index): the same top-1 answers.
    local = tmp_path / "local"
    args = [a for a in args if a != f"http://127.0.0.1:{port}"]
    args = [*args[: args.index("--url")], *args[args.index("--url") + 1 :]]
    args[args.index(str(out))] = str(local)
    res = CliRunner().invoke(app, [*args, "--index", str(city["bundle"]), "-m", str(city["ckpt"])])
    assert res.exit_code == 0, res.output
    again = read_csv(Path(f"{local}.csv"))
    assert [r["submap"] for r in again] == [r["submap"] for r in rows]
    check_summary(res.stdout.strip().splitlines()[-1], again)


def test_replay_without_poses_and_bad_options(city: dict, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    out = tmp_path / "noposes"
    base = ["localize", "--rosbag", str(city["bag"]), "--index", str(city["bundle"]), "--per-scan"]
    res = CliRunner().invoke(app, [*base, "--cloud-topic", "/points", "--every", "12",
                                   "--out", str(out), "--no-plot"])  # fmt: skip
    assert res.exit_code == 0, res.output
    rows = read_csv(Path(f"{out}.csv"))
    assert len(rows) == 2 and all(r["error_m"] == "" and r["true_northing"] == "" for r in rows)
    assert not Path(f"{out}.png").exists()
    assert res.stdout.strip().splitlines()[-1] == (
        f"replay: 2 of 2 queries answered, {sum(r['verified'] == 'true' for r in rows)} verified "
        "(no poses in the bag: errors unknown)"
    )
    # stderr is not a terminal here: the progress comes as plain lines, the last one 2 of 2.
    bar = [line for line in res.stderr.splitlines() if line.startswith("replay:")]
    assert "\r" not in res.stderr and bar[-1].startswith("replay: 100% 2/2 [")
    res = CliRunner().invoke(app, [*base, "--cloud-topic", "/points", "--every", "12",
                                   "--out", str(out), "--no-plot", "--no-progress"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "replay:" not in res.stderr
    cases = [
        ([*base], "--rosbag needs --cloud-topic"),
        ([*base, "--cloud-topic", "/odom"], "holds nav_msgs/msg/Odometry"),
        ([*base, "--cloud-topic", "/points", "--every", "0"], "--every: must be >= 1"),
        ([*base, "--cloud-topic", "/points", "--preprocess"], "do not go with --rosbag"),
        ([*base, "--cloud-topic", "/points", "--pose-topic", "/nope"], "'/nope' not found"),
        (["localize", "--index", str(city["bundle"]), "--every", "3"], "--every: applies to"),
        (["localize", "--index", str(city["bundle"])], "give a scan file (or --rosbag BAG"),
        (["localize", "--index", str(city["bundle"]), "--out", "x"], "--out: applies to"),
    ]
    for args, message in cases:
        bad = ["--out", str(tmp_path / "bad")] if "--rosbag" in args else []
        res = CliRunner().invoke(app, [*args, *bad])
        assert res.exit_code == 2, (args, res.output)
        errors = [line for line in res.output.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and message in errors[0], (args, res.output)
    assert not list(tmp_path.glob("bad*"))


def test_replay_with_windows_asks_with_the_last_stretch(city: dict, tmp_path: Path) -> None:
    """--per-scan --window 20: every scan goes into the window, each query is the last 20 m
    laid with the bag's poses (kind window): a map of submaps answers them, a map of keyframes
    refuses them (a window is not a single scan), each refusal a row, not the end."""
    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from pnvlad_service.index import build as ix

    base = ["localize", "--rosbag", str(city["bag"]), "--cloud-topic", "/points",
            "--pose-topic", "/odom", "--origin", city["origin"], "--per-scan", "--every", "8",
            "--window", "20", "-m", str(city["ckpt"]), "--no-plot", "--no-progress"]  # fmt: skip
    out = tmp_path / "subs"
    res = CliRunner().invoke(app, [*base, "--index", str(city["bundle"]), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = read_csv(Path(f"{out}.csv"))
    assert [int(r["scan"]) for r in rows] == [0, 8, 16]
    assert all(r["status"] == "ok" and r["kind"] == "submap" for r in rows)
    keys = tmp_path / "keys.index"
    ix.build_bundle(keys, city["ckpt"], city["base"] / "tree", layout="keyframe", progress=False)
    out = tmp_path / "keys"
    res = CliRunner().invoke(app, [*base, "--index", str(keys), "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = read_csv(Path(f"{out}.csv"))
    assert len(rows) == 3 and all(r["status"].startswith("refused") for r in rows)
    assert "keyframe" in rows[0]["status"]
    # A window without poses cannot be laid; --window does not go with following.
    bag = ["localize", "--rosbag", str(city["bag"]), "--cloud-topic", "/points"]
    res = CliRunner().invoke(app, [*bag, "--per-scan", "--window", "20", "--odometry", "none",
                                   "--index", str(keys), "--out", str(tmp_path / "x")])  # fmt: skip
    assert res.exit_code == 2 and "--odometry" in res.output
    res = CliRunner().invoke(app, [*bag, "--pose-topic", "/odom", "--window", "20",
                                   "--index", str(keys), "--out", str(tmp_path / "y")])  # fmt: skip
    assert res.exit_code == 2 and "--window" in res.output
