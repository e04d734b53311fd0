"""Evaluation sets: per run a database and its queries, with the ground truth in every other run.

Test layout, per run: the database is every submap of the run; the queries are its submaps
inside the test regions; ``truth[j][i][q]`` lists run i's database submaps with
``d <= truth_radius`` (25 m, inclusive) of query q of run j, for every i != j.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pnvlad_service.data.splits.geometry import within_radius
from pnvlad_service.data.splits.regions import TestRegions, resolve_regions
from pnvlad_service.data.tree import BenchmarkTree, Kind

log = logging.getLogger(__name__)

#: Ground truth radius of the published scripts, metres.
TRUTH_RADIUS = 25.0

_AREA_RUN = re.compile(r"^(?P<area>.+)_run\d+$")


@dataclass
class RunSubmaps:
    """Submaps of one run: relative ``files`` [N] and float64 [N] UTM ``northing``, ``easting``
    (``nan`` where unknown)."""

    run: str
    files: list[str]
    northing: np.ndarray
    easting: np.ndarray

    def __len__(self) -> int:
        return len(self.files)


@dataclass
class EvaluationSet:
    """The evaluation set of one dataset or area: per run a database and queries.

    ``truth[j][i][q]``: sorted int64 indices into ``database[i]`` of the submaps within
    ``truth_radius`` of query q of run j, for every i != j (the metrics' ``Truth``).
    """

    name: str
    runs: list[str]
    database: list[RunSubmaps]
    queries: list[RunSubmaps]
    truth: list[dict[int, list[np.ndarray]]]
    truth_radius: float | None = TRUTH_RADIUS

    def query_db_index(self, j: int) -> np.ndarray:
        """int64 [M_j]: where each query of run j sits in run j's database (-1: absent)."""
        pos = {f: k for k, f in enumerate(self.database[j].files)}
        return np.asarray([pos.get(f, -1) for f in self.queries[j].files], dtype=np.int64)

    def n_queries(self) -> int:
        return sum(len(q) for q in self.queries)


def evaluation_groups(dataset: str, runs: Sequence[str]) -> dict[str, list[str]]:
    """Group runs named ``<area>_run<k>`` by area (the in-house layout); otherwise one group
    named after the dataset."""
    matches = [_AREA_RUN.match(r) for r in runs]
    if runs and all(matches):
        groups: dict[str, list[str]] = {}
        for r, m in zip(runs, matches, strict=True):
            assert m is not None
            groups.setdefault(m.group("area"), []).append(r)
        return groups
    return {dataset: list(runs)}


def build_evaluation_set(
    tree: BenchmarkTree,
    dataset: str,
    runs: Sequence[str],
    regions: TestRegions,
    *,
    name: str | None = None,
    truth_radius: float = TRUTH_RADIUS,
    kind: Kind = "test",
) -> EvaluationSet:
    """One evaluation set from the test-layout submaps of ``runs`` (in the given order)."""
    database: list[RunSubmaps] = []
    queries: list[RunSubmaps] = []
    for run in runs:
        subs = tree.submaps(dataset, run, kind)
        loc = tree.locations(dataset, run, kind)
        database.append(RunSubmaps(run, [s.path for s in subs], loc.northing, loc.easting))
        inside = regions.contains(loc.northing, loc.easting)
        queries.append(
            RunSubmaps(
                run,
                [s.path for s, k in zip(subs, inside, strict=True) if k],
                loc.northing[inside],
                loc.easting[inside],
            )
        )
    # one radius search per database run, over the queries of every run at once
    truth: list[dict[int, list[np.ndarray]]] = [{} for _ in queries]
    q_n = np.concatenate([q.northing for q in queries]) if queries else np.empty(0)
    q_e = np.concatenate([q.easting for q in queries]) if queries else np.empty(0)
    starts = np.cumsum([0] + [len(q) for q in queries])
    for i, db in enumerate(database):
        found = within_radius(db.northing, db.easting, q_n, q_e, truth_radius)
        for j in range(len(queries)):
            if j != i:
                truth[j][i] = found[starts[j] : starts[j + 1]]
    es = EvaluationSet(name or dataset, list(runs), database, queries, truth, float(truth_radius))
    log.info(
        "%s: %d runs, %d database submaps, %d queries",
        es.name,
        len(runs),
        sum(len(d) for d in database),
        es.n_queries(),
    )
    return es


def build_evaluation_sets(
    tree: BenchmarkTree,
    dataset: str,
    regions: TestRegions | Mapping[str, TestRegions] | None = None,
    *,
    truth_radius: float = TRUTH_RADIUS,
    runs: Sequence[str] | None = None,
    kind: Kind = "test",
) -> list[EvaluationSet]:
    """Evaluation sets of ``dataset``: one per area for in-house style runs (``<area>_run<k>``),
    else one for the dataset. ``runs`` restricts the runs (default: every run with the
    ``kind`` layout, the test one unless told, sorted). Test regions resolved by
    ``resolve_regions``."""
    chosen = [r for r in (tree.runs(dataset) if runs is None else runs)]
    chosen = [r for r in chosen if tree.has(dataset, r, kind)]
    out = []
    for group, group_runs in evaluation_groups(dataset, chosen).items():
        reg = resolve_regions(tree, dataset, group, regions)
        out.append(
            build_evaluation_set(
                tree, dataset, group_runs, reg, name=group, truth_radius=truth_radius, kind=kind
            )
        )
    return out
