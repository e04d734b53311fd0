"""Submaps for training and evaluation: who is near whom, and the clouds themselves in RAM.

- :class:`TrainingSet`: the training submaps (paths, UTM positions) with, for every one, its
  positives (other submaps within the positive radius) and the rule for its negatives (farther
  than the negative radius). Anchors are the submaps with at least ``min_positives`` positives.
- :class:`EvalRun`: one run of an evaluation set (its database, its queries and, for every query,
  the ground truth in every other run).
- :func:`load_clouds`: read submaps into one float32 array [N, num_points, 3] with a thread pool.

Adapters from the splits (``splits.py``) and the published pickles live here too, so that
``train.py`` and ``evaluate.py`` only see these small records.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import read_bin_points

log = logging.getLogger(__name__)


@dataclass
class TrainingSet:
    """Training submaps and their neighbourhoods.

    ``paths``: N submap files. ``positions``: float64 [N, 2] UTM (northing, easting), metres.
    ``positives[i]``: int64 indices of the submaps within the positive radius of i (i excluded).
    ``near[i]`` (optional): int64 indices within the negative radius of i (i included; the
    ``splits.TrainingTuples`` form): the negatives of i are all the others. Without it, a negative
    is any submap farther than ``negative_radius`` metres from i.
    ``datasets`` (optional): (name, first, stop) of each pooled dataset's rows, in order.
    """

    paths: list[Path]
    positions: np.ndarray
    positives: list[np.ndarray]
    near: list[np.ndarray] | None = None
    negative_radius: float = 50.0
    datasets: list[tuple[str, int, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        n = len(self.paths)
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(n, 2)
        self.positives = [np.asarray(p, dtype=np.int64) for p in self.positives]
        if len(self.positives) != n:
            raise InputError(f"{len(self.positives)} positive lists for {n} submaps", "positives")
        if self.near is not None:
            self.near = [np.asarray(p, dtype=np.int64) for p in self.near]

    def __len__(self) -> int:
        return len(self.paths)

    def anchors(self, min_positives: int = 2) -> np.ndarray:
        """int64 indices of the submaps with at least ``min_positives`` positives."""
        return np.array(
            [i for i, p in enumerate(self.positives) if len(p) >= min_positives], dtype=np.int64
        )

    def negative_mask(self, i: int, cand: np.ndarray) -> np.ndarray:
        """bool [len(cand)]: which candidate indices are negatives of submap i."""
        cand = np.asarray(cand, dtype=np.int64)
        if self.near is not None:
            return ~np.isin(cand, self.near[i])
        d2 = ((self.positions[cand] - self.positions[i]) ** 2).sum(axis=1)
        return d2 > self.negative_radius**2

    def sample_negatives(self, rng: np.random.Generator, i: int, k: int) -> np.ndarray:
        """Up to ``k`` distinct random negatives of submap i (int64, in random order)."""
        n = len(self)
        if k >= n // 2:
            cand = rng.permutation(n)
            return cand[self.negative_mask(i, cand)][:k]
        out: list[np.ndarray] = []
        seen = 0
        for _ in range(8):  # rejection sampling; negatives are the vast majority of submaps
            cand = rng.choice(n, size=min(n, 2 * k), replace=False)
            cand = cand[self.negative_mask(i, cand)]
            out.append(cand)
            seen = len(np.unique(np.concatenate(out)))
            if seen >= k:
                break
        allc = np.concatenate(out)
        _, first = np.unique(allc, return_index=True)
        return allc[np.sort(first)][:k]


@dataclass
class EvalRun:
    """One run of an evaluation set.

    ``db_paths`` [M] with ``db_positions`` float64 [M, 2] (UTM northing, easting, metres);
    ``query_paths`` [Q] with ``query_positions`` [Q, 2]; ``truth[q]`` maps another run's index
    to the int64 indices of its database submaps within 25 m of query q.
    """

    name: str
    db_paths: list[Path]
    db_positions: np.ndarray
    query_paths: list[Path]
    query_positions: np.ndarray
    truth: list[dict[int, np.ndarray]]
    area: str = ""


def read_submap(path: str | Path) -> np.ndarray:
    """One submap as float32 [P, 3]: ``.bin`` (float64 x, y, z interleaved, any number of
    points: :func:`pnvlad_service.io.submap.read_bin_points`), ``.npy`` or any format
    :func:`pnvlad_service.io.readers.read_points` knows. :func:`fit_points` then brings it to
    the model's point count."""
    path = Path(path)
    try:
        if path.suffix == ".bin":
            return read_bin_points(path).astype(np.float32)
        if path.suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
            return np.asarray(arr, dtype=np.float32).reshape(-1, 3)
    except FileNotFoundError:
        raise InputError("submap file not found", path) from None
    from pnvlad_service.io.readers import read_points

    return np.asarray(read_points(path), dtype=np.float32)[:, :3]


