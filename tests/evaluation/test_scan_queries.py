"""Single raw scans as queries (pnvlad_service.evaluation.scan_queries) on the tiny city: the
queries are the raw scans at the query submaps' places, their ground truth the map entries
within 25 m, their direction the database run's at that place, and `pnvlad eval --queries
scans` reports them."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.scans import read_raw_scans
from pnvlad_service.data.splits import load_splits
from pnvlad_service.errors import InputError
from pnvlad_service.evaluation.scan_queries import (
    preprocess_queries,
    query_frames,
    scan_query_set,
)


def test_queries_are_the_raw_scans_at_the_query_submaps(tiny: Path) -> None:
    submaps = load_splits(tiny / "splits.json")
    keys = load_splits(tiny / "splits_keyframes.json")
    qs = scan_query_set(tiny, keys)
    assert qs.map_kind == "keyframe" and qs.g_config.max_range == 50.0
    (es,) = submaps.evaluation.values()
    (kes,) = keys.evaluation.values()
    for j, run in enumerate(qs.runs):
        # The same places as the benchmark's query submaps: their timestamps name both.
        want = [int(Path(f).stem) for f in es.queries[j].files]
        assert [s.timestamp for s in qs.scans[j]] == want
        np.testing.assert_array_equal(run.query_positions[:, 0], es.queries[j].northing)
        # Truth: every keyframe of every other run within 25 m, by brute force.
        for q, pos in enumerate(run.query_positions):
            for i, db in enumerate(kes.database):
                if i == j:
                    assert i not in run.truth[q]
                    continue
                d = np.hypot(db.northing - pos[0], db.easting - pos[1])
                assert run.truth[q][i].tolist() == np.flatnonzero(d <= 25.0).tolist()
    with pytest.raises(InputError, match="no evaluation set"):
        scan_query_set(tiny, keys, sets=["nowhere"])


def test_directions_follow_the_runs(tiny: Path) -> None:
    """A query is 'opposite' to a database run that drove the route the other way: the runs'
    own directions, from synth.json, agree with the per-query flags (headings at the place)."""
    qs = scan_query_set(tiny, load_splits(tiny / "splits_keyframes.json"))
    reverse = {
        r["run"]: r["reverse"] for r in json.loads((tiny / "synth.json").read_text())["runs"]
    }
    agree = total = 0
    for run, opp in zip(qs.runs, qs.opposite, strict=True):
        for i, flags in opp.items():
            expected = reverse[run.name] != reverse[qs.runs[i].name]
            agree += int((flags == expected).sum())
            total += len(flags)
    assert total > 0 and agree / total > 0.95


def test_preprocessed_queries_and_their_frames(tiny: Path, tmp_path: Path) -> None:
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.io.submap import read_submap

    qs = scan_query_set(tiny, load_splits(tiny / "splits_keyframes.json"))
    runs = preprocess_queries(qs, tmp_path, workers=1, progress=False)
    frames = query_frames(qs, runs)
    scan = qs.scans[0][0]
    path = runs[0].query_paths[0]
    pts = read_submap(path)
    assert pts.shape == (4096, 3) and np.abs(pts).max() <= 1.0
    frame = frames[str(Path(path).resolve())]
    metres = frame.local_m(pts)
    raw = read_points(scan.path, "kitti")
    # G's centre and scale give the points back in the sensor's frame, cropped at 50 m.
    assert np.linalg.norm(metres, axis=1).max() <= 50.5
    near = np.linalg.norm(raw[:, None, :2] - metres[None, ::256, :2], axis=2).min(axis=0)
    assert np.median(near) < 1.0
    # The frame's truth is the scan's true sensor pose.
    np.testing.assert_allclose(frame.true_pose, scan.true_pose, atol=1e-9)


def test_eval_cli_with_scan_queries(tiny_maps: dict, tiny: Path, tmp_path: Path) -> None:
    out = tmp_path / "scans.json"
    base = ["eval", "-m", str(tiny_maps["ckpt"]), "--root", str(tiny), "--no-progress"]
    res = CliRunner().invoke(
        app,
        [
            *base,
            "--splits",
            str(tiny / "splits_keyframes.json"),
            "--queries",
            "scans",
            "-o",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["queries_kind"] == "scan" and rep["map_kind"] == "keyframe"
    assert rep["query_g_config"]["max_range"] == 50.0
    n = sum(len(read_raw_scans(tiny / "business" / r)) for r in rep["runs"])
    assert 0 < rep["n_queries"] < n  # the scans inside the test regions
    same, opp = rep["direction"]["same"], rep["direction"]["opposite"]
    assert same["n_queries_evaluated"] + opp["n_queries_evaluated"] == rep["n_queries_evaluated"]
    # Against the 20 m submaps the same scans go through plain G (the map's own).
    res = CliRunner().invoke(app, [*base, "--splits", str(tiny / "splits.json"),
                                   "--queries", "scans", "-o", str(out)])  # fmt: skip
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    assert rep["map_kind"] == "submap" and rep["query_g_config"]["max_range"] is None


def test_eval_cli_refuses_scan_queries_it_cannot_make(tiny: Path, tmp_path: Path) -> None:
    old = tmp_path / "old"
    shutil.copytree(tiny, old)
    run = sorted(p for p in (old / "business").iterdir() if p.is_dir())[1]
    (run / "raw_scans.csv").unlink()  # a tree made before raw scans
    cases = [
        (["--root", str(old), "--splits", str(old / "splits.json"), "--queries", "scans"],
         "no raw_scans.csv"),
        (["--splits", str(tiny / "splits.json"), "--queries", "scans"], "--root"),
        (["--root", str(tiny), "--queries", "everything"], "--queries"),
    ]  # fmt: skip
    for args, message in cases:
        res = CliRunner().invoke(app, ["eval", "--baseline", *args])
        assert res.exit_code == 2, res.output
        assert message in res.output, res.output


def test_splits_with_a_query_run_ask_with_its_scans_alone(tiny: Path) -> None:
    """`data splits --query-run`: the held-out run's raw scans are the only queries (every one
    of them: no test regions), each with truth in the map runs alone."""
    from pnvlad_service.data import splits as sp

    runs = sorted(p.name for p in (tiny / "business").iterdir() if p.is_dir())
    held = runs[-1]
    qs = scan_query_set(tiny, sp.build_splits(tiny, query_runs=[held], keyframes=True))
    counts = {r.name: len(r.query_paths) for r in qs.runs}
    assert counts[held] == len(read_raw_scans(tiny / "business" / held))
    assert all(n == 0 for r, n in counts.items() if r != held)
    j = [r.name for r in qs.runs].index(held)
    assert all(set(t) == {i for i in range(len(runs)) if i != j} for t in qs.runs[j].truth)
    assert any(len(t[i]) for t in qs.runs[j].truth for i in t)
