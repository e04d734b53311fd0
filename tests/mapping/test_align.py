"""pnvlad map align on the tiny city: the command end to end, the aligned tree (its layout, its
re-laid metres, an index built from it, its accuracy against the simulator's truth), the
report and plot, and the recorded tree left byte for byte as it was."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("gtsam")


def tree_digest(root: Path) -> dict[str, str]:
    """Every file under ``root`` -> its sha256."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def aligned(tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    from pnvlad_cli.main import app

    before = tree_digest(tiny)
    out = tmp_path_factory.mktemp("align") / "tiny-aligned"
    res = CliRunner().invoke(app, ["map", "align", str(tiny), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return {"out": out, "before": before, "output": res.output}


def test_the_recorded_tree_is_left_as_it_was(tiny: Path, aligned: dict) -> None:
    assert tree_digest(tiny) == aligned["before"]


def test_the_command_says_what_it_did(aligned: dict) -> None:
    text = aligned["output"]
    assert "aligned 3 runs" in text and "closures accepted" in text and "stages:" in text


def test_the_aligned_tree_has_the_recorded_layout_and_checks(tiny: Path, aligned: dict) -> None:
    from pnvlad_service.data.tree import BenchmarkTree, check_tree

    out = aligned["out"]
    a, b = BenchmarkTree(tiny), BenchmarkTree(out)
    assert a.datasets == b.datasets and a.runs("business") == b.runs("business")
    for run in a.runs("business"):
        for kind in ("train", "test", "keyframe"):
            assert list(a.locations("business", run, kind).timestamp) == list(
                b.locations("business", run, kind).timestamp
            )
        assert (out / "business" / run / "aligned_poses.csv").is_file()
    report = check_tree(out, deep=True)
    assert report.ok, report.problems[:3]


def _metres_in_utm(root: Path, run: str, kind: str, k: int) -> np.ndarray:
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.io.submap import read_submap

    tree = BenchmarkTree(root)
    frame = tree.frames("business", run, kind)[k]  # type: ignore[index]
    sub = tree.submaps("business", run, kind)[k]  # type: ignore[arg-type]
    return frame.local_m(read_submap(root / sub.path)) + frame.origin


def test_a_keyframe_is_its_recorded_metres_moved_by_its_aligned_pose(
    tiny: Path, aligned: dict
) -> None:
    """The re-laid keyframe's metres, read back from the aligned tree, are the recorded
    metres turned and moved as aligned_poses.csv says: its yaw and position, horizontally
    (the file leaves out roll and pitch, whose corrections are tenths of a degree)."""
    import csv

    from pnvlad_service.data.tree import BenchmarkTree

    out = aligned["out"]
    run = BenchmarkTree(tiny).runs("business")[1]
    rows = list(csv.DictReader((out / "business" / run / "aligned_poses.csv").open()))
    for k in (0, len(rows) // 2, len(rows) - 1):
        row = rows[k]
        rec = _metres_in_utm(tiny, run, "keyframe", k)
        new = _metres_in_utm(out, run, "keyframe", k)
        origin = np.array([float(row[f"recorded_{a}"]) for a in ("easting", "northing", "height")])
        moved = np.array([float(row[f"aligned_{a}"]) for a in ("easting", "northing", "height")])
        yaw = math.radians(float(row["aligned_yaw_deg"]))
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        expected = (rec - origin) @ rot.T + moved
        assert np.abs(new - expected)[:, :2].max() < 0.02
        assert np.linalg.norm(moved - origin) > 0.0
        # the sensor's recorded heading turns with the points; speed and yaw rate stay
        before = BenchmarkTree(tiny).frames("business", run, "keyframe")[k].motion
        after = BenchmarkTree(out).frames("business", run, "keyframe")[k].motion
        turn = math.degrees(math.atan2(rot[1, 0], rot[0, 0]))
        assert abs((after[0] - before[0] - turn + 180) % 360 - 180) < 0.05
        assert np.array_equal(after[1:], before[1:])


def test_alignment_brings_the_map_nearer_the_truth_and_the_runs_together(
    tiny: Path, aligned: dict
) -> None:
    from pnvlad_service.mapping.accuracy import tree_accuracy

    before = tree_accuracy(tiny, "keyframe")
    after = tree_accuracy(aligned["out"], "keyframe")
    assert np.median(after.errors_m) < 0.8 * np.median(before.errors_m)
    assert np.median(after.disagreement_m) < 0.5 * np.median(before.disagreement_m)
    # the test submaps are re-laid from the same corrections
    t_before, t_after = tree_accuracy(tiny, "test"), tree_accuracy(aligned["out"], "test")
    assert np.median(t_after.errors_m) < np.median(t_before.errors_m)


def test_the_report_lists_closures_corrections_residuals_and_stages(aligned: dict) -> None:
    out = aligned["out"]
    report = json.loads((out / "align_report.json").read_text())
    closures = report["closures"]
    assert closures["accepted"] > 0
    assert closures["accepted"] + closures["rejected"] == len(closures["list"])
    for row in closures["list"]:
        assert 0.0 <= row["fitness"] <= 1.0
        assert row["accepted"] == (row["reason"] is None)
        assert "residual_m" in row or not row["accepted"]
    assert len(report["corrections"]) == 3 and report["runs_alone"] == []
    assert set(report["seconds"]) >= {"nodes", "candidates", "odometry", "closures", "solve"}
    assert report["residuals_m"]["odometry"]["median"] < 0.5
    assert (out / "align.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_index_is_built_from_the_aligned_tree(aligned: dict, tmp_path: Path) -> None:
    """pnvlad index build takes the aligned tree as it is: its entries at the aligned
    positions, its geometry at the re-laid metres."""
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.build import build_bundle
    from pnvlad_service.index.bundle import IndexBundle
    from tests.index.helpers import make_checkpoint

    out = aligned["out"]
    ckpt = make_checkpoint(tmp_path / "ckpt")
    rep = build_bundle(tmp_path / "keys.index", ckpt, out, layout="keyframe", progress=False)
    tree = BenchmarkTree(out)
    expected = sum(len(tree.locations("business", r, "keyframe")) for r in tree.runs("business"))
    assert rep.count == expected
    bundle = IndexBundle.load(tmp_path / "keys.index")
    loc = tree.locations("business", tree.runs("business")[0], "keyframe")
    assert np.allclose(bundle.metadata.northing[: len(loc)], loc.northing)
