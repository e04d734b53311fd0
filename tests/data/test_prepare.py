"""Tests of pnvlad_service.data.prepare (drives -> submaps) and `pnvlad data prepare`.

Drives are built in tmp_path from the real KITTI scans (symlinked, never copied into the repo)
with poses along a straight line, so several submaps are cut (where they are cut:
test_cuts.py).
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.prepare import prepare_drive
from pnvlad_service.data.sources.csv_drive import CsvDrive
from pnvlad_service.data.sources.kitti import KittiSequence
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import SUBMAP_BYTES
from tests.data.helpers import (
    FAST,
    FRAMES,
    STEP_M,
    CountingDrive,
    ListDrive,
    make_kitti_sequence,
    plain_cuts,
    read_csv_rows,
    tree_bytes,
    write_street,
)

# --------------------------------------------------------------------------------------------
# Preparing runs


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory: pytest.TempPathFactory, real_scans: Path):
    """An uninterrupted two-layout run of the synthetic sequence: (sequence, run dir, result)."""
    root = tmp_path_factory.mktemp("prepare_ref")
    seq = make_kitti_sequence(root, real_scans)
    drive = CountingDrive(KittiSequence(seq))
    run = root / "tree" / "oxford" / "2024-01-01-00-00-00"
    result = prepare_drive(drive, run, **FAST)
    return seq, run, result, drive


def test_run_has_benchmark_files(reference_run) -> None:
    seq, run, result, _ = reference_run
    kitti = KittiSequence(seq)
    d = [i * STEP_M for i in range(FRAMES)]
    for folder, csv_name, stride in [
        ("pointcloud_20m_10overlap", "pointcloud_locations_20m_10overlap.csv", 10.0),
        ("pointcloud_20m", "pointcloud_locations_20m.csv", 20.0),
    ]:
        expected = plain_cuts(d, 20.0, stride)
        rows = read_csv_rows(run / csv_name)
        assert [r[0] for r in rows] == [int(kitti.timestamps[c]) for c, _ in expected]
        for (ts, north, east), (c, _) in zip(rows, expected, strict=True):
            assert ts == round(0.1 * c * 1e6)
            assert (north, east) == pytest.approx((0.0, c * STEP_M), abs=1e-6)
        files = sorted((run / folder).iterdir())
        assert sorted(f.name for f in files) == sorted(f"{r[0]}.bin" for r in rows)
        for f in files:
            assert f.stat().st_size == SUBMAP_BYTES
            pts = np.fromfile(f, dtype="<f8").reshape(-1, 3)
            assert np.all(np.abs(pts) <= 1.0)
            assert np.mean(np.linalg.norm(pts - pts.mean(axis=0), axis=1)) == pytest.approx(
                0.5, abs=0.05
            )
    assert [r.submaps for r in result.layouts] == [4, 2]
    assert not list(run.rglob("*.tmp"))


def test_each_scan_is_read_once(reference_run) -> None:
    _, _, result, drive = reference_run
    d = [i * STEP_M for i in range(FRAMES)]
    needed = {i for _, window in plain_cuts(d, 20.0, 10.0) for i in window}
    assert sorted(drive.reads) == sorted(needed)
    assert result.scans_read == len(needed)


def test_a_stop_adds_one_scan_not_all(tmp_path: Path, real_scans: Path) -> None:
    # 10 m driven, 30 scans standing still (with 13 mm of jitter), 20 m more.
    forward = [1.0 * i for i in range(10)]
    forward += [10.0 + 0.013 * (i % 2) for i in range(30)]
    forward += [10.0 + 1.0 * i for i in range(1, 21)]
    seq = make_kitti_sequence(tmp_path, real_scans, forward=forward)
    drive = CountingDrive(KittiSequence(seq))
    prepare_drive(drive, tmp_path / "run", kinds=("test",), **FAST)
    # Reference: plain loop keeping scans at least 0.05 m of travel after the last kept one.
    d = [0.0]
    for a, b in itertools.pairwise(forward):
        d.append(d[-1] + abs(b - a))
    kept, last = [], -math.inf
    for i, value in enumerate(d):
        if value - last >= 0.05:
            kept.append(i)
            last = value
    (_, window), *_ = plain_cuts(d, 20.0, 20.0)
    assert sorted(drive.reads) == sorted(set(window) & set(kept))
    assert len(drive.reads) < len(window) - 15


def test_check_tree_accepts_the_run(reference_run) -> None:
    from pnvlad_service.data.tree import check_tree

    _, run, _, _ = reference_run
    report = check_tree(run.parent.parent)
    assert report.ok, report


def test_single_kind_gives_the_same_bytes(reference_run, tmp_path: Path) -> None:
    seq, run, _, _ = reference_run
    out = tmp_path / "run"
    prepare_drive(KittiSequence(seq), out, kinds=("test",), **FAST)
    ref = {k: v for k, v in tree_bytes(run).items() if k.startswith("pointcloud_20m/")}
    for name in ("pointcloud_locations_20m.csv", "pointcloud_locations_20m.frames.csv"):
        ref[name] = (run / name).read_bytes()
    assert tree_bytes(out) == ref
    # A test submap shares its window (and seed) with the train submap at the same place.
    for name, data in ref.items():
        if name.endswith(".bin"):
            assert data == (run / "pointcloud_20m_10overlap" / Path(name).name).read_bytes()


def test_utm_origin_gives_the_same_bytes(reference_run, tmp_path: Path) -> None:
    seq, _, _, _ = reference_run
    local = prepare_drive(
        KittiSequence(seq, yaw_deg=30.0), tmp_path / "local", kinds=("test",), **FAST
    )
    utm = prepare_drive(
        KittiSequence(seq, origin_ne=(5_735_712.768124, 620_084.402381), yaw_deg=30.0),
        tmp_path / "utm",
        kinds=("test",),
        **FAST,
    )
    a, b = tree_bytes(local.out_run_dir), tree_bytes(utm.out_run_dir)
    bins = [k for k in a if k.endswith(".bin")]
    assert len(bins) == 2 and bins == [k for k in b if k.endswith(".bin")]
    for k in bins:
        assert a[k] == b[k], k
    rows_a = read_csv_rows(tmp_path / "local" / "pointcloud_locations_20m.csv")
    rows_b = read_csv_rows(tmp_path / "utm" / "pointcloud_locations_20m.csv")
    for (ta, na, ea), (tb, nb, eb) in zip(rows_a, rows_b, strict=True):
        assert ta == tb
        assert nb - na == pytest.approx(5_735_712.768124, abs=1e-5)
        assert eb - ea == pytest.approx(620_084.402381, abs=1e-5)
    # Yaw 30 deg: the first test submap (10.5 m travelled) lies along 30 deg from east.
    assert (na, ea) != (0.0, 0.0)
    n0, e0 = rows_a[0][1], rows_a[0][2]
    assert math.degrees(math.atan2(n0, e0)) == pytest.approx(30.0, abs=1e-6)


def test_interrupted_run_leaves_no_partial_output_and_resume_completes(
    reference_run, tmp_path: Path
) -> None:
    seq, run, _, _ = reference_run
    out = tmp_path / "run"
    crashing = CountingDrive(KittiSequence(seq), fail_at=24)
    with pytest.raises(RuntimeError, match="simulated crash"):
        prepare_drive(crashing, out, **FAST)
    left = [p for p in out.rglob("*") if p.is_file() and not p.name.startswith(".prepare-")]
    assert left, "the submaps before the crash should stay on disk"
    assert not [p for p in left if p.suffix != ".bin"], left  # no CSV, no temporary file
    assert all(p.stat().st_size == SUBMAP_BYTES for p in left)
    assert not list(out.rglob("*.tmp"))

    with pytest.raises(FileExistsError, match="--resume"):
        prepare_drive(KittiSequence(seq), out, **FAST)
    with pytest.raises(InputError, match="stride_m"):
        prepare_drive(KittiSequence(seq), out, resume=True, strides_m={"train": 5.0}, **FAST)

    again = CountingDrive(KittiSequence(seq))
    result = prepare_drive(again, out, resume=True, **FAST)
    assert sum(r.resumed for r in result.layouts) == len(left)
    assert sum(r.written for r in result.layouts) == 6 - len(left)
    assert tree_bytes(out) == tree_bytes(run)
    # Windows already written were not read again.
    assert 0 not in again.reads

    # A resume that crashes leaves no CSV behind either (the old one would list a lost file).
    (out / "pointcloud_20m" / "700000.bin").unlink()  # centre scan 7: window of scans 0..13
    with pytest.raises(RuntimeError, match="simulated crash"):
        prepare_drive(CountingDrive(KittiSequence(seq), fail_at=0), out, resume=True, **FAST)
    assert not list(out.glob("*.csv"))


def test_overwrite_starts_again(reference_run, tmp_path: Path) -> None:
    seq, run, _, _ = reference_run
    out = tmp_path / "run"
    prepare_drive(KittiSequence(seq), out, kinds=("test",), strides_m={"test": 10.0}, **FAST)
    assert len(list((out / "pointcloud_20m").iterdir())) == 4
    prepare_drive(KittiSequence(seq), out, kinds=("test",), overwrite=True, **FAST)
    assert sorted(p.name for p in (out / "pointcloud_20m").iterdir()) == sorted(
        p.name for p in (run / "pointcloud_20m").iterdir()
    )


def test_inhouse_layout_crops_to_the_box(reference_run, tmp_path: Path) -> None:
    seq, _, _, _ = reference_run
    result = prepare_drive(KittiSequence(seq), tmp_path / "run", layout="inhouse", **FAST)
    names = sorted(p.name for p in (tmp_path / "run").iterdir() if not p.name.startswith("."))
    assert names == [
        "pointcloud_25m_10",
        "pointcloud_25m_25",
        "pointcloud_centroids_10.csv",
        "pointcloud_centroids_10.frames.csv",
        "pointcloud_centroids_25.csv",
        "pointcloud_centroids_25.frames.csv",
    ]
    # 58.5 m of travel, 25 m windows: train centres 12.5, 22.5, 32.5, 42.5; test 12.5, 37.5.
    assert [r.submaps for r in result.layouts] == [4, 2]


def test_in_memory_drive_in_utm(tmp_path: Path) -> None:
    # A drive heading north-east from a UTM point, street scans identical in the sensor frame.
    rng = np.random.default_rng(5)
    x = rng.uniform(-15, 15, 3000)
    street = np.vstack(
        [
            np.c_[x[:1000], rng.uniform(-8, 8, 1000), np.full(1000, -1.7)],
            np.c_[x[1000:], np.repeat([-8.0, 8.0], 1000), rng.uniform(-1.7, 6, 2000)],
        ]
    )
    t_count = 45
    yaw = math.radians(45)
    poses = np.tile(np.eye(4), (t_count, 1, 1))
    poses[:, :3, :3] = [
        [math.cos(yaw), -math.sin(yaw), 0],
        [math.sin(yaw), math.cos(yaw), 0],
        [0, 0, 1],
    ]
    along = np.arange(t_count) * 0.5
    poses[:, 0, 3] = 620_000.0 + along * math.cos(yaw)
    poses[:, 1, 3] = 5_735_000.0 + along * math.sin(yaw)
    drive = ListDrive([street] * t_count, poses, [10**15 + 50_000 * i for i in range(t_count)])
    result = prepare_drive(drive, tmp_path / "run", progress=False)
    # 22 m travelled (44 steps of 0.5 m): one whole 20 m window, centred at 10 m (scan 20).
    assert [r.submaps for r in result.layouts] == [1, 1]
    rows = read_csv_rows(tmp_path / "run" / "pointcloud_locations_20m.csv")
    assert rows == [
        (
            10**15 + 50_000 * 20,
            pytest.approx(5_735_000.0 + 10 * math.sin(yaw), abs=1e-6),
            pytest.approx(620_000.0 + 10 * math.cos(yaw), abs=1e-6),
        )
    ]


def test_bad_drives_are_refused(tmp_path: Path) -> None:
    class Bad:
        name = "bad"
        timestamps = np.array([5, 5], dtype=np.int64)
        poses = np.tile(np.eye(4), (2, 1, 1))

        def __len__(self) -> int:
            return 2

        def scan(self, i: int) -> np.ndarray:
            return np.zeros((10, 3))

    with pytest.raises(InputError, match="increase strictly"):
        prepare_drive(Bad(), tmp_path / "run", kinds=("train",), progress=False)
    assert not (tmp_path / "run").exists()
    Bad.timestamps = np.array([5, 6], dtype=np.int64)
    with pytest.raises(InputError, match="layout"):
        prepare_drive(Bad(), tmp_path / "run", layout="nope", kinds=("train",), progress=False)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="stride_m"):
        prepare_drive(
            Bad(), tmp_path / "run", kinds=("train",), strides_m={"train": -1.0}, progress=False
        )
    assert not (tmp_path / "run").exists()


# --------------------------------------------------------------------------------------------
# CsvDrive


def test_csv_drive_prepares_a_run(tmp_path: Path) -> None:
    stamps = [2_000_000 + 100_000 * i for i in range(32)]
    write_street(tmp_path / "scans", stamps, np.random.default_rng(2))
    (tmp_path / "poses.csv").write_text(
        "timestamp,northing,easting,heading_deg\n"
        + "".join(f"{t},{5_735_000 + 1.0 * i},620000,0\n" for i, t in enumerate(stamps))
    )
    drive = CsvDrive(tmp_path / "scans", tmp_path / "poses.csv")
    result = prepare_drive(drive, tmp_path / "run", kinds=("train",), progress=False)
    rows = read_csv_rows(tmp_path / "run" / "pointcloud_locations_20m_10overlap.csv")
    # 31 m travelled northwards: centres at 10 and 20 m, scans 10 and 20.
    assert rows == [(3_000_000, 5_735_010.0, 620_000.0), (4_000_000, 5_735_020.0, 620_000.0)]
    assert result.layouts[0].written == 2


# --------------------------------------------------------------------------------------------
# CLI


def test_cli_prepare(reference_run, tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    seq, run, _, _ = reference_run
    runner = CliRunner()
    out = tmp_path / "run"
    args = ["data", "prepare", "--kitti", str(seq), "--out", str(out), "--points-per-scan", "2000"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "pointcloud_20m_10overlap: 4 submaps" in res.output
    assert "pointcloud_20m: 2 submaps" in res.output
    assert tree_bytes(out) == tree_bytes(run)

    res = runner.invoke(app, args)
    assert res.exit_code == 2 and "--resume" in res.output
    res = runner.invoke(app, [*args, "--resume"])
    assert res.exit_code == 0 and "4 kept" in res.output
    res = runner.invoke(app, ["data", "prepare", "--out", str(out)])
    assert res.exit_code == 2 and "--kitti" in res.output
    res = runner.invoke(app, [*args, "--origin", "5735712"])
    assert res.exit_code == 2 and "NORTHING,EASTING" in res.output


def test_cli_prepare_scans_and_g_config(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    stamps = [2_000_000 + 100_000 * i for i in range(32)]
    write_street(tmp_path / "scans", stamps, np.random.default_rng(3))
    poses = tmp_path / "poses.csv"
    poses.write_text(
        "timestamp,northing,easting,yaw_deg\n"
        + "".join(f"{t},5735000,{620_000 + 1.0 * i},0\n" for i, t in enumerate(stamps))
    )
    (tmp_path / "g.yaml").write_text("target_points: 1024\n")
    out = tmp_path / "run"
    base = ["data", "prepare", "--scans", str(tmp_path / "scans"), "--poses", str(poses)]
    res = CliRunner().invoke(
        app, [*base, "--out", str(out), "--kind", "test", "--g-config", str(tmp_path / "g.yaml")]
    )
    assert res.exit_code == 0, res.output
    files = list((out / "pointcloud_20m").iterdir())
    assert [f.name for f in files] == ["3000000.bin"]  # 31 m: one 20 m window, at 10 m
    assert files[0].stat().st_size == 1024 * 24
    assert read_csv_rows(out / "pointcloud_locations_20m.csv") == [(3_000_000, 5735000.0, 620010.0)]

    (tmp_path / "g.yaml").write_text("target_points: -5\n")
    res = CliRunner().invoke(
        app, [*base, "--out", str(tmp_path / "r2"), "--g-config", str(tmp_path / "g.yaml")]
    )
    assert res.exit_code == 2 and "target_points" in res.output
    res = CliRunner().invoke(app, [*base, "--out", str(tmp_path / "r3"), "--origin", "1,2"])
    assert res.exit_code == 2 and "--kitti and --rosbag only" in res.output
    assert not (tmp_path / "r2").exists() and not (tmp_path / "r3").exists()
