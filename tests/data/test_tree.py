"""data.tree: layouts, location CSVs, BenchmarkTree, check_tree and `pnvlad data check`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from pnvlad_service.data.tree import (
    LAYOUTS,
    BenchmarkTree,
    check_tree,
    read_locations_csv,
    write_locations_csv,
)
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import SUBMAP_BYTES


def make_run(
    root: Path,
    dataset: str,
    run: str,
    rows: dict[str, list[tuple[int, float, float]]],
    layout: str = "oxford",
) -> Path:
    """Write a run: for each kind, tiny valid .bin files (zeros) and a CSV written by hand."""
    lay = LAYOUTS[layout]
    run_dir = root / dataset / run
    for kind, kind_rows in rows.items():
        folder = run_dir / lay.folder(kind)
        folder.mkdir(parents=True, exist_ok=True)
        lines = ["timestamp,northing,easting"]
        for t, n, e in kind_rows:
            np.zeros((4096, 3), dtype=np.float64).tofile(folder / f"{t}.bin")
            lines.append(f"{t},{n!r},{e!r}")
        (run_dir / lay.csv(kind)).write_text("\n".join(lines) + "\n")
    return run_dir


def good_tree(root: Path) -> Path:
    make_run(
        root,
        "oxford",
        "2014-05-19-13-20-57",
        {
            "train": [
                (30, 5735000.0, 620000.0),
                (10, 5735010.0, 620000.5),
                (20, 5735020.0, 620001),
            ],
            "test": [(15, 5735005.0, 620000.0), (25, 5735025.5, 620002.0)],
        },
    )
    make_run(
        root,
        "oxford",
        "2014-05-14-13-46-12",
        {"train": [(110, 5734990.0, 619999.0)], "test": [(115, 5734995.0, 619998.0)]},
    )
    make_run(
        root,
        "inhouse_datasets",
        "business_run1",
        {"train": [(1, 360000.0, 140000.0)], "test": [(2, 360010.0, 140010.0)]},
        layout="inhouse",
    )
    return root


# ------------------------------------------------------------------ CSV


def test_read_keeps_row_order_and_extra_columns(tmp_path: Path) -> None:
    p = tmp_path / "loc.csv"
    p.write_text("easting,extra,timestamp,northing\n620000.25,x,30,5735000.125\n1.5,y,10,-2\n\n")
    loc = read_locations_csv(p)
    assert loc.timestamp.tolist() == [30, 10]
    assert loc.timestamp.dtype == np.int64
    assert loc.northing.tolist() == [5735000.125, -2.0]
    assert loc.easting.tolist() == [620000.25, 1.5]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("timestamp,northing\n1,2\n", "missing column.*easting"),
        ("time,northing,easting\n1,2,3\n", "missing column.*timestamp"),
        ("timestamp,northing,easting\n1,2,3\n4,abc,6\n", "line 3: northing 'abc'"),
        ("timestamp,northing,easting\n1,2,nan\n", "line 2: easting is 'nan'"),
        ("timestamp,northing,easting\n1,inf,2\n", "line 2: northing is 'inf'"),
        ("timestamp,northing,easting\n1.5,2,3\n", "line 2: timestamp '1.5'"),
        ("timestamp,northing,easting\n1,2\n", "line 2: 2 fields"),
        ("", "empty file"),
    ],
)
def test_read_errors_name_file_and_line(tmp_path: Path, text: str, match: str) -> None:
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as exc:
        read_locations_csv(p)
    assert exc.value.source == str(p)


utm = st.floats(min_value=-1e7, max_value=1e7, allow_nan=False, allow_infinity=False)


@settings(max_examples=40, deadline=None)
@given(rows=st.lists(st.tuples(st.integers(0, 2**62), utm, utm), max_size=20))
def test_write_read_round_trip_is_exact(tmp_path_factory, rows) -> None:
    p = tmp_path_factory.mktemp("csv") / "loc.csv"
    write_locations_csv(p, rows)
    loc = read_locations_csv(p)
    assert loc.rows() == [(t, n, e) for t, n, e in rows]
    # and through the Locations object itself
    write_locations_csv(p, loc)
    assert read_locations_csv(p).rows() == loc.rows()


def test_write_refuses_nan_and_leaves_no_file(tmp_path: Path) -> None:
    p = tmp_path / "loc.csv"
    with pytest.raises(InputError, match="row 1"):
        write_locations_csv(p, [(1, 1.0, 2.0), (2, float("nan"), 3.0)])
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ tree


def test_tree_lists_datasets_runs_and_submaps_in_csv_order(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    (root / ".oxford.tmp123").mkdir()  # an interrupted atomic write: ignored
    (root / "oxford" / "test_regions.json").write_text("{}")  # a file beside runs: ignored
    tree = BenchmarkTree(root)
    assert tree.datasets == ["inhouse_datasets", "oxford"]
    assert tree.runs("oxford") == ["2014-05-14-13-46-12", "2014-05-19-13-20-57"]
    subs = tree.submaps("oxford", "2014-05-19-13-20-57", "train")
    assert [s.timestamp for s in subs] == [30, 10, 20]  # CSV order, not sorted
    assert [s.row for s in subs] == [0, 1, 2]
    assert subs[0].path == "oxford/2014-05-19-13-20-57/pointcloud_20m_10overlap/30.bin"
    assert (subs[0].northing, subs[0].easting, subs[0].kind) == (5735000.0, 620000.0, "train")
    assert (root / subs[0].path).stat().st_size == SUBMAP_BYTES
    test = tree.submaps("oxford", "2014-05-19-13-20-57", "test")
    assert test[1].path == "oxford/2014-05-19-13-20-57/pointcloud_20m/25.bin"
    inh = tree.submaps("inhouse_datasets", "business_run1", "test")
    assert inh[0].path == "inhouse_datasets/business_run1/pointcloud_25m_25/2.bin"
    assert tree.layout("inhouse_datasets", "business_run1").name == "inhouse"


def test_tree_root_must_hold_datasets(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    with pytest.raises(InputError, match="tree root"):
        BenchmarkTree(root / "oxford")
    with pytest.raises(InputError, match="not a directory"):
        BenchmarkTree(root / "missing")
    with pytest.raises(InputError, match="no dataset 'kitti'"):
        BenchmarkTree(root).runs("kitti")


# ------------------------------------------------------------------ check_tree


def test_check_good_tree_counts_and_extent(tmp_path: Path) -> None:
    report = check_tree(good_tree(tmp_path), deep=True)
    assert report.ok, report.problems
    by = {s.name: s for s in report.datasets}
    ox = by["oxford"]
    assert ox.runs == 2
    assert ox.layouts == {"oxford"}
    assert ox.submaps == {"train": 4, "test": 3, "keyframe": 0}
    assert ox.northing == (5734990.0, 5735025.5)
    assert ox.easting == (619998.0, 620002.0)
    assert by["inhouse_datasets"].submaps == {"train": 1, "test": 1, "keyframe": 0}


def _one_problem(root: Path, needle: str, deep: bool = False) -> str:
    report = check_tree(root, deep=deep)
    assert not report.ok
    hits = [str(p) for p in report.problems if needle in str(p)]
    assert hits, [str(p) for p in report.problems]
    return hits[0]


RUN = "oxford/2014-05-19-13-20-57"


def test_check_truncated_and_oversized_bin(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    folder = root / RUN / "pointcloud_20m_10overlap"
    (folder / "10.bin").write_bytes(b"\0" * (SUBMAP_BYTES - 8))
    (folder / "20.bin").write_bytes(b"\0" * (SUBMAP_BYTES + 1))
    report = check_tree(root)
    msgs = {p.path: p.message for p in report.problems}
    assert "truncated: 98296 bytes" in msgs[f"{RUN}/pointcloud_20m_10overlap/10.bin"]
    assert "oversized: 98305 bytes" in msgs[f"{RUN}/pointcloud_20m_10overlap/20.bin"]
    assert len(report.problems) == 2


def test_check_nan_in_csv(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    csv = root / RUN / "pointcloud_locations_20m.csv"
    csv.write_text(csv.read_text().replace("5735025.5", "nan"))
    assert "line 3: northing is 'nan'" in _one_problem(root, "pointcloud_locations_20m.csv")


def test_check_missing_column(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    csv = root / RUN / "pointcloud_locations_20m.csv"
    csv.write_text("timestamp,northing\n15,1\n25,2\n")
    assert "missing column(s) easting" in _one_problem(root, "missing column")


def test_check_rows_without_files_and_files_without_rows(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    folder = root / RUN / "pointcloud_20m"
    (folder / "15.bin").unlink()
    np.zeros((4096, 3)).tofile(folder / "99.bin")
    assert _one_problem(root, "CSV row without").startswith(f"{RUN}/pointcloud_20m/15.bin")
    assert _one_problem(root, "without a row").startswith(f"{RUN}/pointcloud_20m/99.bin")


def test_check_duplicate_timestamps_and_empty_run(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    csv = root / RUN / "pointcloud_locations_20m.csv"
    csv.write_text(csv.read_text() + "15,1.0,2.0\n")
    (root / "oxford" / "2015-empty").mkdir()
    assert "duplicate timestamp 15" in _one_problem(root, "duplicate")
    assert _one_problem(root, "empty run").startswith("oxford/2015-empty")


def test_check_folder_without_csv_and_empty_dataset(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    (root / RUN / "pointcloud_locations_20m.csv").unlink()
    (root / "empty_area").mkdir()
    assert "without pointcloud_locations_20m.csv" in _one_problem(root, "folder without")
    assert _one_problem(root, "empty dataset").startswith("empty_area")


def test_check_lists_ten_of_each_and_counts_the_rest(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    run = root / RUN
    rows = "".join(f"{1000 + k},5735000.0,620000.0\n" for k in range(13))
    (run / "pointcloud_locations_20m.csv").write_text("timestamp,northing,easting\n" + rows)
    for k in range(12):
        np.zeros((4096, 3)).tofile(run / "pointcloud_20m" / f"{5000 + k}.bin")
    report = check_tree(root)
    messages = [(p.path, p.message) for p in report.problems]
    folder = f"{RUN}/pointcloud_20m"
    no_file = [p for p, m in messages if m == "CSV row without a file"]
    assert no_file == [f"{folder}/{1000 + k}.bin" for k in range(10)]
    assert (folder, "3 more rows without file") in messages
    extra = sorted(f"{t}.bin" for t in [15, 25, *range(5000, 5012)])[:10]
    no_row = [p for p, m in messages if m.startswith("file without a row")]
    assert no_row == [f"{folder}/{name}" for name in extra]
    assert (folder, "4 more files without row") in messages
    assert len(messages) == 10 + 1 + 10 + 1


def test_check_csv_without_folder_and_a_root_without_datasets(tmp_path: Path) -> None:
    root = good_tree(tmp_path / "a")
    for f in (root / RUN / "pointcloud_20m").iterdir():
        f.unlink()
    (root / RUN / "pointcloud_20m").rmdir()
    assert _one_problem(root, "CSV without folder") == (
        f"{RUN}/pointcloud_locations_20m.csv: CSV without folder pointcloud_20m"
    )
    (tmp_path / "b").mkdir()
    report = check_tree(tmp_path / "b")
    assert [(p.path, p.message) for p in report.problems] == [
        (str(tmp_path / "b"), "no dataset folders")
    ]


def test_check_deep_reads_values(tmp_path: Path) -> None:
    root = good_tree(tmp_path)
    pts = np.zeros((4096, 3))
    pts[5, 1] = 1.5
    pts.tofile(root / RUN / "pointcloud_20m" / "15.bin")
    assert check_tree(root).ok  # size is right
    assert "outside [-1, 1]" in _one_problem(root, "outside", deep=True)
    pts[5, 1] = np.nan
    pts.tofile(root / RUN / "pointcloud_20m" / "15.bin")
    assert "NaN" in _one_problem(root, "NaN", deep=True)


# ------------------------------------------------------------------ CLI


def test_cli_check(tmp_path: Path) -> None:
    from pnvlad_cli.main import app

    root = good_tree(tmp_path)
    runner = CliRunner()
    res = runner.invoke(app, ["data", "check", str(root)])
    assert res.exit_code == 0, res.output
    assert "oxford" in res.output and "no problems found" in res.output
    assert "N 5734990.0..5735025.5" in res.output
    (root / RUN / "pointcloud_20m" / "15.bin").write_bytes(b"\0" * 100)
    res = runner.invoke(app, ["data", "check", str(root)])
    assert res.exit_code == 1
    assert "truncated: 100 bytes" in res.output
    res = runner.invoke(app, ["data", "check", str(root / "nope")])
    assert res.exit_code == 2