def fit_points(points: np.ndarray, num_points: int, seed: int = 0) -> np.ndarray:
    """float32 [num_points, 3]: a fixed random subset of the rows (or all of them, repeated
    when too few). The subset depends only on ``seed`` and the cloud size, so it is the same at
    training and evaluation."""
    if len(points) == num_points:
        return points
    return points[fit_indices(len(points), num_points, seed)]


def fit_indices(n: int, num_points: int, seed: int = 0) -> np.ndarray:
    """The sorted int64 rows :func:`fit_points` keeps of a cloud of ``n`` points."""
    if n == 0:
        raise InputError("empty submap", "points")
    if n == num_points:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    idx = rng.permutation(n)[:num_points] if n > num_points else rng.choice(n, num_points)
    return np.sort(idx)


def load_clouds(
    paths: Sequence[str | Path],
    num_points: int,
    *,
    workers: int = 4,
    progress: bool = False,
    desc: str = "loading submaps",
    point_features: Callable[[np.ndarray], np.ndarray] | None = None,
) -> np.ndarray:
    """Read submaps into float32 [N, num_points, 3] (about 48 KiB a 4096-point submap).

    ``point_features``: a function of a whole submap's points [n, 3] that gives each point F
    features [n, F] (F is read off its answer for an empty cloud); the clouds are then
    [N, num_points, 3 + F], the features taken before the submap is cut to ``num_points``, so
    that a model trained on a subset sees the neighbourhoods it meets on whole submaps (the
    local shape features of ``models/local_shape.py``, which the stages after this one pass)."""
    width = 3
    if point_features is not None:
        width += int(point_features(np.zeros((0, 3), dtype=np.float32)).shape[1])
    out = np.empty((len(paths), num_points, width), dtype=np.float32)

    def one(i: int) -> None:
        points = read_submap(paths[i])
        rows = fit_indices(len(points), num_points)
        out[i, :, :3] = points[rows]
        if point_features is not None:
            out[i, :, 3:] = point_features(points)[rows]

    _run_parallel(one, len(paths), workers, progress, desc)
    return out


def _run_parallel(
    fn: Callable[[int], None], n: int, workers: int, progress: bool, desc: str
) -> None:
    from pnvlad_service.progress import tqdm

    bar = tqdm(total=n, desc=desc, unit="submap", disable=not progress, leave=False)
    try:
        if workers <= 1:
            for i in range(n):
                fn(i)
                bar.update()
        else:
            with ThreadPoolExecutor(workers) as pool:
                for _ in pool.map(fn, range(n)):
                    bar.update()
    finally:
        bar.close()


# ---------------------------------------------------------------------------------------------
# Adapters: splits.py (our JSON, or the published pickles imported) -> TrainingSet, EvalRun


def training_set_from_tuples(tuples: Sequence[Any], root: Path | None) -> TrainingSet:
    """One :class:`TrainingSet` pooling ``splits.TrainingTuples`` of one or more datasets
    (indices offset per dataset; no tuple crosses datasets). Paths are resolved under ``root``."""
    paths: list[Path] = []
    pos: list[np.ndarray] = []
    near: list[np.ndarray] = []
    xy: list[np.ndarray] = []
    datasets: list[tuple[str, int, int]] = []
    for t in tuples:
        off = len(paths)
        n = len(t)
        datasets.append((str(t.dataset), off, off + n))
        paths.extend(_resolve(root, f) for f in t.files)
        pos.extend(np.asarray(p, dtype=np.int64) + off for p in t.positives)
        near.extend(np.asarray(p, dtype=np.int64) + off for p in t.near)
        if t.northing is not None and t.easting is not None:
            xy.append(np.stack([t.northing, t.easting], axis=1))
        else:
            xy.append(np.full((n, 2), np.nan))
    positions = np.concatenate(xy) if xy else np.zeros((0, 2))
    return TrainingSet(paths, positions, pos, near, datasets=datasets)


