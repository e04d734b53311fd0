"""Splits of a map of one's own drives: training tuples from every place of the map runs and
no query run, each query run evaluated against the map alone; checked against plain loops over
hand-placed entries."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data import splits as sp
from tests.data.splits.helpers import CE, CN, brute_within, make_run

# Keyframes along the easting axis, 5 m apart with some gaps; positions exact in float64.
OFFSETS = {
    "r1": [0.0, 5.0, 10.0, 15.0, 60.0, 65.0, 200.0],
    "r2": [2.5, 7.5, 12.5, 62.5, 120.0],
    "r3": [1.0, 6.0, 64.0, 300.0],  # the query drive
}


def _campus(root: Path) -> Path:
    for k, (run, offs) in enumerate(OFFSETS.items()):
        rows = [(1000 * k + 10 * i + 10, CN, CE + x) for i, x in enumerate(offs)]
        make_run(root, "campus", run, {"keyframe": rows})
    return root


def _points(runs: list[str]) -> list[tuple[float, float]]:
    return [(CN, CE + x) for r in runs for x in OFFSETS[r]]


def test_map_runs_train_and_query_runs_are_evaluated_against_them(tmp_path: Path) -> None:
    root = _campus(tmp_path)
    s = sp.build_splits(root, query_runs=["r3"], keyframes=True)
    t = s.training["campus"]
    # Every place of r1 and r2 (no test regions), none of r3.
    assert [f.split("/")[1] for f in t.files] == ["r1"] * 7 + ["r2"] * 5
    ref = _points(["r1", "r2"])
    for i, q in enumerate(ref):
        assert t.positives[i].tolist() == [j for j in brute_within(ref, q, 10.0) if j != i]
        assert t.near[i].tolist() == brute_within(ref, q, 50.0)
    es = s.evaluation["campus"]
    assert es.runs == ["r1", "r2", "r3"]
    assert [len(q) for q in es.queries] == [0, 0, 4]  # every r3 entry a query, no map run's
    for i, run in enumerate(["r1", "r2"]):
        got = [x.tolist() for x in es.truth[2][i]]
        assert got == [brute_within(_points([run]), q, 25.0) for q in _points(["r3"])]
    assert es.truth[0] == {1: [], 2: []} and es.truth[1] == {0: [], 2: []}
    assert s.params["query_runs"] == ["r3"] and s.params["kind"] == "keyframe"


def test_two_query_runs_are_never_each_others_map(tmp_path: Path) -> None:
    root = _campus(tmp_path)
    s = sp.build_splits(root, query_runs=["r2", "r3"], keyframes=True)
    assert {f.split("/")[1] for f in s.training["campus"].files} == {"r1"}
    es = s.evaluation["campus"]
    assert all(len(x) == 0 for x in es.truth[1][2]) and all(len(x) == 0 for x in es.truth[2][1])
    assert any(len(x) for x in es.truth[2][0])


def test_cli_writes_the_keyframe_splits_and_refuses_bad_runs(tmp_path: Path) -> None:
    root = _campus(tmp_path)
    runner = CliRunner()
    res = runner.invoke(app, ["data", "splits", str(root), "--kind", "keyframe",
                              "--query-run", "r3"])  # fmt: skip
    assert res.exit_code == 0, res.output
    loaded = sp.load_splits(root / "splits_keyframes.json")
    built = sp.build_splits(root, query_runs=["r3"], keyframes=True)
    assert loaded.training["campus"].files == built.training["campus"].files
    assert [len(q) for q in loaded.evaluation["campus"].queries] == [0, 0, 4]
    for args, message in [
        (["--query-run", "r9"], "--query-run: no run 'r9'"),
        (["--query-run", "r1", "--query-run", "r2", "--query-run", "r3"], "needs at least one"),
        (["--kind", "scan", "--query-run", "r3"], "--kind: expected submap or keyframe"),
    ]:
        out = tmp_path / "x.json"
        res = runner.invoke(app, ["data", "splits", str(root), "-o", str(out), *args])
        assert res.exit_code == 2 and message in res.output, res.output
        assert not out.exists()
