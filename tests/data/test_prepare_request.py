"""data.prepare_request: the kinds, strides and keyframe G a prepare asks for, checked in the
command's order; the request runs prepare_drive as asked; its report lines."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.prepare import LayoutResult, PrepareResult, prepare_drive
from pnvlad_service.data.prepare_request import (
    PrepareRequest,
    keyframe_g,
    kind_strides,
    parse_kinds,
    report_lines,
)
from pnvlad_service.data.sources.csv_drive import CsvDrive
from pnvlad_service.errors import InputError
from pnvlad_service.preprocess.filter_g import SCAN_MAX_RANGE_M, SCAN_PREVOXEL_M, GConfig
from tests.data.helpers import tree_bytes, write_street


@pytest.mark.parametrize(
    ("kind", "kinds"),
    [
        ("both", ("train", "test")),
        ("all", ("train", "test", "keyframe")),
        ("keyframe", ("keyframe",)),
        ("test, train,test", ("test", "train")),
    ],
)
def test_kinds(kind: str, kinds: tuple[str, ...]) -> None:
    assert parse_kinds(kind) == kinds


@pytest.mark.parametrize("kind", ["", "trian", "train,", "both,all"])
def test_unknown_kinds_are_refused(kind: str) -> None:
    with pytest.raises(InputError, match="expected train, test, keyframe") as err:
        parse_kinds(kind)
    assert err.value.source == "--kind"


def test_strides_go_to_the_kinds_they_name() -> None:
    assert kind_strides(("train", "test"), 7.0) == {"train": 7.0}
    assert kind_strides(("test",), 7.0) == {"test": 7.0}
    assert kind_strides(("train", "test", "keyframe"), 7.0, 9.0, 3.0) == {
        "train": 7.0,
        "test": 9.0,
        "keyframe": 3.0,
    }
    assert kind_strides(("keyframe",), 7.0) == {}
    with pytest.raises(InputError, match="--test-stride goes with --kind both"):
        kind_strides(("test",), None, 9.0)
    with pytest.raises(InputError, match="goes with --kind keyframe") as err:
        kind_strides(("train", "test"), None, None, 3.0)
    assert err.value.source == "--keyframe-stride"


def test_keyframe_g_is_the_scan_g_of_the_config_with_its_range() -> None:
    base = GConfig(ground_threshold=0.4)
    default = keyframe_g(None, ("keyframe",))
    assert (default.max_range, default.prevoxel) == (SCAN_MAX_RANGE_M, SCAN_PREVOXEL_M)
    cut = keyframe_g(base, ("keyframe",), 30.0)
    assert (cut.max_range, cut.ground_threshold) == (30.0, 0.4)
    with pytest.raises(InputError, match="positive number of metres"):
        keyframe_g(None, ("keyframe",), -1.0)
    with pytest.raises(InputError, match="goes with --kind keyframe") as err:
        keyframe_g(None, ("test",), 30.0)
    assert err.value.source == "--scan-range"


def test_checked_refuses_in_the_command_order(tmp_path: Path) -> None:
    g = tmp_path / "g.yaml"
    g.write_text("ground_threshold: 0.4\n")
    with pytest.raises(InputError, match="expected train"):  # --kind before --out
        PrepareRequest.checked(None, kind="none")
    with pytest.raises(InputError, match="missing: the run folder"):
        PrepareRequest.checked(None, kind="test", resume=True, overwrite=True)
    with pytest.raises(InputError, match="exclude each other"):
        PrepareRequest.checked(tmp_path, resume=True, overwrite=True)
    req = PrepareRequest.checked(
        tmp_path, kind="all", stride=5.0, scan_range=40.0, g_config=g, seed=3, window_m=15.0
    )
    assert req.kinds == ("train", "test", "keyframe")
    assert req.strides_m == {"train": 5.0}
    assert req.g_config == GConfig(ground_threshold=0.4)
    assert (req.keyframe_config.max_range, req.keyframe_config.ground_threshold) == (40.0, 0.4)
    assert (req.seed, req.window_m, req.out) == (3, 15.0, tmp_path)


def test_a_request_writes_what_prepare_drive_writes(tmp_path: Path) -> None:
    stamps = [1_600_000_000_000_000 + 100_000 * i for i in range(30)]
    write_street(tmp_path / "scans", stamps, np.random.default_rng(5))
    rows = ["timestamp,northing,easting,yaw_deg"]
    rows += [f"{t},{5735712.0 + 1.5 * i},620084.0,90" for i, t in enumerate(stamps)]
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    drive = CsvDrive(tmp_path / "scans", tmp_path / "poses.csv")
    req = PrepareRequest.checked(
        tmp_path / "a", kind="test", stride=8.0, max_points_per_scan=500, seed=2
    )
    got = req.run(drive, progress=False)
    want = prepare_drive(
        drive,
        tmp_path / "b",
        kinds=("test",),
        strides_m={"test": 8.0},
        max_points_per_scan=500,
        seed=2,
        progress=False,
    )
    assert [r.written for r in got.layouts] == [r.written for r in want.layouts] != [0]
    assert tree_bytes(tmp_path / "a") == tree_bytes(tmp_path / "b")


def test_report_lines() -> None:
    result = PrepareResult(
        Path("run"),
        [
            LayoutResult("train", Path("run/f1"), Path("run/a.csv"), 10, 8, 2, 0),
            LayoutResult("keyframe", Path("run/f2"), Path("run/b.csv"), 5, 3, 0, 1),
        ],
        scans_read=40,
        seconds=4.0,
    )
    assert report_lines(result, 50) == [
        "train    run/f1: 10 submaps (8 written, 2 kept), locations in a.csv",
        "keyframe run/f2: 4 submaps (3 written, 1 failed (see log)), locations in b.csv",
        "50 scans (40 read) in 4.0 s, 2.75 submaps/s",
    ]