def eval_runs_from_set(es: Any, root: Path | None) -> list[EvalRun]:
    """``splits.EvaluationSet`` -> one :class:`EvalRun` per run (``area`` = the set's name)."""
    runs = []
    for j, (db, q) in enumerate(zip(es.database, es.queries, strict=True)):
        truth = [
            {i: np.asarray(t[k], dtype=np.int64) for i, t in es.truth[j].items()}
            for k in range(len(q))
        ]
        runs.append(
            EvalRun(
                name=es.runs[j],
                db_paths=[_resolve(root, f) for f in db.files],
                db_positions=np.stack([db.northing, db.easting], axis=1).reshape(-1, 2),
                query_paths=[_resolve(root, f) for f in q.files],
                query_positions=np.stack([q.northing, q.easting], axis=1).reshape(-1, 2),
                truth=truth,
                area=es.name,
            )
        )
    return runs


def _resolve(root: Path | None, rel: str | Path) -> Path:
    p = Path(rel)
    if p.is_absolute() or root is None:
        return p
    return root.joinpath(*str(rel).split("/"))


def load_splits_any(
    root: Path | None, splits: Path | None = None, pickles: Path | None = None
) -> Any:
    """``splits.Splits`` from our JSON (``splits``), the published pickles (``pickles``: a
    folder or file), or, with neither, built from the tree at ``root`` (its test regions)."""
    from pnvlad_service.data import splits as sp

    if splits is not None and pickles is not None:
        raise InputError("give either a splits file or the pickles, not both", "splits")
    if splits is not None:
        return sp.load_splits(splits)
    if pickles is not None:
        return sp.import_pickles([pickles])
    if root is None:
        raise InputError("need a benchmark tree (--root) or a splits file", "data.root")
    log.info("no splits file given: building splits from %s", root)
    return sp.build_splits(root)


def load_training_data(data: Any) -> tuple[TrainingSet, list[EvalRun]]:
    """(training set, validation runs) for a ``trainconfig.DataSection``: every training
    dataset pooled; validation runs from the first evaluation set."""
    s = load_splits_any(data.root, data.splits, data.pickles)
    if not s.training:
        raise InputError("the splits hold no training tuples", data.splits or data.root)
    root = Path(data.root) if data.root is not None else None
    ts = training_set_from_tuples(list(s.training.values()), root)
    val: list[EvalRun] = []
    if s.evaluation:
        val = eval_runs_from_set(next(iter(s.evaluation.values())), root)
    return ts, val


def load_eval_runs(
    root: Path | None,
    splits: Path | None = None,
    pickles: Path | None = None,
    sets: Sequence[str] | None = None,
) -> list[EvalRun]:
    """Every evaluation run of the splits (or only the sets named in ``sets``), each tagged with
    its set's name as ``area``; ground-truth keys are indices into the returned list."""
    s = load_splits_any(root, splits, pickles)
    names = list(s.evaluation) if not sets else list(sets)
    missing = [n for n in names if n not in s.evaluation]
    if missing:
        raise InputError(
            f"no evaluation set {missing[0]!r} (have: {', '.join(s.evaluation) or 'none'})",
            "sets",
        )
    runs: list[EvalRun] = []
    for n in names:
        # A set's ground truth names runs by their place in that set; in the joined list they
        # sit after the runs of the sets before it.
        offset = len(runs)
        for r in eval_runs_from_set(s.evaluation[n], Path(root) if root else None):
            r.truth = [{offset + i: t for i, t in q.items()} for q in r.truth]
            runs.append(r)
    if not runs:
        raise InputError("the splits hold no evaluation sets", splits or pickles or root)
    return runs
