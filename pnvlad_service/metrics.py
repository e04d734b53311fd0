"""The benchmark's retrieval metrics: recall@N (N = 1..25) and recall@1% over ordered run pairs.

For every ordered pair (database run i, query run j), i != j (BENCHMARK_FORMAT.md, "Metrics",
and the published ``evaluate.py``):

1. find each query's ``k = 25`` nearest database descriptors (Euclidean distance);
2. skip the queries whose ground truth in run i is empty;
3. recall@N: the share of the remaining queries with a true match among the first N results,
   cumulative over N = 1..25, in percent;
4. recall@1%: the same share with N = max(round(len(database i) / 100), 1).

Each figure is averaged over the run pairs (a plain mean over pairs, not weighted by queries).

Choices where the published code is silent or breaks (documented in docs/SPLITS.md):

- A pair whose queries all have empty ground truth cannot be scored (the published code divides
  by zero there). Such pairs are left out of the averages and counted in ``skipped_pairs``.
- A database with fewer than 25 submaps: the ranked list holds all of them, and recall@N for N
  beyond its length equals recall at its length (the published KDTree query raises instead).
- The 1% cut-off uses Python's ``round`` as BENCHMARK_FORMAT.md and later code (MinkLoc3D) do;
  the published TensorFlow ``evaluate.py`` uses ``len // 100``: pass ``one_percent="floor"``
  to reproduce it. On Oxford (347 to 445 submaps a run) both give 3 or 4, except runs of
  350 to 399 submaps (round: 4, floor: 3).
- Ties in distance are broken by the lower database index (a stable sort), so results do not
  depend on the search library.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

NUM_NEIGHBOURS = 25

#: ``truth[j][i][q]``: indices into run i's database of the true matches of query q of run j.
Truth = Sequence[Mapping[int, Sequence[Sequence[int]]]]


@dataclass
class PairRecall:
    """Recall of one ordered pair (database run ``db``, query run ``query``).

    ``recall_at_n``: float64 [25], percent; ``recall_at_1pct``: percent; ``n_queries``: queries
    evaluated (non-empty ground truth); ``one_percent_n``: the N used for recall@1%;
    ``top1_correct``: bool [n_queries] in the query run's order of evaluated queries.
    """

    db: int
    query: int
    recall_at_n: np.ndarray
    recall_at_1pct: float
    n_queries: int
    one_percent_n: int
    top1_correct: np.ndarray = field(repr=False)
    evaluated: np.ndarray = field(repr=False)


@dataclass
class RecallResult:
    """Recall averaged over ordered run pairs.

    ``recall_at_n``: float64 [25], percent (index 0 is recall@1); ``recall_at_1pct``: percent;
    ``per_pair``: every scored pair; ``n_queries``: queries evaluated summed over pairs;
    ``skipped_pairs``: ``(db, query)`` pairs left out because no query had ground truth.
    """

    recall_at_n: np.ndarray
    recall_at_1pct: float
    per_pair: list[PairRecall]
    n_queries: int
    skipped_pairs: list[tuple[int, int]]

    @property
    def recall_at_1(self) -> float:
        return float(self.recall_at_n[0])

    def to_dict(self) -> dict:
        """Plain JSON-ready summary (per pair: run indices, n_queries, recall@1, @1%)."""
        return {
            "recall_at_n": [float(x) for x in self.recall_at_n],
            "recall_at_1": self.recall_at_1,
            "recall_at_1pct": float(self.recall_at_1pct),
            "n_queries": int(self.n_queries),
            "n_pairs": len(self.per_pair),
            "skipped_pairs": [list(p) for p in self.skipped_pairs],
            "per_pair": [
                {
                    "db": p.db,
                    "query": p.query,
                    "n_queries": p.n_queries,
                    "recall_at_1": float(p.recall_at_n[0]),
                    "recall_at_1pct": float(p.recall_at_1pct),
                }
                for p in self.per_pair
            ],
        }


def one_percent_n(db_size: int, mode: Literal["round", "floor"] = "round") -> int:
    """The N of recall@1%: ``max(round(db_size / 100), 1)`` (or ``db_size // 100``, floored)."""
    n = round(db_size / 100) if mode == "round" else db_size // 100
    return max(int(n), 1)


def nearest(
    db: np.ndarray, queries: np.ndarray, k: int = NUM_NEIGHBOURS, block: int = 1024
) -> np.ndarray:
    """Exact k nearest neighbours by Euclidean distance, ties broken by the lower index.

    ``db``: float [N, D]; ``queries``: float [M, D]. Returns int64 [M, min(k, N)], nearest
    first. Distances are computed in float64 (``|q|² - 2 q·d + |d|²``) block by block.
    """
    db = np.asarray(db, dtype=np.float64)
    queries = np.asarray(queries, dtype=np.float64)
    if db.ndim != 2 or queries.ndim != 2 or (len(queries) and db.shape[1] != queries.shape[1]):
        raise InputError(
            f"descriptor shapes do not match: database {db.shape}, queries {queries.shape}",
            source="descriptors",
        )
    kk = min(k, len(db))
    out = np.empty((len(queries), kk), dtype=np.int64)
    if kk == 0:
        return out
    dn = np.einsum("ij,ij->i", db, db)
    for s in range(0, len(queries), block):
        q = queries[s : s + block]
        d2 = np.einsum("ij,ij->i", q, q)[:, None] - 2.0 * (q @ db.T) + dn[None, :]
        if kk < len(db):
            part = np.argpartition(d2, kk - 1, axis=1)[:, :kk]
            # include every index tied with the k-th distance so the stable sort sees them all
            kth = np.take_along_axis(d2, part, axis=1).max(axis=1, keepdims=True)
            for r in range(len(q)):
                cand = np.flatnonzero(d2[r] <= kth[r])
                order = np.lexsort((cand, d2[r, cand]))
                out[s + r] = cand[order[:kk]]
        else:
            out[s : s + len(q)] = np.argsort(d2, axis=1, kind="stable")[:, :kk]
    return out


def pair_recall_from_neighbours(
    neighbours: np.ndarray,
    truth: Sequence[Sequence[int]],
    db_size: int,
    *,
    num_neighbours: int = NUM_NEIGHBOURS,
    one_percent: Literal["round", "floor"] = "round",
    db: int = -1,
    query: int = -1,
) -> PairRecall | None:
    """Recall of one pair from ranked database indices (e.g. a FAISS search result).

    ``neighbours``: int [M, k] database indices, nearest first (``-1`` entries are ignored);
    ``truth``: for each of the M queries, its true database indices; ``db_size``: the number of
    database submaps (for the 1% cut-off). Returns ``None`` when no query has ground truth.
    """
    neighbours = np.asarray(neighbours)
    if len(neighbours) != len(truth):
        raise InputError(
            f"{len(neighbours)} ranked lists for {len(truth)} queries", source="neighbours"
        )
    n1 = one_percent_n(db_size, one_percent)
    first_hit = np.full(len(truth), -1, dtype=np.int64)
    evaluated = np.zeros(len(truth), dtype=bool)
    pct_hits = 0
    for q, true in enumerate(truth):
        if len(true) == 0:
            continue
        evaluated[q] = True
        ranked = neighbours[q, :num_neighbours]
        hits = np.flatnonzero(np.isin(ranked, np.asarray(true)) & (ranked >= 0))
        if len(hits):
            first_hit[q] = hits[0]
            if hits[0] < n1:
                pct_hits += 1
    n_eval = int(evaluated.sum())
    if n_eval == 0:
        return None
    counts = np.zeros(num_neighbours, dtype=np.float64)
    fh = first_hit[evaluated]
    np.add.at(counts, fh[fh >= 0], 1.0)
    recall = np.cumsum(counts) / n_eval * 100.0
    return PairRecall(
        db=db,
        query=query,
        recall_at_n=recall,
        recall_at_1pct=pct_hits / n_eval * 100.0,
        n_queries=n_eval,
        one_percent_n=n1,
        top1_correct=fh == 0,
        evaluated=np.flatnonzero(evaluated),
    )


def recall_at_n(
    db_desc: Sequence[np.ndarray],
    query_desc: Sequence[np.ndarray],
    truth: Truth,
    *,
    num_neighbours: int = NUM_NEIGHBOURS,
    one_percent: Literal["round", "floor"] = "round",
    progress: bool = False,
) -> RecallResult:
    """The benchmark's recall over every ordered pair of runs (database i, queries j), i != j.

    ``db_desc[i]``: float32 [N_i, D] descriptors of run i's database; ``query_desc[j]``: float32
    [M_j, D] of run j's queries; ``truth[j][i][q]``: true indices into database i for query q
    of run j (``EvaluationSet.truth`` from ``pnvlad_service.splits``). Exact search (numpy,
    float64). Returns the averages over the scorable pairs (see the module docstring).
    """
    if len(db_desc) != len(query_desc) or len(truth) != len(query_desc):
        raise InputError(
            f"{len(db_desc)} databases, {len(query_desc)} query sets and {len(truth)} truth "
            "sets: expected one of each per run",
            source="descriptors",
        )
    # database-major order, as the published evaluate.py loops
    pairs = [(i, j) for i in range(len(db_desc)) for j in range(len(query_desc)) if i != j]
    iterator = pairs
    if progress:
        from tqdm import tqdm

        iterator = tqdm(pairs, desc="recall", unit="pair")
    per_pair: list[PairRecall] = []
    skipped: list[tuple[int, int]] = []
    for i, j in iterator:
        t = truth[j].get(i)
        if t is None:
            raise InputError(f"no ground truth of query run {j} in database run {i}", "truth")
        if len(t) != len(query_desc[j]):
            raise InputError(
                f"query run {j}: {len(query_desc[j])} descriptors but {len(t)} truth lists",
                source="truth",
            )
        if not any(len(x) for x in t):
            skipped.append((i, j))
            continue
        pr = pair_recall_from_neighbours(
            nearest(db_desc[i], query_desc[j], num_neighbours),
            t,
            len(db_desc[i]),
            num_neighbours=num_neighbours,
            one_percent=one_percent,
            db=i,
            query=j,
        )
        assert pr is not None
        per_pair.append(pr)
    return average_pairs(per_pair, skipped, num_neighbours)


def average_pairs(
    per_pair: list[PairRecall],
    skipped: list[tuple[int, int]] | None = None,
    num_neighbours: int = NUM_NEIGHBOURS,
) -> RecallResult:
    """Average per-pair recalls (a plain mean over pairs, as the published code does)."""
    if skipped:
        log.warning("%d run pair(s) without any query with ground truth left out", len(skipped))
    if not per_pair:
        nan = np.full(num_neighbours, np.nan)
        return RecallResult(nan, float("nan"), [], 0, list(skipped or []))
    return RecallResult(
        recall_at_n=np.mean([p.recall_at_n for p in per_pair], axis=0),
        recall_at_1pct=float(np.mean([p.recall_at_1pct for p in per_pair])),
        per_pair=per_pair,
        n_queries=sum(p.n_queries for p in per_pair),
        skipped_pairs=list(skipped or []),
    )


#: The name in the coordinator's brief; the same function.
evaluate_descriptors = recall_at_n


def recall_at_1_by_distance(
    query_xy: np.ndarray, top1_xy: np.ndarray, thresholds: Sequence[float]
) -> np.ndarray:
    """Recall@1 as a function of the distance threshold (the paper's Fig. of accuracy vs d).

    ``query_xy``, ``top1_xy``: float64 [M, 2] UTM (northing, easting) of each query and of its
    top-1 retrieved database submap. Returns float64 [T], percent: for each threshold d (metres)
    the share of queries whose top-1 lies within d (inclusive, as the ground truth is).
    """
    q = np.asarray(query_xy, dtype=np.float64)
    r = np.asarray(top1_xy, dtype=np.float64)
    if q.shape != r.shape or q.ndim != 2 or q.shape[1] != 2:
        raise InputError(f"expected two [M, 2] arrays, got {q.shape} and {r.shape}", "positions")
    if len(q) == 0:
        return np.full(len(thresholds), np.nan)
    d2 = ((q - r) ** 2).sum(axis=1)
    return np.array([(d2 <= float(t) ** 2).mean() * 100.0 for t in thresholds])
