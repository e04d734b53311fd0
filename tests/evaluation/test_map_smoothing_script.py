"""benchmarks/map_smoothing.py: the denser map it can measure (each run's training-layout
submaps as its database) with the truth recomputed, against a direct computation."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.data.dataset import load_eval_runs
from pnvlad_service.data.tree import BenchmarkTree
from tests.benchmark_scripts import load
from tests.training.street import make_tiny_tree


def test_training_layout_databases_and_their_truth(tmp_path: Path) -> None:
    splits = make_tiny_tree(tmp_path, runs=3, train_step=4.0)
    runs = load_eval_runs(tmp_path, splits, None, None)
    dense = load("map_smoothing").train_layout_databases(tmp_path, runs)
    tree = BenchmarkTree(tmp_path)
    for r, d in zip(runs, dense, strict=True):
        subs = tree.submaps("city", r.name.split("/")[-1], "train")
        assert [p.name for p in d.db_paths] == [f"{s.timestamp}.bin" for s in subs]
        assert len(d.db_paths) == 75 > len(r.db_paths)  # every 4 m over 300 m, not every 10
        assert d.query_paths == r.query_paths
    for j, q in enumerate(dense):
        for k, pos in enumerate(q.query_positions):
            for i, db in enumerate(dense):
                near = [
                    m
                    for m, p in enumerate(db.db_positions)
                    if i != j and np.hypot(*(p - pos)) <= 25.0
                ]
                assert q.truth[k].get(i, np.zeros(0)).tolist() == near
