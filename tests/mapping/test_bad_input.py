"""Maps that cannot be aligned are refused before anything is written: a run whose recorded
poses jump, a run that overlaps no other. The message names the run; the recorded tree is left
byte for byte as it was and no aligned tree appears."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from tests.mapping.test_align import tree_digest

pytest.importorskip("gtsam")


def _shift_keyframes(run_dir: Path, first: int, shift_e: float) -> None:
    """Move the keyframes of ``run_dir`` from row ``first`` on by ``shift_e`` metres east in
    their CSV and sidecar (the truth with them: a recording placed elsewhere, not a wrong one)."""
    from pnvlad_service.data.frames import (
        SubmapFrame,
        frames_path,
        read_frames_csv,
        write_frames_csv,
    )
    from pnvlad_service.data.tree import KEYFRAME_CSV, read_locations_csv, write_locations_csv

    csv = run_dir / KEYFRAME_CSV
    rows = read_locations_csv(csv).rows()
    frames = read_frames_csv(frames_path(csv))
    for k in range(first, len(rows)):
        t, n, e = rows[k]
        rows[k] = (t, n, e + shift_e)
        f = frames[k]
        moved = f.origin.copy()
        moved[0] += shift_e
        true = None if f.true_position is None else f.true_position + np.array([shift_e, 0.0, 0.0])
        frames[k] = SubmapFrame(
            f.timestamp, moved, f.centre, f.scale, f.frame, true, f.true_yaw_deg
        )
    write_frames_csv(frames_path(csv), frames)
    write_locations_csv(csv, rows)


def _align(root: Path, out: Path) -> tuple[int, str]:
    from pnvlad_cli.main import app

    res = CliRunner().invoke(app, ["map", "align", str(root), "-o", str(out)])
    return res.exit_code, res.output


@pytest.fixture
def copy(tiny: Path, tmp_path: Path) -> Path:
    out = tmp_path / "tree"
    shutil.copytree(tiny, out)
    return out


def test_a_run_whose_poses_jump_is_refused_by_name(copy: Path, tmp_path: Path) -> None:
    run = sorted(p for p in (copy / "business").iterdir() if p.is_dir())[1]
    _shift_keyframes(run, 20, 45.0)
    before = tree_digest(copy)
    code, text = _align(copy, tmp_path / "out")
    assert code == 2
    assert f"business/{run.name}" in text and "jump 4" in text
    assert tree_digest(copy) == before and not (tmp_path / "out").exists()


def test_a_run_that_overlaps_no_other_is_refused_by_name(copy: Path, tmp_path: Path) -> None:
    run = sorted(p for p in (copy / "business").iterdir() if p.is_dir())[2]
    _shift_keyframes(run, 0, 3000.0)
    before = tree_digest(copy)
    code, text = _align(copy, tmp_path / "out")
    assert code == 2
    assert f"business/{run.name}" in text and "share no verified place" in text
    assert tree_digest(copy) == before and not (tmp_path / "out").exists()


def test_the_recorded_tree_is_never_the_output(tiny: Path) -> None:
    code, text = _align(tiny, tiny)
    assert code == 2 and ("already exists" in text or "beside" in text)
