"""The splits of a tree: training and test tuples and evaluation sets of every dataset.

The rules follow the published scripts (``generate_training_tuples_baseline.py``,
``generate_test_sets.py``); docs/SPLITS.md states each one with its boundary.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.splits.evaluation import (
    TRUTH_RADIUS,
    EvaluationSet,
    RunSubmaps,
    build_evaluation_sets,
    evaluation_groups,
)
from pnvlad_service.data.splits.regions import TestRegions, resolve_regions
from pnvlad_service.data.splits.tuples import (
    NEG_RADIUS,
    POS_RADIUS,
    TrainingTuples,
    build_training_tuples,
)
from pnvlad_service.data.tree import BenchmarkTree, Kind
from pnvlad_service.errors import InputError

#: Indices into the sorted Oxford run folders of the 23 evaluation runs (generate_test_sets.py).
OXFORD_EVAL_RUN_INDICES = (5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 22, 24, 31, 32)
OXFORD_EVAL_RUN_INDICES += (33, 38, 39, 43, 44)


@dataclass
class Splits:
    """Everything ``pnvlad data splits`` makes: training and test tuples per dataset,
    evaluation sets by name, and the parameters used."""

    training: dict[str, TrainingTuples] = field(default_factory=dict)
    test_tuples: dict[str, TrainingTuples] = field(default_factory=dict)
    evaluation: dict[str, EvaluationSet] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)


def published_runs(tree: BenchmarkTree, dataset: str) -> tuple[list[str], list[str]]:
    """The runs the published scripts chose: ``(training runs, evaluation runs)``.

    They index ``sorted(os.listdir(<dataset>))`` (files included): Oxford trains on every entry
    but the last (``range(len - 1)``) and evaluates on entries ``OXFORD_EVAL_RUN_INDICES``; the
    in-house evaluation takes entries 1-4 (business), 5-9 (residential), 10-14 (university)
    and trains on every run. ``InputError`` where the folder does not list like the benchmark.
    """
    listing = sorted(os.listdir(tree.root / dataset))
    if dataset == "oxford":
        train, picks = listing[:-1], OXFORD_EVAL_RUN_INDICES
    elif dataset == "inhouse_datasets":
        train, picks = tree.runs(dataset), tuple(range(1, 15))
    else:
        raise InputError(
            f"the published scripts chose runs only for oxford and inhouse_datasets, not "
            f"{dataset!r}",
            source=tree.root / dataset,
        )
    if len(listing) <= max(picks):
        raise InputError(
            f"{len(listing)} entries, the published run indices go up to {max(picks)}",
            source=tree.root / dataset,
        )
    evaluation = [listing[k] for k in picks]
    runs = set(tree.runs(dataset))
    odd = [r for r in [*train, *evaluation] if r not in runs]
    if odd:
        raise InputError(
            f"entries {odd[:3]} picked by the published indices are not run folders",
            source=tree.root / dataset,
        )
    return list(train), evaluation


def build_splits(
    root: str | Path,
    datasets: Sequence[str] | None = None,
    regions: TestRegions | Mapping[str, TestRegions] | None = None,
    *,
    pos_radius: float = POS_RADIUS,
    neg_radius: float = NEG_RADIUS,
    truth_radius: float = TRUTH_RADIUS,
    published: bool = False,
    keyframes: bool = False,
    query_runs: Sequence[str] | None = None,
) -> Splits:
    """Training tuples, test tuples and evaluation sets of every (or the named) dataset.

    Runs named ``<area>_run<k>`` are grouped by area, each group keyed by its area name;
    otherwise everything is keyed by the dataset name. ``published`` picks the runs the
    published scripts used (``published_runs``); by default every run is used. ``keyframes``:
    every tuple and set from the keyframe maps (single scans, ``pointcloud_keyframes``) in
    place of the training and test layouts, for encoders of single scans.

    ``query_runs`` (a map and its query drives, as a user's own map is: no test regions): the
    training tuples come from every place of the other runs (the map runs) and no query run;
    each query run is evaluated against the map runs, every entry of it a query
    (:func:`hold_out`). Positions are the runs' aligned ones where they have them
    (:mod:`.poses`).
    """
    if query_runs is not None:
        return _map_and_queries(root, datasets, query_runs, pos_radius=pos_radius,
                                neg_radius=neg_radius, truth_radius=truth_radius,
                                keyframes=keyframes)  # fmt: skip
    train_kind: Kind = "keyframe" if keyframes else "train"
    test_kind: Kind = "keyframe" if keyframes else "test"
    tree = BenchmarkTree(root)
    names = list(datasets) if datasets else tree.datasets
    splits = Splits(
        params={
            "pos_radius": float(pos_radius),
            "neg_radius": float(neg_radius),
            "truth_radius": float(truth_radius),
            "published_runs": bool(published),
            "kind": "keyframe" if keyframes else "submap",
            "regions": {},
        }
    )
    for d in names:
        train_runs: Sequence[str] = tree.runs(d)
        eval_runs: Sequence[str] | None = None
        if published:
            train_runs, eval_runs = published_runs(tree, d)
        train_runs = [r for r in train_runs if tree.has(d, r, train_kind)]
        for g, g_runs in (evaluation_groups(d, train_runs) if train_runs else {}).items():
            reg = resolve_regions(tree, d, g, regions)
            splits.params["regions"][g] = reg.to_dict()
            kw: dict[str, Any] = dict(
                pos_radius=pos_radius, neg_radius=neg_radius, runs=g_runs, kind=train_kind
            )
            splits.training[g] = build_training_tuples(tree, d, reg, **kw)
            splits.test_tuples[g] = build_training_tuples(tree, d, reg, inside=True, **kw)
        sets = build_evaluation_sets(
            tree, d, regions, truth_radius=truth_radius, runs=eval_runs, kind=test_kind
        )
        for es in sets:
            if es.name in splits.evaluation:
                raise InputError(f"two evaluation sets named {es.name!r}", source=tree.root)
            splits.evaluation[es.name] = es
            splits.params["regions"].setdefault(
                es.name, resolve_regions(tree, d, es.name, regions).to_dict()
            )
    return splits


def _map_and_queries(
    root: str | Path,
    datasets: Sequence[str] | None,
    query_runs: Sequence[str],
    *,
    pos_radius: float,
    neg_radius: float,
    truth_radius: float,
    keyframes: bool,
) -> Splits:
    """:func:`build_splits` of a map's runs and its query runs (``query_runs``)."""
    kind: Kind = "keyframe" if keyframes else "test"
    train_kind: Kind = "keyframe" if keyframes else "train"
    tree = BenchmarkTree(root)
    names = list(datasets) if datasets else tree.datasets
    every = {r for d in names for r in tree.runs(d)}
    unknown = [r for r in query_runs if r not in every]
    if unknown:
        raise InputError(
            f"no run {unknown[0]!r} in {', '.join(names)} (runs: {', '.join(sorted(every))})",
            "--query-run",
        )
    held = set(query_runs)
    splits = Splits(
        params={
            "pos_radius": float(pos_radius),
            "neg_radius": float(neg_radius),
            "truth_radius": float(truth_radius),
            "published_runs": False,
            "kind": "keyframe" if keyframes else "submap",
            "query_runs": sorted(held),
            "regions": {},
        }
    )
    nowhere, everywhere = TestRegions(), TestRegions(everything=True)
    for d in names:
        runs = tree.runs(d)
        map_runs = [r for r in runs if r not in held and tree.has(d, r, train_kind)]
        for g, g_runs in (evaluation_groups(d, map_runs) if map_runs else {}).items():
            splits.training[g] = build_training_tuples(
                tree, d, nowhere, pos_radius=pos_radius, neg_radius=neg_radius, runs=g_runs,
                kind=train_kind,
            )  # fmt: skip
        eval_runs = [r for r in runs if tree.has(d, r, kind)]
        if not any(r in held for r in eval_runs):
            continue
        for es in build_evaluation_sets(
            tree, d, everywhere, truth_radius=truth_radius, runs=eval_runs, kind=kind
        ):
            if es.name in splits.evaluation:
                raise InputError(f"two evaluation sets named {es.name!r}", source=tree.root)
            splits.evaluation[es.name] = hold_out(es, held)
            splits.params["regions"][es.name] = everywhere.to_dict()
    if not splits.training:
        raise InputError("every run is a query run: the map needs at least one", "--query-run")
    return splits


def hold_out(es: EvaluationSet, query_runs: set[str]) -> EvaluationSet:
    """``es`` with queries only in ``query_runs``, each searched in the other runs (the map)
    alone: a map run's queries dropped, a query run's truth in another query run emptied (no
    pair of theirs is scored)."""
    queries = [
        q if q.run in query_runs else RunSubmaps(q.run, [], q.northing[:0], q.easting[:0])
        for q in es.queries
    ]
    none = np.empty(0, np.int64)
    truth = [
        {
            i: t if es.runs[i] not in query_runs else [none] * len(queries[j])
            for i, t in es.truth[j].items()
        }
        if es.runs[j] in query_runs
        else {i: [] for i in es.truth[j]}
        for j in range(len(es.runs))
    ]
    return EvaluationSet(es.name, es.runs, es.database, queries, truth, es.truth_radius)
