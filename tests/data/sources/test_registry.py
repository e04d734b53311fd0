"""data.sources.registry: each source opened by name gives the drive its own class gives, the
options a source cannot use are refused naming the option, and a new source is one call."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.sources import registry
from pnvlad_service.data.sources.csv_drive import CsvDrive
from pnvlad_service.data.sources.kitti import KittiSequence
from pnvlad_service.data.sources.registry import (
    FLAGS,
    SOURCES,
    DriveOptions,
    DriveSource,
    chosen,
    close_drive,
    open_drive,
    register,
)
from pnvlad_service.errors import InputError
from tests.data.helpers import ListDrive, write_street

STAMPS = [1_600_000_000_000_000 + 100_000 * i for i in range(6)]


def _kitti(root: Path) -> Path:
    """A six-scan KITTI folder: random clouds, the camera 1.5 m further along z each scan."""
    rng = np.random.default_rng(3)
    (root / "velodyne").mkdir(parents=True)
    for i in range(6):
        rng.normal(0, 5, (200, 4)).astype(np.float32).tofile(root / "velodyne" / f"{i:06d}.bin")
    rows = [f"1 0 0 0 0 1 0 0 0 0 1 {1.5 * i}" for i in range(6)]
    (root / "poses.txt").write_text("\n".join(rows) + "\n")
    return root


def _csv(root: Path) -> tuple[Path, Path]:
    """A six-scan street as .npy files with a planar pose CSV (1 m north a scan, facing north)."""
    write_street(root / "scans", STAMPS, np.random.default_rng(4))
    rows = ["timestamp,northing,easting,yaw_deg"]
    rows += [f"{t},{5735712.0 + i},{620084.0},90" for i, t in enumerate(STAMPS)]
    (root / "poses.csv").write_text("\n".join(rows) + "\n")
    return root / "scans", root / "poses.csv"


def test_the_sources_are_registered_in_the_order_offered() -> None:
    assert list(SOURCES) == ["kitti", "csv", "rosbag", "rosbag-clouds"]
    assert [s.flag for s in SOURCES.values()] == ["--kitti", "--scans", "--rosbag", "--rosbag"]
    for source in SOURCES.values():
        assert set(source.own) <= set(source.reads) <= set(FLAGS)


def test_kitti_by_name_is_the_kitti_sequence(tmp_path: Path) -> None:
    seq = _kitti(tmp_path / "00")
    origin = (5735712.8, 620084.4)
    drive = open_drive("kitti", seq, DriveOptions(origin_ne=origin, yaw_deg=30.0))
    direct = KittiSequence(seq, origin_ne=origin, yaw_deg=30.0)
    assert isinstance(drive, KittiSequence)
    np.testing.assert_array_equal(drive.poses, direct.poses)
    np.testing.assert_array_equal(drive.timestamps, direct.timestamps)
    np.testing.assert_array_equal(drive.scan(4), direct.scan(4))
    assert SOURCES["kitti"].notes(DriveOptions(origin_ne=origin)) == []
    assert "no --origin" in SOURCES["kitti"].notes(DriveOptions())[0]


def test_csv_by_name_is_the_csv_drive(tmp_path: Path) -> None:
    scans, poses = _csv(tmp_path)
    drive = open_drive("csv", scans, DriveOptions(poses=poses))
    direct = CsvDrive(scans, poses)
    np.testing.assert_array_equal(drive.poses, direct.poses)
    np.testing.assert_array_equal(drive.timestamps, STAMPS)
    assert drive.poses[3, 1, 3] == pytest.approx(5735715.0)  # northing is y
    assert SOURCES["csv"].report(drive) is None


def test_a_bag_written_from_a_drive_opens_by_name_with_its_poses(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from pnvlad_service.data.sources.rosbag_write import write_drive_bag

    scans, poses = _csv(tmp_path)
    drive = CsvDrive(scans, poses)
    origin = (5735700.0, 620080.0)
    bag = write_drive_bag(drive, tmp_path / "drive.bag", origin_ne=origin, tf_topic="/tf")
    for topics in (DriveOptions(pose_topic="/odom"), DriveOptions(tf_frame="odom")):
        options = DriveOptions(
            cloud_topic="/points",
            pose_topic=topics.pose_topic,
            tf_frame=topics.tf_frame,
            origin_ne=origin,
            max_pose_gap=0.0,  # 0: interpolate across any gap
        )
        read = open_drive("rosbag", bag, options)
        try:
            np.testing.assert_allclose(read.poses, drive.poses, atol=1e-6)
            np.testing.assert_array_equal(read.timestamps, STAMPS)
            line = SOURCES["rosbag"].report(read)
            assert line.startswith("drive.bag: 6 of 6 clouds on /points used; poses from ")
        finally:
            close_drive(read)
    # The same bag's clouds alone (no poses): the scans and their times, for a drive asked scan
    # by scan; the cloud topic is the bag source's own option, read by this one too.
    clouds = open_drive("rosbag-clouds", bag, DriveOptions(cloud_topic="/points"))
    try:
        assert not hasattr(clouds, "poses")
        np.testing.assert_array_equal(clouds.timestamps, STAMPS)
        np.testing.assert_allclose(clouds.scan(2), drive.scan(2), atol=1e-6)
    finally:
        close_drive(clouds)
    with pytest.raises(InputError, match="needs --cloud-topic") as err:
        open_drive("rosbag-clouds", bag, DriveOptions())
    assert err.value.source == "--cloud-topic"


@pytest.mark.parametrize(
    ("name", "options", "field", "message"),
    [
        ("kitti", DriveOptions(reader="npy"), "--kitti", "apply to --scans only"),
        ("kitti", DriveOptions(cloud_topic="/p"), "--cloud-topic", "applies to --rosbag only"),
        ("kitti", DriveOptions(tf_frame="odom"), "--tf", "applies to --rosbag only"),
        ("csv", DriveOptions(max_pose_gap=3.0), "--max-pose-gap", "applies to --rosbag only"),
        ("csv", DriveOptions(), "--poses", "--scans needs --poses CSV"),
        ("csv", DriveOptions(poses=Path("p.csv"), yaw_deg=5.0), "--origin", "apply to --kitti"),
        ("rosbag", DriveOptions(poses=Path("p.csv")), "--rosbag", "do not apply to --rosbag"),
        ("rosbag", DriveOptions(pose_topic="/odom"), "--cloud-topic", "needs --cloud-topic"),
        ("rosbag", DriveOptions(cloud_topic="/p"), "--pose-topic", "needs --pose-topic"),
        ("rosbag", DriveOptions(cloud_topic="/p", pose_topic="/o", tf_frame="f"), "--tf", "both"),
        ("gps", DriveOptions(), "source", "unknown drive source 'gps'"),
    ],
)
def test_options_a_source_cannot_use_are_refused_by_name(
    tmp_path: Path, name: str, options: DriveOptions, field: str, message: str
) -> None:
    with pytest.raises(InputError, match=message) as err:
        open_drive(name, tmp_path, options)
    assert err.value.source == field


def test_one_source_must_be_chosen() -> None:
    paths = {"kitti": None, "csv": Path("scans"), "rosbag": None}
    source, path = chosen(paths)
    assert (source.name, path) == ("csv", Path("scans"))
    for wrong in ({**paths, "csv": None}, {**paths, "kitti": Path("seq")}):
        with pytest.raises(InputError) as err:
            chosen(wrong)
        assert str(err.value) == (
            "--kitti: give one of --kitti SEQ_DIR, --scans DIR --poses CSV or --rosbag BAG"
        )


def test_a_new_source_is_one_register_call(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "SOURCES", dict(SOURCES))
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    memory = ListDrive([np.zeros((5, 3))] * 3, poses, [1, 2, 3])
    register(
        DriveSource(
            name="memory",
            flag="--memory",
            usage="--memory NAME",
            summary="a drive held in memory",
            reads=("origin_ne",),
            opener=lambda path, options: memory,
        )
    )
    source, path = chosen({"memory": Path("m"), "kitti": None})
    assert source.open(path) is memory
    assert open_drive("memory", "m") is memory
    with pytest.raises(InputError, match="applies to --rosbag only"):
        open_drive("memory", "m", DriveOptions(pose_topic="/odom"))
    with pytest.raises(ValueError, match="registered already"):
        register(registry.SOURCES["memory"])
    with pytest.raises(ValueError, match="lacks"):
        register(DriveSource("gnss", "--gnss", "--gnss F", "", ("speed",), lambda p, o: memory))


def test_every_option_is_a_flag_of_data_prepare() -> None:
    import typer

    from pnvlad_cli.data_prepare import prepare

    app = typer.Typer()
    app.command()(prepare)
    flags = {o for p in typer.main.get_command(app).params for o in p.opts}
    assert set(FLAGS.values()) <= flags
    assert {s.flag for s in SOURCES.values()} <= flags
