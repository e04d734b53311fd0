"""metrics.py against a hand-worked case and a plain Python re-implementation of evaluate.py."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.evaluation.metrics import (
    nearest,
    one_percent_n,
    pair_recall_from_neighbours,
    recall_at_1_by_distance,
    recall_at_n,
)


def reference_recall(db, qs, truth, k=25, mode="round"):
    """The published get_recall/evaluate loop, in plain Python (ties to the lower index)."""
    pair_recalls, pair_pct = [], []
    for i in range(len(db)):
        for j in range(len(qs)):
            if i == j:
                continue
            counts = [0] * k
            pct, n_eval = 0, 0
            n1 = max(round(len(db[i]) / 100) if mode == "round" else len(db[i]) // 100, 1)
            for q, true in enumerate(truth[j][i]):
                if not true:
                    continue
                n_eval += 1
                dists = []
                for d, vec in enumerate(db[i]):
                    s = 0.0
                    for a, b in zip(qs[j][q], vec, strict=True):
                        s += (float(a) - float(b)) ** 2
                    dists.append((s, d))
                ranked = [d for _, d in sorted(dists)][:k]
                for pos, d in enumerate(ranked):
                    if d in true:
                        counts[pos] += 1
                        break
                if set(ranked[:n1]) & set(true):
                    pct += 1
            if n_eval == 0:
                continue
            cum, acc = [], 0
            for c in counts:
                acc += c
                cum.append(acc / n_eval * 100)
            pair_recalls.append(cum)
            pair_pct.append(pct / n_eval * 100)
    mean = [sum(r[n] for r in pair_recalls) / len(pair_recalls) for n in range(k)]
    return mean, sum(pair_pct) / len(pair_pct), len(pair_recalls)


def test_hand_worked_case_with_ties_empty_truth_and_small_database() -> None:
    db = [np.array([[0.0], [1.0], [2.0], [3.0]]), np.array([[10.0], [11.0]])]
    qs = [np.array([[10.4]]), np.array([[0.9], [1.5], [5.0]])]
    truth = [
        {1: [[1]]},  # run 0's query: nearest 0 (0.4), then 1 (0.6): hit at rank 2
        {0: [[2], [2], []]},  # 0.9: order 1, 0, 2 -> rank 3; 1.5: tie 1|2 -> rank 2; skipped
    ]
    res = recall_at_n(db, qs, truth)
    assert res.recall_at_n[:4].tolist() == [0.0, 75.0, 100.0, 100.0]
    assert res.recall_at_n[-1] == 100.0  # databases of 2 and 4 submaps: stays at their size
    assert res.recall_at_1pct == 0.0  # N = max(round(4/100), 1) = 1
    assert res.n_queries == 3
    assert [(p.db, p.query, p.n_queries) for p in res.per_pair] == [(0, 1, 2), (1, 0, 1)]
    assert res.per_pair[0].recall_at_n[:3].tolist() == [0.0, 50.0, 100.0]
    assert res.skipped_pairs == []


def test_matches_plain_loop_on_random_runs() -> None:
    rng = np.random.default_rng(0)
    sizes_db = [40, 12, 130, 60]
    sizes_q = [7, 5, 9, 0]
    centres = rng.normal(size=(130, 6))
    db, qs, truth = [], [], []
    for n, m in zip(sizes_db, sizes_q, strict=True):
        db.append((centres[:n] + 0.3 * rng.normal(size=(n, 6))).astype(np.float32))
        qs.append((centres[:m] + 0.3 * rng.normal(size=(m, 6))).astype(np.float32))
    for j, m in enumerate(sizes_q):
        t = {}
        for i, n in enumerate(sizes_db):
            if i == j:
                continue
            # truth: the same "place" and a random neighbour, some queries with none
            t[i] = [
                sorted({q, int(rng.integers(n))} & set(range(n))) if rng.random() > 0.2 else []
                for q in range(m)
            ]
        truth.append(t)
    truth[0][1] = [[] for _ in range(sizes_q[0])]  # a pair with no query to score
    res = recall_at_n(db, qs, truth)
    ref, ref_pct, n_pairs = reference_recall(db, qs, truth)
    np.testing.assert_allclose(res.recall_at_n, ref, rtol=0, atol=1e-9)
    assert res.recall_at_1pct == pytest.approx(ref_pct, abs=1e-9)
    assert len(res.per_pair) == n_pairs
    assert (1, 0) in res.skipped_pairs  # database 1, queries 0
    assert all(p.query != 3 for p in res.per_pair)  # run 3 has no queries at all
    res_floor = recall_at_n(db, qs, truth, one_percent="floor")
    assert res_floor.recall_at_1pct == pytest.approx(
        reference_recall(db, qs, truth, mode="floor")[1], abs=1e-9
    )
    assert 0 < res.recall_at_n[0] < res.recall_at_n[-1] <= 100  # a case that discriminates
    # monotone and bounded
    assert np.all(np.diff(res.recall_at_n) >= 0) and res.recall_at_n[-1] <= 100


def test_faiss_neighbours_give_the_same_recall() -> None:
    faiss = pytest.importorskip("faiss")
    rng = np.random.default_rng(1)
    db = rng.normal(size=(300, 16)).astype(np.float32)
    q = rng.normal(size=(50, 16)).astype(np.float32)
    index = faiss.IndexFlatL2(16)
    index.add(db)
    _, ranked = index.search(q, 25)
    mine = nearest(db, q, 25)
    assert (mine == ranked).all()
    truth = [[int(x) for x in rng.choice(300, size=3, replace=False)] for _ in range(50)]
    a = pair_recall_from_neighbours(ranked, truth, 300)
    b = recall_at_n([db, db], [q, q], [{1: truth}, {0: truth}]).per_pair[0]
    assert a.recall_at_n.tolist() == b.recall_at_n.tolist()
    assert a.recall_at_1pct == b.recall_at_1pct and a.one_percent_n == 3
    # a bigger database: the k smallest are selected before sorting, same ranks
    big = rng.normal(size=(9000, 8)).astype(np.float32)
    index = faiss.IndexFlatL2(8)
    index.add(big)
    _, ranked = index.search(q[:, :8].copy(), 25)
    assert (nearest(big, q[:, :8], 25) == ranked).all()
    with pytest.raises(InputError, match="outside the database"):
        pair_recall_from_neighbours(ranked, [[9000]] * 50, 9000)


def test_nearest_breaks_ties_by_index_and_handles_small_databases() -> None:
    db = np.array([[1.0], [-1.0], [1.0], [0.0], [-1.0]])
    assert nearest(db, np.array([[0.0]]), 3).tolist() == [[3, 0, 1]]
    assert nearest(db, np.array([[0.0]]), 25).tolist() == [[3, 0, 1, 2, 4]]
    assert nearest(db[:0], np.array([[0.0]]), 25).shape == (1, 0)
    # ties across the k-th place: the lower indices win, as with a full stable sort
    many = np.array([[2.0], [1.0], [1.0], [1.0], [0.0], [1.0]])
    assert nearest(many, np.array([[0.0]]), 3).tolist() == [[4, 1, 2]]
    rng = np.random.default_rng(7)
    coarse = rng.integers(0, 3, size=(200, 2)).astype(np.float32)  # many exact ties
    qs = rng.integers(0, 3, size=(20, 2)).astype(np.float32)
    full = [
        sorted(range(200), key=lambda d, q=q: (float(((coarse[d] - q) ** 2).sum()), d))[:25]
        for q in qs
    ]
    assert nearest(coarse, qs, 25).tolist() == full
    with pytest.raises(InputError, match="shapes"):
        nearest(db, np.zeros((2, 3)))


@pytest.mark.parametrize(
    ("size", "rounded", "floored"),
    [(1, 1, 1), (50, 1, 1), (150, 2, 1), (347, 3, 3), (350, 4, 3), (399, 4, 3), (445, 4, 4)],
)
def test_one_percent_n(size: int, rounded: int, floored: int) -> None:
    assert one_percent_n(size) == rounded
    assert one_percent_n(size, "floor") == floored


def test_no_scorable_pair_and_bad_shapes() -> None:
    db = [np.zeros((3, 2)), np.zeros((3, 2))]
    qs = [np.zeros((1, 2)), np.zeros((1, 2))]
    res = recall_at_n(db, qs, [{1: [[]]}, {0: [[]]}])
    assert np.isnan(res.recall_at_n).all() and res.per_pair == []
    assert sorted(res.skipped_pairs) == [(0, 1), (1, 0)]
    with pytest.raises(InputError, match="truth lists"):
        recall_at_n(db, qs, [{1: [[], []]}, {0: [[]]}])
    with pytest.raises(InputError, match="one of each per run"):
        recall_at_n(db, qs[:1], [{}])


def test_recall_at_1_by_distance_is_inclusive() -> None:
    q = np.array([[5735712.0, 620084.0]] * 3)
    top = q + np.array([[0.0, 10.0], [25.0, 0.0], [0.0, -40.0]])
    assert recall_at_1_by_distance(q, top, [5.0, 10.0, 25.0, 50.0]).tolist() == pytest.approx(
        [0.0, 100 / 3, 200 / 3, 100.0]
    )
