"""data.splits.evaluation: databases, queries and ground truth by hand and by plain loops.

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
    eval_tree,
    make_run,
)


def test_evaluation_sets_by_hand(tmp_path: Path) -> None:
    (es,) = sp.build_evaluation_sets(BenchmarkTree(eval_tree(tmp_path)), "oxford", REG)
    assert es.name == "oxford" and es.runs == ["r1", "r2", "r3"]
    assert [len(d) for d in es.database] == [5, 4, 5]
    # queries: inside ±150 strictly; 149.75 in, 150 out, 250 and -300 out
    assert [len(q) for q in es.queries] == [4, 3, 4]
    assert es.query_db_index(0).tolist() == [1, 2, 3, 4]
    assert es.query_db_index(2).tolist() == [0, 1, 2, 3]
    # query r1@0: r2 database within 25 m inclusive -> offset 25 (exactly 25 m); r3 -> -24.75, 0
    q0 = 1  # r1's queries are offsets -100, 0, 40, 149.75
    assert es.truth[0][1][q0].tolist() == [1]
    assert es.truth[0][2][q0].tolist() == [1, 2]
    # query r2@25 in r3: 25.25 is 0.25 away, 0 is exactly 25 m away (inclusive)
    assert es.truth[1][2][1].tolist() == [2, 3]
    # query r1@149.75 has nothing within 25 m in r2 (nearest 65)
    assert es.truth[0][1][3].tolist() == []
    assert set(es.truth[0]) == {1, 2} and set(es.truth[1]) == {0, 2}


def test_evaluation_truth_matches_a_plain_loop(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    runs = {}
    for r in range(4):
        pts = rng.integers(-400, 400, size=(30, 2)) * 0.5
        runs[f"run{r}"] = [(r * 100 + k, CN + a, CE + b) for k, (a, b) in enumerate(pts)]
        make_run(tmp_path, "oxford", f"run{r}", {"test": runs[f"run{r}"]})
    (es,) = sp.build_evaluation_sets(BenchmarkTree(tmp_path), "oxford", REG)
    names = sorted(runs)
    for j, qrun in enumerate(names):
        qs = [(n, e) for _, n, e in runs[qrun] if abs(n - CN) < 150 and abs(e - CE) < 150]
        assert len(es.queries[j]) == len(qs)
        for i, drun in enumerate(names):
            if i == j:
                continue
            db = [(n, e) for _, n, e in runs[drun]]
            assert [x.tolist() for x in es.truth[j][i]] == [brute_within(db, q, 25.0) for q in qs]


def test_inhouse_runs_group_by_area_with_builtin_regions(tmp_path: Path) -> None:
    for k in (1, 2):
        make_run(
            tmp_path,
            "inhouse_datasets",
            f"business_run{k}",
            {"test": [(k * 10, 100.0, 200.0 + k)]},
            "inhouse",
        )
        n, e = sp.INHOUSE_CENTRES["residential"][0]
        make_run(
            tmp_path,
            "inhouse_datasets",
            f"residential_run{k}",
            {"test": [(k * 10 + 1, n, e), (k * 10 + 2, n + 500.0, e)]},
            "inhouse",
        )
    sets = sp.build_evaluation_sets(BenchmarkTree(tmp_path), "inhouse_datasets")
    by = {s.name: s for s in sets}
    assert set(by) == {"business", "residential"}
    assert [len(q) for q in by["business"].queries] == [1, 1]  # everything is a query
    assert [len(q) for q in by["residential"].queries] == [1, 1]
