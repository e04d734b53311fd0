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
    first. Distances are computed in float64 (``|q|² - 2 q·d + |d|²``) block by block; the
    k smallest are selected, then ordered by (distance, index), and a tie across the k-th place
    is resolved by index too (the result equals a full stable sort).
    """
    db, dn = _prepare(db)
    queries, qn = _prepare(queries)
    if len(queries) and db.shape[1] != queries.shape[1]:
        raise InputError(
            f"descriptor shapes do not match: database {db.shape}, queries {queries.shape}",
            source="descriptors",
        )
    out = np.empty((len(queries), min(k, len(db))), dtype=np.int64)
    for s in range(0, len(queries), block):
        q = queries[s : s + block]
        out[s : s + len(q)] = _rank(qn[s : s + block, None] - 2.0 * (q @ db.T) + dn[None, :], k)
    return out


def _prepare(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float64 copy [N, D] and squared norms [N] of a descriptor array."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise InputError(f"descriptors must be [N, D], got shape {x.shape}", "descriptors")
    return x, np.einsum("ij,ij->i", x, x)


def _rank(d2: np.ndarray, k: int) -> np.ndarray:
    """int64 [M, min(k, N)]: column indices of the k smallest of each row of ``d2`` [M, N],
    ordered by (value, index): exact, ties to the lower index, also across the k-th place."""
    m, n = d2.shape
    kk = min(k, n)
    if kk == 0:
        return np.empty((m, 0), dtype=np.int64)
    if kk == n:
        return np.argsort(d2, axis=1, kind="stable")
    part = np.argpartition(d2, kk - 1, axis=1)[:, :kk]
    dist = np.take_along_axis(d2, part, axis=1)
    out = np.take_along_axis(part, np.lexsort((part, dist), axis=-1), axis=1)
    # rows where more than k values are <= the k-th one: a tie straddles the cut, sort fully
    kth = dist.max(axis=1)
    tied = np.flatnonzero((d2 <= kth[:, None]).sum(axis=1) > kk)
    if len(tied):
        out[tied] = np.argsort(d2[tied], axis=1, kind="stable")[:, :kk]
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
    neighbours = np.asarray(neighbours, dtype=np.int64)
    if neighbours.ndim != 2 or len(neighbours) != len(truth):
        raise InputError(
            f"{len(neighbours)} ranked lists for {len(truth)} queries", source="neighbours"
        )
    n1 = one_percent_n(db_size, one_percent)
    ranked = neighbours[:, :num_neighbours]
    m = len(ranked)
    lens = np.fromiter((len(t) for t in truth), dtype=np.int64, count=m)
    evaluated = lens > 0
    n_eval = int(evaluated.sum())
    if n_eval == 0:
        return None
    # hit[q, r]: ranked[q, r] is a true match of q; keys q * (db_size + 1) + index, vectorised
    stride = int(max(db_size, int(ranked.max(initial=0)) + 1)) + 1
    flat = np.fromiter((x for t in truth for x in t), dtype=np.int64, count=int(lens.sum()))
    if len(flat) and (flat.min() < 0 or flat.max() >= db_size):
        raise InputError(f"ground truth index outside the database (0..{db_size - 1})", "truth")
    true_keys = np.repeat(np.arange(m), lens) * stride + flat
    keys = np.arange(m)[:, None] * stride + ranked
    hit = np.isin(keys, true_keys) & (ranked >= 0)
    any_hit = hit.any(axis=1)
    first = np.where(any_hit, hit.argmax(axis=1), -1)[evaluated]
    counts = np.bincount(first[first >= 0], minlength=num_neighbours)[:num_neighbours]
    recall = np.cumsum(counts.astype(np.float64)) / n_eval * 100.0
    pct = int(((first >= 0) & (first < n1)).sum())
    return PairRecall(
        db=db,
        query=query,
        recall_at_n=recall,
        recall_at_1pct=pct / n_eval * 100.0,
        n_queries=n_eval,
        one_percent_n=n1,
        top1_correct=first == 0,
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
    block: int = 256,
) -> RecallResult:
    """The benchmark's recall over every ordered pair of runs (database i, queries j), i != j.

    ``db_desc[i]``: float32 [N_i, D] descriptors of run i's database; ``query_desc[j]``: float32
    [M_j, D] of run j's queries; ``truth[j][i][q]``: true indices into database i for query q
    of run j (``EvaluationSet.truth`` from ``pnvlad_service.data.splits``). Exact search (numpy,
    float64). Returns the averages over the scorable pairs (see the module docstring).
    """
    if len(db_desc) != len(query_desc) or len(truth) != len(query_desc):
        raise InputError(
            f"{len(db_desc)} databases, {len(query_desc)} query sets and {len(truth)} truth "
            "sets: expected one of each per run",
            source="descriptors",
        )
    dbp = [_prepare(d) for d in db_desc]
    qp = [_prepare(q) for q in query_desc]
    dims = {x.shape[1] for x, _ in dbp + qp if len(x)}
    if len(dims) > 1:
        raise InputError(f"descriptors of different dimensions {sorted(dims)}", "descriptors")
    for j, t in enumerate(truth):
        for i in range(len(db_desc)):
            if i == j:
                continue
            if i not in t:
                raise InputError(f"no ground truth of query run {j} in database run {i}", "truth")
            if len(t[i]) != len(query_desc[j]):
                raise InputError(
                    f"query run {j}: {len(query_desc[j])} descriptors but {len(t[i])} truth lists",
                    source="truth",
                )
    # every database stacked once: one matrix product per query run, sliced per pair
    all_db = np.concatenate([x for x, _ in dbp]) if dbp else np.empty((0, 0))
    all_dn = np.concatenate([n for _, n in dbp]) if dbp else np.empty(0)
    offsets = np.cumsum([0] + [len(x) for x, _ in dbp])
    scored: dict[tuple[int, int], PairRecall] = {}
    skipped: list[tuple[int, int]] = []
    runs = range(len(query_desc))
    if progress:
        from pnvlad_service.progress import tqdm

        runs = tqdm(runs, desc="recall", unit="query run")
    for j in runs:
        q, qn = qp[j]
        todo = [i for i in range(len(db_desc)) if i != j and any(len(x) for x in truth[j][i])]
        skipped.extend((i, j) for i in range(len(db_desc)) if i != j and i not in todo)
        if not todo:
            continue
        ranked: dict[int, list[np.ndarray]] = {i: [] for i in todo}
        for s in range(0, len(q), block):
            qb = q[s : s + block]
            d2 = qn[s : s + block, None] - 2.0 * (qb @ all_db.T) + all_dn[None, :]
            for i in todo:
                ranked[i].append(_rank(d2[:, offsets[i] : offsets[i + 1]], num_neighbours))
        for i in todo:
            pr = pair_recall_from_neighbours(
                np.concatenate(ranked[i]),
                truth[j][i],
                len(db_desc[i]),
                num_neighbours=num_neighbours,
                one_percent=one_percent,
                db=i,
                query=j,
            )
            assert pr is not None
            scored[(i, j)] = pr
    # database-major order, as the published evaluate.py loops
    per_pair = [scored[key] for key in sorted(scored)]
    skipped.sort()
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
