"""benchmarks/replay_benchmark.py's protocols: the strict one (a held-out run's map aligned from
its area's other recorded runs only, benchmarks/leave_one_out.py) and the drives that leave the
map or are kidnapped, named apart so that no figure is read from another drive's files."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
RUNS = ["2026-01-01-00-00-00", "2026-01-02-00-00-00", "2026-01-03-00-00-00"]


def _benchmark(name: str):
    """The script benchmarks/NAME.py imported as a module (its siblings importable meanwhile)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(BENCHMARKS))


@pytest.fixture(scope="module")
def loo():
    return _benchmark("leave_one_out")


@pytest.fixture(scope="module")
def rb():
    return _benchmark("replay_benchmark")


def recorded_tree(root: Path) -> Path:
    """A tree of one area, three runs each with one file, its synth.json and splits."""
    for run in RUNS:
        (root / "city" / run).mkdir(parents=True)
        (root / "city" / run / "raw_scans.csv").write_text(f"{run}\n")
    (root / "city" / "test_regions.json").write_text("[]")
    (root / "synth.json").write_text("{}")
    (root / "splits_keyframes.json").write_text("{}")
    return root


def snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): p.read_text() for p in root.rglob("*") if p.is_file()}


def test_the_map_of_a_held_out_run_is_aligned_without_it(loo, tmp_path: Path) -> None:
    root = recorded_tree(tmp_path / "rec")
    before = snapshot(root)
    calls: list[list[str]] = []

    def invoke(args: list[str], what: str) -> None:
        calls.append(args)
        links, out = Path(args[2]), Path(args[4])
        # What `pnvlad map align` reads: the other runs, through links, and nothing else.
        assert sorted(p.name for p in (links / "city").iterdir() if p.is_dir()) == [
            RUNS[0],
            RUNS[2],
        ]
        assert all((links / "city" / r).is_symlink() for r in (RUNS[0], RUNS[2]))
        assert (links / "city" / RUNS[0] / "raw_scans.csv").read_text() == f"{RUNS[0]}\n"
        assert (links / "synth.json").is_file() and (links / "city/test_regions.json").is_file()
        out.mkdir(parents=True)
        (out / "align_report.json").write_text("{}")

    tree, seconds = loo.aligned_without(root, tmp_path / "work", "city", RUNS[1], invoke)
    assert calls and calls[0][:2] == ["map", "align"] and "--overwrite" in calls[0]
    assert tree == tmp_path / "work" / "aligned" / "city" / RUNS[1]
    assert seconds is not None and seconds >= 0
    # A whole aligned tree is reused, not aligned again; the recorded tree is as it was.
    again, seconds = loo.aligned_without(root, tmp_path / "work", "city", RUNS[1], invoke)
    assert again == tree and seconds is None and len(calls) == 1
    assert snapshot(root) == before


def test_a_half_made_link_tree_is_made_again_and_a_bad_run_refused(loo, tmp_path: Path) -> None:
    root = recorded_tree(tmp_path / "rec")
    dest = tmp_path / "links"
    (dest / "city" / RUNS[1]).mkdir(parents=True)  # a run that must not be there
    loo.linked_tree(root, dest, "city", [RUNS[0]])
    assert [p.name for p in (dest / "city").iterdir() if p.is_dir()] == [RUNS[0]]
    with pytest.raises(SystemExit, match="not a run"):
        loo.aligned_without(root, tmp_path / "w", "city", "2026-09-09-00-00-00", print)


def test_each_drive_has_its_own_bag_and_replay_name(rb) -> None:
    names = {
        rb.drive_name(1, None, None),
        rb.drive_name(2, None, None),
        rb.drive_name(1, (400.0, 300.0), None),
        rb.drive_name(1, (400.0, 200.0), None),
        rb.drive_name(1, None, "60:60"),
        rb.drive_name(1, (400.0, 300.0), "60:60"),
    }
    assert len(names) == 6
    assert all("/" not in n and ":" not in n for n in names)


def test_every_nth_keeps_the_truth_with_its_scans(rb) -> None:
    class Drive:
        name = "d"
        timestamps = np.arange(10, dtype=np.int64) * 100
        poses = np.tile(np.eye(4), (10, 1, 1))
        true_poses = np.tile(np.eye(4), (10, 1, 1))
        true_poses[:, 0, 3] = np.arange(10)

        def __len__(self) -> int:
            return 10

        def scan(self, i: int) -> np.ndarray:
            return np.full((2, 3), i, dtype=np.float32)

    sub = rb.EveryNth(Drive(), 3)
    assert len(sub) == 4 and list(sub.true[:, 0, 3]) == [0, 3, 6, 9]
    assert sub.scan(2)[0, 0] == 6


def test_the_help_names_no_issue_numbers(rb) -> None:
    import re

    text = rb.parser().format_help()
    assert "--per-scan" in text and "--aligned-map" in text
    assert not re.search(r"#\d", text), text
