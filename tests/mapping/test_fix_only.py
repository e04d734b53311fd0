"""A fleet with position fixes only, end to end: the tiny city's runs driven with a sensor's
rate, their GNSS/INS poses replaced by fixes of their positions once a second (no heading),
posed by KISS-ICP laid onto the fixes, prepared, then `pnvlad map align`: the aligned keyframes
land nearer the simulator's truth than the fixes themselves; a run whose fixes jump, or that
overlaps no other, is refused by name with the recorded tree untouched."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.mapping.test_align import tree_digest
from tests.mapping.test_bad_input import _shift_keyframes

pytest.importorskip("gtsam")
pytest.importorskip("kiss_icp")

#: Metres between the tiny city's scans here: 10 to 20 scans a second at its speeds (its
#: preset's 4 m are a tenth of a second's drive at most 2.5 times a second: too far apart for
#: KISS-ICP's constant-velocity start).
SPACING_M = 0.5


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from pnvlad_service.data.prepare import prepare_drive
    from pnvlad_service.data.sources.fix_odometry import FixOdometryDrive
    from pnvlad_service.data.sources.fixes import Fixes
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    spec = get_preset("tiny").model_copy(update={"scan_spacing": SPACING_M})
    root = tmp_path_factory.mktemp("fleet") / "tree"
    fix_errors = []
    for k in range(spec.runs):
        drive = simulated_drive(spec, 0, k, 3)
        t = drive.timestamps
        idx = np.unique(np.searchsorted(t, np.arange(t[0], t[-1], 1_000_000)))
        fixes = Fixes(t[idx], drive.poses[idx, :3, 3].copy(), np.full(len(idx), np.nan))
        truth = drive.true_poses[idx, :2, 3]
        fix_errors += list(np.linalg.norm(fixes.enu[:, :2] - truth, axis=1))
        laid = FixOdometryDrive(drive, fixes, progress=False)
        prepare_drive(laid, root / "business" / drive.name, kinds=("keyframe",), progress=False)
    return {"root": root, "fix_errors": np.array(fix_errors)}


def _align(root: Path, out: Path) -> tuple[int, str]:
    from pnvlad_cli.main import app

    res = CliRunner().invoke(app, ["map", "align", str(root), "-o", str(out)])
    return res.exit_code, res.output


def test_aligned_fix_only_runs_land_nearer_the_truth_than_their_fixes(
    fleet: dict, tmp_path: Path
) -> None:
    import json

    from pnvlad_service.mapping.accuracy import tree_accuracy

    root = fleet["root"]
    runs = sorted(p for p in (root / "business").iterdir())
    assert all((r / "fixes.csv").is_file() for r in runs)
    before = tree_digest(root)
    code, text = _align(root, tmp_path / "out")
    assert code == 0, text
    assert tree_digest(root) == before
    report = json.loads((tmp_path / "out" / "align_report.json").read_text())
    assert report["fix_runs"]["runs"] == [f"business/{r.name}" for r in runs]
    # the error against the simulator's truth, from the sidecars' true poses
    laid = tree_accuracy(root, "keyframe").errors_m
    aligned = tree_accuracy(tmp_path / "out", "keyframe").errors_m
    fixes = fleet["fix_errors"]
    assert np.median(aligned) < 0.85 * np.median(fixes)
    assert np.percentile(aligned, 99) < min(3.0, np.percentile(laid, 99))
    # the aligned tree is a recorded-pose tree again: it keeps no fixes
    assert not list((tmp_path / "out").rglob("fixes.csv"))


def test_a_fix_only_run_whose_fixes_jump_is_refused_by_name(fleet: dict, tmp_path: Path) -> None:
    root = tmp_path / "tree"
    shutil.copytree(fleet["root"], root)
    run = sorted((root / "business").iterdir())[1]
    csv = run / "fixes.csv"
    lines = csv.read_text().splitlines()
    for k in range(12, len(lines)):  # a receiver 25 m off from fix 11 on
        cells = lines[k].split(",")
        cells[1] = repr(float(cells[1]) + 25.0)
        lines[k] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    before = tree_digest(root)
    code, text = _align(root, tmp_path / "out")
    assert code == 2
    last = text.strip().splitlines()[-1]  # the log's lines before it
    assert f"business/{run.name}" in last and "fixes jump 25" in last
    assert tree_digest(root) == before and not (tmp_path / "out").exists()


def test_a_fix_only_run_that_overlaps_no_other_is_refused_by_name(
    fleet: dict, tmp_path: Path
) -> None:
    root = tmp_path / "tree"
    shutil.copytree(fleet["root"], root)
    run = sorted((root / "business").iterdir())[2]
    _shift_keyframes(run, 0, 3000.0)
    csv = run / "fixes.csv"
    lines = csv.read_text().splitlines()
    for k in range(1, len(lines)):  # the fixes and where the odometry was, 3 km east alike
        cells = lines[k].split(",")
        cells[1], cells[5] = (repr(float(cells[i]) + 3000.0) for i in (1, 5))
        lines[k] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    before = tree_digest(root)
    code, text = _align(root, tmp_path / "out")
    assert code == 2
    assert f"business/{run.name}" in text and "share no verified place" in text
    assert tree_digest(root) == before and not (tmp_path / "out").exists()


def test_kiss_icp_stands_in_only_for_a_fix_only_runs_failed_registrations() -> None:
    from pnvlad_service.data.sources.fixes import Fixes
    from pnvlad_service.mapping.edges import Edge
    from pnvlad_service.mapping.fixes import FixConfig, FixRun, odometry_fallback
    from pnvlad_service.mapping.nodes import MapNodes, RunNodes

    def run(name: str, turn: float) -> RunNodes:
        poses = np.tile(np.eye(4), (4, 1, 1))
        for k in range(4):
            c, s = np.cos(turn * k), np.sin(turn * k)
            poses[k, :2, :2] = [[c, -s], [s, c]]
            poses[k, :3, 3] = [5.0 * k, 0.0, 0.0]
        return RunNodes(name, np.arange(4, dtype=np.int64), poses)

    nodes = MapNodes([run("a/gnss", 0.0), run("a/fixes", 0.1)])

    def edge(target: int, reason: str | None) -> Edge:
        return Edge("odometry", target, target + 1, np.eye(4), None, 0.1, 0.0, reason=reason)

    edges = [
        edge(0, "fitness 0.10 < 0.2"),  # a GNSS/INS run's: its chain spans it
        edge(4, "fitness 0.10 < 0.2"),  # replaced
        edge(5, "moved the step 4.00 m, 1.00 deg from the recorded one"),  # kept out
        edge(6, None),
    ]
    fix = FixRun(1, Fixes(np.arange(3), np.zeros((3, 3)), np.full(3, np.nan)), np.zeros((3, 3)))
    out = odometry_fallback(nodes, edges, [fix], FixConfig())
    assert [e.kind for e in out] == ["odometry", "odometry-kiss-icp", "odometry", "odometry"]
    assert out[0] is edges[0] and out[2] is edges[2] and out[3] is edges[3]
    swapped = out[1]
    expected = np.linalg.inv(nodes.poses[4]) @ nodes.poses[5]
    assert swapped.accepted and np.allclose(swapped.transform, expected)
    sigma = np.sqrt(np.diag(swapped.covariance))  # type: ignore[arg-type]
    assert np.allclose(sigma[:3], 0.05 + 0.02 * 5.0)
    assert np.allclose(sigma[3:], np.radians(0.5))
