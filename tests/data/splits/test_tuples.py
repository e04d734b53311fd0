"""data.splits.tuples: positives and negatives at their exact boundaries, against plain loops.

Expected values come from hand-worked cases (points placed at exactly 10, 25, 50 and 150 m
along one axis, where float64 arithmetic on UTM magnitudes is exact) and from plain Python
loops over every pair of submaps.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.data import splits as sp
from pnvlad_service.data.tree import BenchmarkTree
from tests.data.splits.helpers import (
    CE,
    CN,
    REG,
    brute_within,
    make_run,
    train_tree,
)


def test_training_tuples_boundaries_and_order(tmp_path: Path) -> None:
    tree = BenchmarkTree(train_tree(tmp_path))
    t = sp.build_training_tuples(tree, "oxford", REG)
    # runs sorted, CSV row order, region submaps dropped
    assert [f.rsplit("/", 1)[1] for f in t.files] == [
        "50.bin",
        "40.bin",
        "30.bin",
        "20.bin",
        "10.bin",
        "70.bin",
        "80.bin",
    ]
    assert t.files[0] == "oxford/2014-a/pointcloud_20m_10overlap/50.bin"
    assert t.positives[0].tolist() == [1, 5]  # 10 m exactly, and run B at 0 m; not itself
    assert t.negatives(0).tolist() == [4, 6]  # 50.25 m and 400 m; 50 m exactly is not
    assert 3 not in t.negatives(0) and 2 not in t.negatives(0) and 2 not in t.positives[0]
    assert t.positives[1].tolist() == [0, 5]  # both exactly 10 m away
    assert t.positives[2].tolist() == []  # 10.25 m from 0 and 5
    assert t.anchors(2).tolist() == [0, 1, 5]
    assert t.anchors(3).tolist() == []
    inside = sp.build_training_tuples(tree, "oxford", REG, inside=True)
    assert [f.rsplit("/", 1)[1] for f in inside.files] == ["60.bin", "90.bin"]


def test_training_tuples_match_a_plain_loop(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    rows = {}
    for r in range(3):
        pts = rng.integers(-240, 240, size=(40, 2)) * 0.5
        rows[r] = [(1000 * r + k, CN - 600 + a, CE + b) for k, (a, b) in enumerate(pts)]
        make_run(tmp_path, "oxford", f"run{r}", {"train": rows[r]})
    t = sp.build_training_tuples(BenchmarkTree(tmp_path), "oxford", REG)
    pooled = [(n, e) for r in range(3) for _, n, e in rows[r] if not (abs(n - CN) < 150)]
    assert len(t) == len(pooled)
    for i, q in enumerate(pooled):
        assert t.positives[i].tolist() == [k for k in brute_within(pooled, q, 10.0) if k != i]
        near = brute_within(pooled, q, 50.0)
        assert t.negatives(i).tolist() == [k for k in range(len(pooled)) if k not in near]
