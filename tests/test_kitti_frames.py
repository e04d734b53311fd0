"""benchmarks/kitti_frames.py: the ranks and ratios it prints, computed by hand for made-up
descriptors, and the shipped bev-netvlad models on the real KITTI frames: each tells the real
revisit (frame 4501 against 52) and the consecutive frames (95 against 94) apart by a wider
margin than the same network with random weights."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.benchmark_scripts import BENCHMARKS, load


@pytest.fixture(scope="module")
def kf():  # the script as a module
    return load("kitti_frames")


def test_rows_rank_the_place_among_the_other_scans(kf) -> None:
    # FRAMES = (0, 5, 52, 94, 95, 4501): descriptors on a line, so distances are differences
    at = {0: 10.0, 5: 20.0, 52: 3.0, 94: 7.5, 95: 8.0, 4501: 0.0}
    desc = np.array([[at[f], 0.0] for f in kf.FRAMES])
    got = {q: (rank, d_place, d_other) for q, rank, d_place, d_other in kf.rows(desc)}
    # 4501 at 0: 52 at 3 is nearest of 0 (10), 5 (20), 52 (3), 94 (7.5), 95 (8)
    assert got[4501] == (1, pytest.approx(3.0), pytest.approx(7.5))
    # 95 at 8: 94 (0.5 away) first; the nearest other is frame 0 (2 away)
    assert got[95] == (1, pytest.approx(0.5), pytest.approx(2.0))
    at[52] = 9.0  # now 94 (7.5) and 95 (8) lie nearer 4501 than 52 (9) does: rank 3
    desc = np.array([[at[f], 0.0] for f in kf.FRAMES])
    got = {q: rank for q, rank, _, _ in kf.rows(desc)}
    assert got[4501] == 3


def test_a_folder_without_the_scans_is_one_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / "kitti_frames.py"), "--scans", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr == f"error: {tmp_path}: no kitti00_000000.bin here (the real KITTI scans)\n"


@pytest.mark.parametrize("name", ["bev-benchmark", "bev-mixed", "bev-oxford"])
def test_a_shipped_model_separates_the_real_places_better_than_random_weights(
    kf, real_scans: Path, tmp_path: Path, name: str
) -> None:
    from pnvlad_service.models.runtimes import load_encoder

    x = kf.clouds(kf.scans_dir(real_scans))
    model = f"pretrained:{name}"
    ratios = {}
    for label, path in (("trained", model), ("random", kf.random_twin(model, tmp_path))):
        found = kf.rows(load_encoder(path, runtime="torch").embed(x))
        if label == "trained":  # each real place is the nearest of the five scans
            assert [rank for _, rank, _, _ in found] == [1, 1]
        ratios[label] = {q: d_place / d_other for q, _, d_place, d_other in found}
    for query in kf.QUERIES:
        assert ratios["trained"][query] < ratios["random"][query] - 0.1, (query, ratios)
