"""The oxford preset in small (``oxford_tiny``): a push-broom old town over the RobotCar's
coordinates, written in the published Oxford layout, with partial runs; ``pnvlad data splits
--dataset oxford`` scores each run's queries against every other run."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.splits import load_splits
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import read_submap
from pnvlad_service.synth.generate import generate, part_of_route
from pnvlad_service.synth.runs import Route
from tests.benchmark_scripts import load


@pytest.fixture(scope="module")
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("oxford_tiny") / "tree"
    generate("oxford_tiny", root, seed=0, workers=2, progress=False)
    return root


def _ne(path: Path) -> np.ndarray:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    return np.array([[float(r["northing"]), float(r["easting"])] for r in rows])


def _runs(tree: Path) -> list[Path]:
    return sorted(p for p in (tree / "oxford").iterdir() if p.is_dir())


def test_submaps_every_10_and_20_m_along_each_run(tree: Path) -> None:
    for run in _runs(tree):
        for name, step in (
            ("pointcloud_locations_20m_10overlap.csv", 10.0),
            (
                "pointcloud_locations_20m.csv",
                20.0,
            ),
        ):
            ne = _ne(run / name)
            gaps = np.linalg.norm(np.diff(ne, axis=0), axis=1)
            assert len(ne) >= 3 and abs(np.median(gaps) - step) < 1.5
        pts = read_submap(next((run / "pointcloud_20m").iterdir()))
        assert pts.shape == (4096, 3) and np.abs(pts).max() <= 1.0
    summary = json.loads((tree / "synth.json").read_text())
    assert summary["preset"]["pushbroom"]["name"] == "LMS-151"


def test_partial_runs_drive_their_share_of_the_route(tree: Path) -> None:
    summary = json.loads((tree / "synth.json").read_text())
    runs = _runs(tree)
    full = _ne(runs[0] / "pointcloud_locations_20m_10overlap.csv")
    length = np.linalg.norm(np.diff(full, axis=0), axis=1).sum()
    parts = {r["run"]: r.get("part") for r in summary["runs"]}
    assert parts[runs[0].name] is None and all(parts[r.name] for r in runs[1:])
    for run in runs[1:]:
        start, end = parts[run.name]
        ne = _ne(run / "pointcloud_locations_20m_10overlap.csv")
        driven = np.linalg.norm(np.diff(ne, axis=0), axis=1).sum()
        assert abs(driven - (end - start) * length) < 25.0
        # On the first run's path (lane and GNSS/INS error apart), nowhere else.
        near = np.linalg.norm(ne[:, None] - full[None], axis=2).min(1)
        assert near.max() < 9.0


def test_part_of_route_is_the_stretch_asked_for() -> None:
    pts = np.stack([np.arange(101.0), np.zeros(101)], 1)
    route = Route(pts, np.arange(101.0), np.full(101, 3.0))
    part = part_of_route(route, 0.25, 0.6)
    np.testing.assert_array_equal(part.points, pts[25:61])
    assert part.s[0] == 0.0 and part.length == 35.0
    with pytest.raises(InputError, match="empty"):
        part_of_route(route, 0.5, 0.501)


def test_data_splits_scores_each_run_against_every_other(tree: Path, tmp_path: Path) -> None:
    out = tmp_path / "splits.json"
    res = CliRunner().invoke(app, ["data", "splits", str(tree), "--dataset", "oxford", "-o", out])
    assert res.exit_code == 0, res.output
    es = load_splits(out).evaluation["oxford"]
    names = [r.name for r in _runs(tree)]
    assert es.runs == names
    for j in range(len(names)):
        assert sorted(es.truth[j]) == [i for i in range(len(names)) if i != j]
    # The full run's queries find their place in each partial run that passes it.
    assert all(any(len(t) for t in es.truth[0][i]) for i in range(1, len(names)))
    assert json.loads((tree / "oxford" / "test_regions.json").read_text())["half_size"] == 150.0


def test_scale_free_queries_takes_the_evaluation_sets_queries(tree: Path) -> None:
    """benchmarks/scale_free_queries.py --splits: of each run asked, exactly the test submaps
    the splits list as its queries (those inside the published squares), each with its frame."""
    sfq = load("scale_free_queries")
    bt = BenchmarkTree(tree)
    runs = bt.runs("oxford")
    listed = json.loads((tree / "splits.json").read_text())["evaluation"]["oxford"]["queries"]
    by_run = {q["run"]: q["files"] for q in listed}
    every = sfq.select_queries(bt, "oxford", runs[1:], None)
    chosen = sfq.select_queries(bt, "oxford", runs[1:], tree / "splits.json")
    assert len(every) == sum(len(bt.submaps("oxford", r, "test")) for r in runs[1:])
    assert [s.path for s, _ in chosen] == [f for r in runs[1:] for f in by_run.get(r, [])]
    assert 0 < len(chosen) < len(every)
    assert all(f.timestamp == s.timestamp for s, f in chosen)
    with pytest.raises(SystemExit, match="no evaluation set"):
        sfq.select_queries(bt, "elsewhere", runs[1:], tree / "splits.json")
