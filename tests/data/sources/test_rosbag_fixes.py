"""`pnvlad data prepare --rosbag BAG --fix-topic /fix --odometry kiss-icp`: a bag of clouds and
NavSatFix fixes only (no pose topic, no /tf) prepared into a run whose keyframes lie where the
simulator says, with its fixes kept beside it; what is missing is refused in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rosbags")
pytest.importorskip("kiss_icp")
pytest.importorskip("pyproj")

ZONE = "30U"


@pytest.fixture(scope="module")
def fix_bag(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The first 120 m of a tiny-city run, its scans every 0.5 m as PointCloud2 and its GNSS
    positions once a second as NavSatFix (1.5 m std in the covariance), nothing else."""
    from pnvlad_service.data.sources.rosbag_write import BagWriter, navsatfix, pointcloud2
    from pnvlad_service.io.utm import to_latlon
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    spec = get_preset("tiny").model_copy(update={"scan_spacing": 0.5})
    drive = simulated_drive(spec, 0, 1, 3)
    n = 240
    t = drive.timestamps[:n]
    fixes = np.unique(np.searchsorted(t, np.arange(t[0], t[-1], 1_000_000)))
    lat, lon = to_latlon(ZONE, drive.poses[fixes, 0, 3], drive.poses[fixes, 1, 3])
    path = tmp_path_factory.mktemp("bag") / "fixes.bag"
    with BagWriter(path) as bag:
        for i in range(n):
            ns = int(t[i]) * 1000
            bag.write("/points", pointcloud2(bag.types, drive.scan(i), ns, "lidar"), ns)
            k = np.searchsorted(fixes, i)
            if k < len(fixes) and fixes[k] == i:
                alt = float(drive.poses[i, 2, 3])
                bag.write("/fix", navsatfix(bag.types, lat[k], lon[k], alt, ns, std_m=1.5), ns)
    return {"bag": path, "truth": drive.true_poses[:n], "stamps": t, "fixes": len(fixes)}


def _prepare(*args: str) -> tuple[int, str]:
    from pnvlad_cli.main import app

    res = CliRunner().invoke(app, ["data", "prepare", *args])
    return res.exit_code, res.output


def test_a_bag_of_clouds_and_fixes_prepares_a_run_laid_where_it_is(
    fix_bag: dict, tmp_path: Path
) -> None:
    from pnvlad_service.data.frames import frames_path, read_frames_csv
    from pnvlad_service.data.sources.fixes import read_run_fixes
    from pnvlad_service.data.tree import KEYFRAME_CSV

    out = tmp_path / "city" / "run1"
    code, text = _prepare(
        "--rosbag", str(fix_bag["bag"]), "--cloud-topic", "/points", "--fix-topic", "/fix",
        "--odometry", "kiss-icp", "--utm-zone", ZONE, "--kind", "keyframe", "--out", str(out),
    )  # fmt: skip
    assert code == 0, text
    assert f"KISS-ICP odometry laid onto {fix_bag['fixes']} fixes of /fix" in text
    fixes, _ = read_run_fixes(out)  # type: ignore[misc]
    assert len(fixes) == fix_bag["fixes"] and np.allclose(fixes.std_m, 1.5)
    frames = read_frames_csv(frames_path(out / KEYFRAME_CSV))
    index = {int(s): i for i, s in enumerate(fix_bag["stamps"])}
    truth = np.stack([fix_bag["truth"][index[f.timestamp], :2, 3] for f in frames])
    off = np.linalg.norm(np.stack([f.origin[:2] for f in frames]) - truth, axis=1)
    assert len(frames) >= 20 and np.median(off) < 2.5 and off.max() < 5.0


def test_fixes_without_odometry_or_zone_are_refused_in_one_line(
    fix_bag: dict, tmp_path: Path
) -> None:
    base = ["--rosbag", str(fix_bag["bag"]), "--cloud-topic", "/points", "--fix-topic", "/fix"]
    code, text = _prepare(*base, "--utm-zone", ZONE, "--out", str(tmp_path / "a"))
    assert code == 2 and "--odometry" in text and len(text.strip().splitlines()) == 1
    code, text = _prepare(*base, "--odometry", "kiss-icp", "--out", str(tmp_path / "b"))
    assert code == 2 and "--utm-zone" in text and len(text.strip().splitlines()) == 1
    code, text = _prepare(
        *base, "--odometry", "kiss-icp", "--utm-zone", ZONE, "--pose-topic", "/odom",
        "--out", str(tmp_path / "c"),
    )  # fmt: skip
    assert code == 2 and "not both" in text
    # a fix topic the bag lacks, or one of another type: named, with the NavSatFix topics there
    wrong = {
        "/gps": "'/gps' not found (NavSatFix topics in the bag: /fix)",
        "/points": "'/points' holds sensor_msgs/msg/PointCloud2, not",
    }
    for topic, says in wrong.items():
        args = [*base[:5], topic, "--odometry", "kiss-icp", "--utm-zone", ZONE]
        code, text = _prepare(*args, "--out", str(tmp_path / "d"))
        assert code == 2 and says in text, text
    assert not any((tmp_path / k).exists() for k in "abcd")
