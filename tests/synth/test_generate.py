"""synth.generate: the tree it writes is a valid benchmark, the same for the same seed."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.splits import load_splits
from pnvlad_service.data.tree import BenchmarkTree, check_tree
from pnvlad_service.errors import InputError
from pnvlad_service.synth.generate import choose_test_regions, generate, get_preset
from pnvlad_service.synth.runs import make_route


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_tiny_tree_is_a_valid_benchmark_with_truth_in_every_run_pair(tiny: Path) -> None:
    report = check_tree(tiny)
    assert report.ok, report.problems
    splits = load_splits(tiny / "splits.json")
    (es,) = splits.evaluation.values()
    runs = len(es.runs)
    assert runs == get_preset("tiny").runs
    for j in range(runs):
        for i in range(runs):
            if i == j:
                continue
            # Some query of run j has a true match in run i: every ordered pair is scored.
            assert any(len(t) > 0 for t in es.truth[j][i]), (i, j)
    (tuples,) = splits.training.values()
    assert len(tuples.anchors(2)) > 10
    for sub in tiny.rglob("pointcloud_*/*.bin"):
        assert sub.stat().st_size == 98_304


def test_tiny_tree_keeps_a_raw_scan_at_every_test_submap_and_a_keyframe_map(tiny: Path) -> None:
    from pnvlad_service.data.scans import read_raw_scans
    from pnvlad_service.io.readers import read_points

    tree = BenchmarkTree(tiny)
    for run in tree.runs("business"):
        test = tree.locations("business", run, "test")
        scans = read_raw_scans(tiny / "business" / run)
        # One raw scan a test submap, named by its timestamp and at its recorded position.
        assert [s.timestamp for s in scans] == test.timestamp.tolist()
        assert [s.northing for s in scans] == test.northing.tolist()
        assert [s.easting for s in scans] == test.easting.tolist()
        for s in scans[:3]:
            pts = read_points(s.path, "kitti")
            # Raw: the sensor frame (within the sensor's range of its origin), not G's [-1, 1].
            assert len(pts) > 4096 and np.abs(pts).max() > 5.0
            assert np.linalg.norm(pts, axis=1).max() <= get_preset("tiny").lidar.max_range + 1
            assert s.true_pose is not None and s.true_pose[2, 2] == pytest.approx(1.0)
        keys = tree.locations("business", run, "keyframe")
        # A keyframe every 5 m of the drive: far more than the 20 m test submaps.
        steps = np.hypot(np.diff(keys.northing), np.diff(keys.easting))
        assert len(keys) > 3 * len(test) and np.median(steps) == pytest.approx(5.0, abs=1.0)
    splits = load_splits(tiny / "splits_keyframes.json")
    assert splits.params["kind"] == "keyframe"
    (es,) = splits.evaluation.values()
    assert all("/pointcloud_keyframes/" in f for db in es.database for f in db.files)


def test_same_seed_same_bytes(tiny: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    generate("tiny", again, seed=3, workers=1, progress=False)  # other worker count too
    assert _tree_digest(again) == _tree_digest(tiny)


def test_test_regions_cover_about_the_share_asked() -> None:
    t = np.linspace(0, 1, 2001)
    route = np.c_[t * 2000.0, 100 * np.sin(t * 8)]  # a 2 km wiggly street
    centres = choose_test_regions(route, 0.3, 150.0)
    inside = np.zeros(len(route), bool)
    for cx, cy in centres:
        inside |= (np.abs(route[:, 0] - cx) < 150) & (np.abs(route[:, 1] - cy) < 150)
    assert 0.25 <= inside.mean() <= 0.5
    for i, a in enumerate(centres):  # squares do not overlap
        for b in centres[i + 1 :]:
            assert max(abs(a[0] - b[0]), abs(a[1] - b[1])) >= 300.0


def test_cli_synth_refuses_an_existing_tree_and_an_unknown_preset(
    tiny: Path, tmp_path: Path
) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["synth", "--preset", "tiny", "--out", str(tiny), "--no-progress"])
    assert res.exit_code == 2 and "exists" in res.output
    res = runner.invoke(app, ["synth", "--preset", "nope", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "tiny" in res.output


def test_cli_refresh_truth_leaves_a_current_tree_as_it_is_and_names_a_bad_one(
    tiny: Path, tmp_path: Path
) -> None:
    import shutil

    copy = tmp_path / "t"
    shutil.copytree(tiny, copy)
    sides = sorted(copy.rglob("*.frames.csv"))
    before = [p.read_bytes() for p in sides]
    res = CliRunner().invoke(app, ["synth", "--refresh-truth", "--out", str(copy), "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "refreshed the true poses and keyframes' motion of" in res.output
    assert [p.read_bytes() for p in sides] == before  # made by this version: nothing changes
    (tmp_path / "plain").mkdir()
    res = CliRunner().invoke(app, ["synth", "--refresh-truth", "--out", str(tmp_path / "plain")])
    assert res.exit_code == 2 and "synth.json" in res.output


def test_eval_scores_every_area_of_a_multi_area_tree(tiny: Path, tmp_path: Path) -> None:
    """Two identical areas must score identically: ground truth of the second set must point
    at its own runs, not at the first set's (a bug once scored only the first area)."""
    import json
    import shutil

    from pnvlad_service.data.splits import build_splits, save_splits

    root = tmp_path / "two"
    shutil.copytree(tiny / "business", root / "business")
    shutil.copytree(tiny / "business", root / "twin")
    save_splits(root / "splits.json", build_splits(root))
    out = tmp_path / "rep.json"
    args = ["-q", "eval", "--baseline", "--root", str(root)]
    args += ["--splits", str(root / "splits.json"), "-o", str(out), "--no-progress"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    a, b = rep["per_area"]["business"], rep["per_area"]["twin"]
    assert a["n_pairs"] == b["n_pairs"] == 6 and not a["skipped_pairs"] and not b["skipped_pairs"]
    assert a["recall_at_n"] == b["recall_at_n"]
    assert rep["recall_at_1"] == a["recall_at_1"]


def test_runs_follow_trajectories_a_user_supplies(tmp_path: Path) -> None:
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.synth.generate import _world

    spec = get_preset("tiny")
    area = spec.areas[0]
    world = _world(area, 0)
    # A route of our own: an L along the first street, given in UTM as a user would.
    pts = make_route(world, 200.0, seed=42).points[::5] + world.origin
    tdir = tmp_path / "traj"
    tdir.mkdir()
    for k in range(spec.runs):
        rows = ["timestamp,northing,easting"]
        rows += [f"{i},{n:.3f},{e:.3f}" for i, (e, n) in enumerate(pts)]
        (tdir / f"{k}.csv").write_text("\n".join(rows) + "\n")
    root = tmp_path / "tree"
    generate(spec, root, seed=0, workers=1, trajectories=tdir, progress=False)
    tree = BenchmarkTree(root)
    for run in tree.runs(area.name):
        subs = tree.submaps(area.name, run, "train")
        assert subs
        xy = np.array([[s.easting, s.northing] for s in subs])
        # Every submap sits on the supplied path (lane offset + pose drift: a few metres).
        d = np.min(np.linalg.norm(xy[:, None, :] - pts[None, :, :], axis=2), axis=1)
        assert d.max() < 8.0, d.max()
    bad = tmp_path / "bad"
    bad.mkdir()

    with pytest.raises(InputError, match=r"no trajectory business_0\.csv"):
        generate(spec, tmp_path / "t2", seed=0, workers=1, trajectories=bad, progress=False)
    for k in range(spec.runs):
        (bad / f"{k}.csv").write_text("timestamp,x,y\n0,1,2\n")
    with pytest.raises(InputError, match="columns northing,easting"):
        generate(spec, tmp_path / "t3", seed=0, workers=1, trajectories=bad, progress=False)
    assert not (tmp_path / "t2").exists() and not (tmp_path / "t3").exists()
