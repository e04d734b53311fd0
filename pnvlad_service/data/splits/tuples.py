"""Training tuples: for every training submap, its positives and (as a complement) negatives.

Training layout, submaps outside the test regions, all runs of a dataset pooled, runs sorted,
CSV row order: positives of i are the other submaps j with ``d(i, j) <= pos_radius`` (10 m,
inclusive); negatives those with ``d(i, j) > neg_radius`` (50 m). Every submap is kept as an
entry, as in the published pickle; the rule "an anchor needs at least 2 positives" is the
trainer's (``TrainingTuples.anchors(min_positives=2)``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pnvlad_service.data.splits.geometry import within_radius
from pnvlad_service.data.splits.regions import TestRegions
from pnvlad_service.data.tree import BenchmarkTree, Kind
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

#: Defaults of the published scripts, metres.
POS_RADIUS = 10.0
NEG_RADIUS = 50.0


@dataclass
class TrainingTuples:
    """Training tuples of one dataset, indexed 0..N-1 (runs sorted, CSV row order).

    ``files``: relative submap paths [N]; ``northing``/``easting``: float64 [N] UTM metres
    (``None`` when imported from a pickle without a tree); ``positives[i]``: sorted int64
    indices within ``pos_radius`` (i itself excluded); ``near[i]``: sorted int64 indices within
    ``neg_radius`` (i included): the negatives of i are every index *not* in ``near[i]``,
    stored as the complement because that list is short and the negatives are not.
    """

    dataset: str
    files: list[str]
    positives: list[np.ndarray]
    near: list[np.ndarray]
    northing: np.ndarray | None = None
    easting: np.ndarray | None = None
    pos_radius: float | None = POS_RADIUS
    neg_radius: float | None = NEG_RADIUS

    def __len__(self) -> int:
        return len(self.files)

    def negatives(self, i: int) -> np.ndarray:
        """Sorted int64 indices of the negatives of ``i`` (farther than ``neg_radius``)."""
        mask = np.ones(len(self), dtype=bool)
        mask[self.near[i]] = False
        return np.flatnonzero(mask)

    def anchors(self, min_positives: int = 2) -> np.ndarray:
        """int64 indices usable as anchors: at least ``min_positives`` positives and one
        negative (the published training skips the others)."""
        n = len(self)
        ok = [
            i for i in range(n) if len(self.positives[i]) >= min_positives and len(self.near[i]) < n
        ]
        return np.asarray(ok, dtype=np.int64)


def build_training_tuples(
    tree: BenchmarkTree,
    dataset: str,
    regions: TestRegions,
    *,
    pos_radius: float = POS_RADIUS,
    neg_radius: float = NEG_RADIUS,
    inside: bool = False,
    runs: Sequence[str] | None = None,
    kind: Kind = "train",
) -> TrainingTuples:
    """Training tuples from the training-layout submaps of ``dataset``, all runs pooled.

    ``inside=False`` keeps the submaps outside the test regions (``training_queries_baseline``);
    ``inside=True`` those inside (the published ``test_queries_baseline``). ``runs`` restricts
    the runs (default: every run with the training layout, sorted).
    """
    if not 0 <= pos_radius <= neg_radius:
        raise InputError(
            f"need 0 <= pos_radius <= neg_radius, got {pos_radius} and {neg_radius}", "radius"
        )
    chosen = tree.runs(dataset) if runs is None else list(runs)
    files: list[str] = []
    north: list[np.ndarray] = []
    east: list[np.ndarray] = []
    for run in chosen:
        if not tree.has(dataset, run, kind):
            log.warning("%s/%s: no %s-layout CSV, skipped", dataset, run, kind)
            continue
        subs = tree.submaps(dataset, run, kind)
        loc = tree.locations(dataset, run, kind)
        keep = regions.contains(loc.northing, loc.easting) == inside
        files.extend(s.path for s, k in zip(subs, keep, strict=True) if k)
        north.append(loc.northing[keep])
        east.append(loc.easting[keep])
    n = np.concatenate(north) if north else np.empty(0)
    e = np.concatenate(east) if east else np.empty(0)
    pos = within_radius(n, e, n, e, pos_radius)
    pos = [p[p != i] for i, p in enumerate(pos)]
    near = within_radius(n, e, n, e, neg_radius)
    tuples = TrainingTuples(dataset, files, pos, near, n, e, float(pos_radius), float(neg_radius))
    log.info(
        "%s: %d %s tuples, %d with >= 2 positives",
        dataset,
        len(tuples),
        "test" if inside else "training",
        len(tuples.anchors(2)),
    )
    return tuples
