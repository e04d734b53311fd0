"""Training tuples and evaluation sets of the PointNetVLAD benchmark, in our format and theirs.

The rules follow the published scripts (``generate_training_tuples_baseline.py``,
``generate_test_sets.py``); docs/SPLITS.md states each one with its boundary:

- Test regions: a submap is inside when, for some centre (cn, ce),
  ``cn - w < northing < cn + w`` and ``ce - w < easting < ce + w`` (strict; w = 150 m).
- Training tuples (training layout, submaps outside the test regions, all runs of a dataset
  pooled, runs sorted, CSV row order): positives of i are the other submaps j with
  ``d(i, j) <= pos_radius`` (10 m, inclusive); negatives those with ``d(i, j) > neg_radius``
  (50 m). Every submap is kept as an entry, as in the published pickle; the rule "an anchor needs
  at least 2 positives" is the trainer's (``TrainingTuples.anchors(min_positives=2)``).
- Evaluation sets (test layout, per run): the database is every submap of the run; the queries
  are its submaps inside the test regions; ``truth[j][i][q]`` lists run i's database submaps
  with ``d <= truth_radius`` (25 m, inclusive) of query q of run j, for every i != j.

Distances are Euclidean in (northing, easting), computed as ``dn² + de² <= r²`` in float64 from
coordinate differences, so points exactly r metres away along one axis are inside.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import math
import os
import pickle
import re
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.tree import BenchmarkTree, Kind
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_open, atomic_write_text
from pnvlad_service.io.pickles import dump_plain, safe_load

log = logging.getLogger(__name__)

SPLITS_FORMAT = "pnvlad-splits"
SPLITS_VERSION = 1
REGIONS_FORMAT = "pnvlad-test-regions"
REGIONS_FILE = "test_regions.json"

#: Defaults of the published scripts, metres.
POS_RADIUS = 10.0
NEG_RADIUS = 50.0
TRUTH_RADIUS = 25.0
HALF_SIZE = 150.0

#: The four Oxford test regions, (northing, easting) UTM metres.
OXFORD_CENTRES: tuple[tuple[float, float], ...] = (
    (5735712.768124, 620084.402381),
    (5735611.299219, 620540.270327),
    (5735237.358209, 620543.094379),
    (5734749.303802, 619932.693364),
)
#: The in-house areas' test regions (generate_test_sets.py); business: the whole area.
INHOUSE_CENTRES: dict[str, tuple[tuple[float, float], ...]] = {
    "university": (
        (363621.292362, 142864.19756),
        (364788.795462, 143125.746609),
        (363597.507711, 144011.414174),
    ),
    "residential": (
        (360895.486453, 144999.915143),
        (362357.024536, 144894.825301),
        (361368.907155, 145209.663042),
    ),
}
#: Indices into the sorted Oxford run folders of the 23 evaluation runs (generate_test_sets.py).
OXFORD_EVAL_RUN_INDICES = (5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 22, 24, 31, 32)
OXFORD_EVAL_RUN_INDICES += (33, 38, 39, 43, 44)

_AREA_RUN = re.compile(r"^(?P<area>.+)_run\d+$")


# --------------------------------------------------------------------------------------------
# Test regions


@dataclass(frozen=True)
class TestRegions:
    """Square test regions: ``centres`` (northing, easting) UTM metres, each ± ``half_size``.

    ``everything=True`` puts every submap inside (the in-house business district).
    """

    __test__ = False  # not a pytest class

    centres: tuple[tuple[float, float], ...] = ()
    half_size: float = HALF_SIZE
    everything: bool = False

    @classmethod
    def oxford(cls) -> TestRegions:
        return cls(OXFORD_CENTRES, HALF_SIZE)

    def contains(self, northing: np.ndarray, easting: np.ndarray) -> np.ndarray:
        """bool [N]: inside any region, by the strict published test
        ``c - w < x < c + w`` on both axes."""
        n = np.asarray(northing, dtype=np.float64)
        e = np.asarray(easting, dtype=np.float64)
        if self.everything:
            return np.ones(n.shape, dtype=bool)
        inside = np.zeros(n.shape, dtype=bool)
        w = float(self.half_size)
        for cn, ce in self.centres:
            inside |= (cn - w < n) & (n < cn + w) & (ce - w < e) & (e < ce + w)
        return inside

    def to_dict(self) -> dict[str, Any]:
        return {
            "centres": [[float(a), float(b)] for a, b in self.centres],
            "half_size": float(self.half_size),
            "all": bool(self.everything),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: str | Path = "regions") -> TestRegions:
        try:
            centres = tuple((float(a), float(b)) for a, b in d.get("centres", []))
            half = float(d.get("half_size", HALF_SIZE))
            everything = bool(d.get("all", False))
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"bad test regions ({exc}); expected centres [[northing, easting], ...]", source
            ) from None
        if not math.isfinite(half) or half <= 0:
            raise InputError(f"half_size must be a positive number of metres, got {half}", source)
        if not all(math.isfinite(v) for c in centres for v in c):
            raise InputError("test region centres must be finite numbers", source)
        return cls(centres, half, everything)


def builtin_regions(dataset: str, group: str) -> TestRegions | None:
    """The published test regions for Oxford and the in-house areas, or ``None``."""
    if dataset == "oxford":
        return TestRegions.oxford()
    if dataset == "inhouse_datasets":
        if group == "business":
            return TestRegions(everything=True)
        if group in INHOUSE_CENTRES:
            return TestRegions(INHOUSE_CENTRES[group], HALF_SIZE)
    return None


def load_regions(path: str | Path) -> dict[str, TestRegions] | TestRegions:
    """Read a test-regions file: JSON (docs/SPLITS.md) or CSV ``[dataset,]northing,easting
    [,half_size]``. Returns one ``TestRegions`` for every dataset, or a mapping name -> regions.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("test regions file not found", source=path) from None
    if path.suffix.lower() == ".csv":
        return _regions_from_csv(text, path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON ({exc})", source=path) from None
    if not isinstance(doc, dict):
        raise InputError("expected a JSON object", source=path)
    if doc.get("format", REGIONS_FORMAT) != REGIONS_FORMAT:
        raise InputError(f"format is {doc.get('format')!r}, expected {REGIONS_FORMAT!r}", path)
    if "regions" in doc:
        if not isinstance(doc["regions"], dict):
            raise InputError("'regions' must map names to region sets", source=path)
        return {str(k): TestRegions.from_dict(v, path) for k, v in doc["regions"].items()}
    return TestRegions.from_dict(doc, path)


def _regions_from_csv(text: str, path: Path) -> dict[str, TestRegions] | TestRegions:
    import csv

    rows = list(csv.DictReader(text.splitlines()))
    if not rows or not {"northing", "easting"} <= set(rows[0]):
        raise InputError("expected a CSV with columns northing,easting[,half_size][,dataset]", path)
    groups: dict[str, list[tuple[float, float]]] = {}
    halves: dict[str, float] = {}
    for k, r in enumerate(rows, start=2):
        name = (r.get("dataset") or "").strip() or "*"
        try:
            c = (float(r["northing"]), float(r["easting"]))
            h = float(r["half_size"]) if (r.get("half_size") or "").strip() else HALF_SIZE
        except (TypeError, ValueError):
            raise InputError(
                f"line {k}: northing/easting/half_size must be numbers", path
            ) from None
        if halves.setdefault(name, h) != h:
            raise InputError(
                f"line {k}: one half_size per dataset, got {h} and {halves[name]}", path
            )
        groups.setdefault(name, []).append(c)
    out = {
        n: TestRegions.from_dict({"centres": c, "half_size": halves[n]}, path)
        for n, c in groups.items()
    }
    return out["*"] if list(out) == ["*"] else out


def save_regions(path: str | Path, regions: TestRegions | Mapping[str, TestRegions]) -> None:
    """Write a test-regions JSON file atomically (one set, or a mapping name -> set)."""
    doc: dict[str, Any] = {"format": REGIONS_FORMAT, "version": 1}
    if isinstance(regions, TestRegions):
        doc.update(regions.to_dict())
    else:
        doc["regions"] = {k: v.to_dict() for k, v in regions.items()}
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def resolve_regions(
    tree: BenchmarkTree,
    dataset: str,
    group: str,
    regions: TestRegions | Mapping[str, TestRegions] | None = None,
) -> TestRegions:
    """The test regions of ``group`` (an area or the dataset itself) in ``dataset``.

    In order: ``regions`` given (one set, or a mapping by group or dataset name), the tree's
    ``<root>/<dataset>/test_regions.json``, the published regions (Oxford, in-house areas).
    """
    for candidate in (regions, _tree_regions(tree, dataset)):
        if candidate is None:
            continue
        if isinstance(candidate, TestRegions):
            return candidate
        for key in (group, dataset, "*"):
            if key in candidate:
                return candidate[key]
    found = builtin_regions(dataset, group)
    if found is None:
        raise InputError(
            f"no test regions known for {group!r}: pass --regions FILE or write "
            f"{dataset}/{REGIONS_FILE} (see docs/SPLITS.md)",
            source=tree.root / dataset,
        )
    return found


def _tree_regions(tree: BenchmarkTree, dataset: str) -> dict[str, TestRegions] | TestRegions | None:
    p = tree.root / dataset / REGIONS_FILE
    return load_regions(p) if p.is_file() else None


# --------------------------------------------------------------------------------------------
# Geometry


def within_radius(
    ref_n: np.ndarray,
    ref_e: np.ndarray,
    q_n: np.ndarray,
    q_e: np.ndarray,
    radius: float,
    chunk: int = 4096,
) -> list[np.ndarray]:
    """For each query point, the sorted int64 indices of reference points with
    ``(dn)² + (de)² <= radius²`` (float64, inclusive). Coordinates in UTM metres."""
    from scipy.spatial import cKDTree

    ref_n = np.asarray(ref_n, np.float64)
    ref_e = np.asarray(ref_e, np.float64)
    q_n = np.asarray(q_n, np.float64)
    q_e = np.asarray(q_e, np.float64)
    if len(ref_n) == 0 or len(q_n) == 0:
        return [np.empty(0, np.int64) for _ in range(len(q_n))]
    # A local origin keeps the tree's arithmetic small; the exact test below decides, so the
    # tree only has to propose a superset (a slightly larger radius). Queries go in chunks to
    # bound the memory of the candidate pairs.
    on, oe = float(ref_n.min()), float(ref_e.min())
    tree = cKDTree(np.column_stack([ref_n - on, ref_e - oe]))
    r_tree = radius * (1 + 1e-9) + 1e-6
    r2 = float(radius) ** 2
    out: list[np.ndarray] = []
    for s in range(0, len(q_n), chunk):
        qn, qe = q_n[s : s + chunk], q_e[s : s + chunk]
        qtree = cKDTree(np.column_stack([qn - on, qe - oe]))
        pairs = tree.sparse_distance_matrix(qtree, r_tree, output_type="ndarray")
        ri = pairs["i"].astype(np.int64)
        qi = pairs["j"].astype(np.int64)
        keep = (ref_n[ri] - qn[qi]) ** 2 + (ref_e[ri] - qe[qi]) ** 2 <= r2
        # sort by (query, reference) through one int64 key: faster than a two-key lexsort
        key = qi[keep] * len(ref_n) + ri[keep]
        key.sort()
        qi, ri = np.divmod(key, len(ref_n))
        counts = np.bincount(qi, minlength=len(qn))
        out.extend(np.split(ri, np.cumsum(counts)[:-1]))
    return out


# --------------------------------------------------------------------------------------------
# Training tuples


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


# --------------------------------------------------------------------------------------------
# Evaluation sets


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
) -> list[EvaluationSet]:
    """Evaluation sets of ``dataset``: one per area for in-house style runs (``<area>_run<k>``),
    else one for the dataset. ``runs`` restricts the runs (default: every run with the test
    layout, sorted). Test regions resolved by ``resolve_regions``."""
    chosen = [r for r in (tree.runs(dataset) if runs is None else runs)]
    chosen = [r for r in chosen if tree.has(dataset, r, "test")]
    out = []
    for group, group_runs in evaluation_groups(dataset, chosen).items():
        reg = resolve_regions(tree, dataset, group, regions)
        out.append(
            build_evaluation_set(
                tree, dataset, group_runs, reg, name=group, truth_radius=truth_radius
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Splits: our JSON format


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
) -> Splits:
    """Training tuples, test tuples and evaluation sets of every (or the named) dataset.

    Runs named ``<area>_run<k>`` are grouped by area, each group keyed by its area name;
    otherwise everything is keyed by the dataset name. ``published`` picks the runs the
    published scripts used (``published_runs``); by default every run is used.
    """
    tree = BenchmarkTree(root)
    names = list(datasets) if datasets else tree.datasets
    splits = Splits(
        params={
            "pos_radius": float(pos_radius),
            "neg_radius": float(neg_radius),
            "truth_radius": float(truth_radius),
            "published_runs": bool(published),
            "regions": {},
        }
    )
    for d in names:
        train_runs: Sequence[str] = tree.runs(d)
        eval_runs: Sequence[str] | None = None
        if published:
            train_runs, eval_runs = published_runs(tree, d)
        train_runs = [r for r in train_runs if tree.has(d, r, "train")]
        for g, g_runs in (evaluation_groups(d, train_runs) if train_runs else {}).items():
            reg = resolve_regions(tree, d, g, regions)
            splits.params["regions"][g] = reg.to_dict()
            kw: dict[str, Any] = dict(pos_radius=pos_radius, neg_radius=neg_radius, runs=g_runs)
            splits.training[g] = build_training_tuples(tree, d, reg, **kw)
            splits.test_tuples[g] = build_training_tuples(tree, d, reg, inside=True, **kw)
        sets = build_evaluation_sets(tree, d, regions, truth_radius=truth_radius, runs=eval_runs)
        for es in sets:
            if es.name in splits.evaluation:
                raise InputError(f"two evaluation sets named {es.name!r}", source=tree.root)
            splits.evaluation[es.name] = es
            splits.params["regions"].setdefault(
                es.name, resolve_regions(tree, d, es.name, regions).to_dict()
            )
    return splits


def _floats(a: np.ndarray | None) -> list[float | None] | None:
    if a is None:
        return None
    return [None if math.isnan(x) else x for x in np.asarray(a, np.float64).tolist()]


#: ``save_splits`` packs index lists (docs/SPLITS.md, "Packed index lists") above this many.
PACK_THRESHOLD = 100_000
_PACKING = "delta-zlib-base64"


def _encode(a: np.ndarray) -> str:
    return base64.b64encode(zlib.compress(a.astype("<i4").tobytes(), 6)).decode("ascii")


def pack_lists(lists: Sequence[np.ndarray]) -> dict[str, Any]:
    """Pack index lists: ``lengths`` int32 [n] and ``deltas`` int32 [sum of lengths] (each
    list's first index, then the differences to the previous one), little-endian,
    zlib-compressed, base64-encoded (docs/SPLITS.md). Sorted lists give small deltas that
    compress about 30x."""
    lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
    flat = np.concatenate(lists).astype(np.int64) if len(lists) else np.empty(0, np.int64)
    deltas = np.diff(flat, prepend=0)
    starts = np.cumsum(lengths) - lengths
    nonempty = starts[lengths > 0]
    deltas[nonempty] = flat[nonempty]
    return {"packing": _PACKING, "lengths": _encode(lengths), "deltas": _encode(deltas)}


def _lists_to_json(lists: Sequence[np.ndarray], pack: bool) -> Any:
    return pack_lists(lists) if pack else [x.tolist() for x in lists]


def _tuples_to_json(t: TrainingTuples, pack: bool = False) -> dict[str, Any]:
    return {
        "dataset": t.dataset,
        "pos_radius": t.pos_radius,
        "neg_radius": t.neg_radius,
        "files": t.files,
        "northing": _floats(t.northing),
        "easting": _floats(t.easting),
        "positives": _lists_to_json(t.positives, pack),
        "near": _lists_to_json(t.near, pack),
    }


def _run_to_json(r: RunSubmaps) -> dict[str, Any]:
    return {
        "run": r.run,
        "files": r.files,
        "northing": _floats(r.northing),
        "easting": _floats(r.easting),
    }


def _eval_to_json(es: EvaluationSet, pack: bool = False) -> dict[str, Any]:
    queries = []
    for j, q in enumerate(es.queries):
        d = _run_to_json(q)
        d["truth"] = {str(i): _lists_to_json(lists, pack) for i, lists in es.truth[j].items()}
        queries.append(d)
    return {
        "truth_radius": es.truth_radius,
        "runs": es.runs,
        "database": [_run_to_json(r) for r in es.database],
        "queries": queries,
    }


def _count_indices(splits: Splits) -> int:
    n = 0
    for t in [*splits.training.values(), *splits.test_tuples.values()]:
        n += sum(len(x) for x in t.positives) + sum(len(x) for x in t.near)
    for es in splits.evaluation.values():
        n += sum(len(x) for tj in es.truth for lists in tj.values() for x in lists)
    return n


def splits_to_json(splits: Splits, pack: bool | None = None) -> dict[str, Any]:
    """The JSON document of ``splits`` (docs/SPLITS.md). ``pack``: index lists packed (True),
    plain lists (False), or packed when there are over ``PACK_THRESHOLD`` indices (None)."""
    if pack is None:
        pack = _count_indices(splits) > PACK_THRESHOLD
    return {
        "format": SPLITS_FORMAT,
        "version": SPLITS_VERSION,
        "params": splits.params,
        "training": {k: _tuples_to_json(v, pack) for k, v in splits.training.items()},
        "test_tuples": {k: _tuples_to_json(v, pack) for k, v in splits.test_tuples.items()},
        "evaluation": {k: _eval_to_json(v, pack) for k, v in splits.evaluation.items()},
    }


def save_splits(path: str | Path, splits: Splits, *, pack: bool | None = None) -> None:
    """Write ``splits`` as our JSON format (docs/SPLITS.md), atomically. ``pack`` as in
    ``splits_to_json``: big index lists are stored packed, small ones as readable lists."""
    text = json.dumps(splits_to_json(splits, pack), separators=(",", ":"), allow_nan=False)
    atomic_write_text(path, text + "\n")
    log.info("wrote %s (%.1f MB)", path, len(text) / 1e6)


class _Reader:
    """Typed access to a parsed JSON document; every error names the file and the field."""

    def __init__(self, source: Path) -> None:
        self.source = source

    def fail(self, where: str, msg: str) -> InputError:
        return InputError(f"{where}: {msg}", source=self.source)

    def get(self, d: Any, key: str, typ: type | tuple[type, ...], where: str) -> Any:
        if not isinstance(d, dict) or key not in d:
            raise self.fail(where, f"missing field {key!r}")
        v = d[key]
        if not isinstance(v, typ):
            raise self.fail(f"{where}.{key}", f"expected {typ}, got {type(v).__name__}")
        return v

    def floats(self, v: Any, n: int, where: str) -> np.ndarray | None:
        if v is None:
            return None
        if not isinstance(v, list) or len(v) != n:
            raise self.fail(where, f"expected a list of {n} numbers")
        try:
            return np.asarray([math.nan if x is None else float(x) for x in v], np.float64)
        except (TypeError, ValueError):
            raise self.fail(where, "expected numbers") from None

    def unpack(self, v: Any, dtype: str, where: str) -> np.ndarray:
        if not isinstance(v, str):
            raise self.fail(where, "expected a base64 string")
        try:
            raw = zlib.decompress(base64.b64decode(v, validate=True))
        except (ValueError, zlib.error) as exc:
            raise self.fail(where, f"cannot decode ({exc})") from None
        size = np.dtype(dtype).itemsize
        if len(raw) % size:
            raise self.fail(where, f"{len(raw)} bytes is not a whole number of {dtype} values")
        return np.frombuffer(raw, dtype=dtype).astype(np.int64)

    def packed_lists(self, v: dict, n_lists: int, bound: int, where: str) -> list[np.ndarray]:
        if v.get("packing") != _PACKING:
            raise self.fail(where, f"unknown packing {v.get('packing')!r}, expected {_PACKING!r}")
        lengths = self.unpack(v.get("lengths"), "<i4", f"{where}.lengths")
        deltas = self.unpack(v.get("deltas"), "<i4", f"{where}.deltas")
        if len(lengths) != n_lists or np.any(lengths < 0) or lengths.sum() != len(deltas):
            raise self.fail(where, f"lengths do not describe {n_lists} lists of {len(deltas)}")
        csum = np.cumsum(deltas)
        starts = np.cumsum(lengths) - lengths
        before = np.where(starts > 0, csum[np.maximum(starts - 1, 0)] if len(csum) else 0, 0)
        flat = csum - np.repeat(before, lengths)
        if len(flat) and (flat.min() < 0 or flat.max() >= bound):
            raise self.fail(where, f"index out of range 0..{bound - 1}")
        return np.split(flat, np.cumsum(lengths)[:-1]) if n_lists else []

    def index_lists(self, v: Any, n_lists: int, bound: int, where: str) -> list[np.ndarray]:
        if isinstance(v, dict):
            return self.packed_lists(v, n_lists, bound, where)
        if not isinstance(v, list) or len(v) != n_lists:
            raise self.fail(where, f"expected {n_lists} lists of indices")
        out = []
        for k, lst in enumerate(v):
            if not isinstance(lst, list) or not all(type(x) is int for x in lst):
                raise self.fail(f"{where}[{k}]", "expected a list of integers")
            a = np.asarray(lst, dtype=np.int64)
            if len(a) and (a.min() < 0 or a.max() >= bound):
                raise self.fail(f"{where}[{k}]", f"index out of range 0..{bound - 1}")
            out.append(a)
        return out


def _tuples_from_json(r: _Reader, d: Any, where: str) -> TrainingTuples:
    files = r.get(d, "files", list, where)
    n = len(files)
    if not all(isinstance(f, str) for f in files):
        raise r.fail(f"{where}.files", "expected strings")
    return TrainingTuples(
        dataset=str(d.get("dataset", where)),
        files=files,
        positives=r.index_lists(d.get("positives"), n, n, f"{where}.positives"),
        near=r.index_lists(d.get("near"), n, n, f"{where}.near"),
        northing=r.floats(d.get("northing"), n, f"{where}.northing"),
        easting=r.floats(d.get("easting"), n, f"{where}.easting"),
        pos_radius=d.get("pos_radius"),
        neg_radius=d.get("neg_radius"),
    )


def _run_from_json(r: _Reader, d: Any, where: str) -> RunSubmaps:
    files = r.get(d, "files", list, where)
    if not all(isinstance(f, str) for f in files):
        raise r.fail(f"{where}.files", "expected strings")
    n = len(files)
    north = r.floats(d.get("northing"), n, f"{where}.northing")
    east = r.floats(d.get("easting"), n, f"{where}.easting")
    nan = np.full(n, np.nan)
    return RunSubmaps(
        str(d.get("run", "")), files, nan if north is None else north, nan if east is None else east
    )


def _eval_from_json(r: _Reader, d: Any, name: str) -> EvaluationSet:
    where = f"evaluation.{name}"
    db = [
        _run_from_json(r, x, f"{where}.database[{k}]")
        for k, x in enumerate(r.get(d, "database", list, where))
    ]
    qs_raw = r.get(d, "queries", list, where)
    if len(qs_raw) != len(db):
        raise r.fail(where, f"{len(db)} databases but {len(qs_raw)} query sets")
    queries, truth = [], []
    for j, qd in enumerate(qs_raw):
        w = f"{where}.queries[{j}]"
        q = _run_from_json(r, qd, w)
        t_raw = r.get(qd, "truth", dict, w)
        t: dict[int, list[np.ndarray]] = {}
        for i in range(len(db)):
            if i == j:
                continue
            if str(i) not in t_raw:
                raise r.fail(f"{w}.truth", f"missing run {i}")
            t[i] = r.index_lists(t_raw[str(i)], len(q), len(db[i]), f"{w}.truth.{i}")
        queries.append(q)
        truth.append(t)
    runs = d.get("runs") or [x.run for x in db]
    return EvaluationSet(name, list(runs), db, queries, truth, d.get("truth_radius"))


def splits_from_json(doc: Any, source: str | Path = "splits") -> Splits:
    r = _Reader(Path(source))
    if not isinstance(doc, dict) or doc.get("format") != SPLITS_FORMAT:
        raise r.fail("format", f"not a {SPLITS_FORMAT} file")
    if doc.get("version") != SPLITS_VERSION:
        raise r.fail("version", f"version {doc.get('version')!r}, this code reads {SPLITS_VERSION}")
    return Splits(
        training={
            k: _tuples_from_json(r, v, f"training.{k}")
            for k, v in r.get(doc, "training", dict, "document").items()
        },
        test_tuples={
            k: _tuples_from_json(r, v, f"test_tuples.{k}")
            for k, v in doc.get("test_tuples", {}).items()
        },
        evaluation={
            k: _eval_from_json(r, v, k)
            for k, v in r.get(doc, "evaluation", dict, "document").items()
        },
        params=dict(doc.get("params", {})),
    )


def load_splits(path: str | Path) -> Splits:
    """Read our JSON splits file; ``InputError`` naming the file and field when malformed."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("splits file not found", source=path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON ({exc})", source=path) from None
    return splits_from_json(doc, path)


# --------------------------------------------------------------------------------------------
# The published pickles


def _write_tuples_pickle(path: Path, t: TrainingTuples, progress: bool = False) -> None:
    """Stream ``{i: {'query', 'positives', 'negatives'}}`` as a protocol-2 pickle, one entry at
    a time: the negatives of a big training set do not fit in memory as Python lists."""
    n = len(t)
    it: Any = range(n)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=path.name, unit="tuple")
    with atomic_open(path, "wb") as fh:
        fh.write(pickle.PROTO + b"\x02" + pickle.EMPTY_DICT)
        batch = 0
        for i in it:
            if batch == 0:
                fh.write(pickle.MARK)
            buf = io.BytesIO()
            p = pickle.Pickler(buf, protocol=2)
            p.fast = True  # no memo: entries are independent and never shared
            p.dump(
                (
                    i,
                    {
                        "query": t.files[i],
                        "positives": t.positives[i].tolist(),
                        "negatives": t.negatives(i).tolist(),
                    },
                )
            )
            # strip PROTO (2 bytes), the TUPLE2 opcode and STOP: leave key and value on the stack
            body = buf.getvalue()
            assert body[-2:-1] == pickle.TUPLE2 and body[-1:] == pickle.STOP
            fh.write(body[2:-2])
            batch += 1
            if batch == 1000:
                fh.write(pickle.SETITEMS)
                batch = 0
        if batch:
            fh.write(pickle.SETITEMS)
        fh.write(pickle.STOP)


def evaluation_to_pickles(es: EvaluationSet) -> tuple[list[dict], list[dict]]:
    """The published ``(<name>_evaluation_database, <name>_evaluation_query)`` structures."""

    def entry(r: RunSubmaps, k: int) -> dict:
        return {
            "query": r.files[k],
            "northing": float(r.northing[k]),
            "easting": float(r.easting[k]),
        }

    database = [{k: entry(r, k) for k in range(len(r))} for r in es.database]
    queries = []
    for j, q in enumerate(es.queries):
        run: dict[int, dict] = {}
        for k in range(len(q)):
            e: dict[Any, Any] = entry(q, k)
            for i, lists in es.truth[j].items():
                e[i] = lists[k].tolist()
            run[k] = e
        queries.append(run)
    return database, queries


def export_pickles(splits: Splits, out_dir: str | Path, *, progress: bool = False) -> list[Path]:
    """Write the published pickles into ``out_dir`` (plain types only, atomic each).

    With one training dataset: ``training_queries_baseline.pickle`` and
    ``test_queries_baseline.pickle`` (the published names); with several, one pair per dataset
    prefixed ``<dataset>_``. Per evaluation set: ``<name>_evaluation_database.pickle`` and
    ``<name>_evaluation_query.pickle``. Negatives are written sorted (the published script
    shuffled them). Returns the paths written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    single = len(splits.training) == 1
    for label, table in (("training", splits.training), ("test", splits.test_tuples)):
        for name, t in table.items():
            fname = f"{label}_queries_baseline.pickle"
            path = out / (fname if single else f"{name}_{fname}")
            _write_tuples_pickle(path, t, progress)
            written.append(path)
    for name, es in splits.evaluation.items():
        db, q = evaluation_to_pickles(es)
        for suffix, obj in (("database", db), ("query", q)):
            path = out / f"{name}_evaluation_{suffix}.pickle"
            dump_plain(obj, path)
            written.append(path)
    log.info("wrote %d pickle(s) to %s", len(written), out)
    return written


def _entries(obj: Any, source: Path, where: str) -> list[dict]:
    """Entries of a published ``dict index -> entry`` as a list, checking keys are 0..n-1."""
    if not isinstance(obj, dict):
        raise InputError(
            f"{where}: expected a dict index -> entry, got {type(obj).__name__}", source
        )
    n = len(obj)
    if set(obj) != set(range(n)):
        raise InputError(f"{where}: keys are not the integers 0..{n - 1}", source)
    out = []
    for k in range(n):
        e = obj[k]
        if not isinstance(e, dict) or not isinstance(e.get("query"), str):
            raise InputError(f"{where}[{k}]: expected a dict with a 'query' path", source)
        out.append(e)
    return out


def _index_list(v: Any, bound: int, source: Path, where: str, unique: bool = True) -> np.ndarray:
    """A published list of indices as int64 (sorted and de-duplicated with ``unique``)."""
    if not isinstance(v, list):
        raise InputError(f"{where}: expected a list of integers", source)
    if not v:
        return np.empty(0, dtype=np.int64)
    try:
        a = np.asarray(v)
    except (OverflowError, ValueError):
        a = np.asarray([0.5])  # mixed or huge values: refused below
    if a.ndim != 1 or a.dtype.kind not in "iu":  # floats, bools, strings, nested lists
        raise InputError(f"{where}: expected a list of integers", source)
    a = a.astype(np.int64)
    if a.min() < 0 or a.max() >= bound:
        raise InputError(f"{where}: index out of range 0..{bound - 1}", source)
    return np.unique(a) if unique else a


def tuples_from_pickle(path: str | Path, name: str | None = None) -> TrainingTuples:
    """Read a published ``training_queries_*.pickle`` (safely) as ``TrainingTuples``.

    Coordinates are unknown (``None``); ``near`` is the complement of the negatives.
    """
    path = Path(path)
    entries = _entries(safe_load(path), path, "training tuples")
    n = len(entries)
    files = [e["query"] for e in entries]
    pos, near = [], []
    for k, e in enumerate(entries):
        pos.append(_index_list(e.get("positives"), n, path, f"entry {k} positives"))
        neg = _index_list(e.get("negatives"), n, path, f"entry {k} negatives", unique=False)
        mask = np.ones(n, dtype=bool)
        mask[neg] = False
        near.append(np.flatnonzero(mask))
    heads = {f.split("/", 1)[0] for f in files}
    dataset = name or (heads.pop() if len(heads) == 1 else path.stem)
    return TrainingTuples(dataset, files, pos, near, None, None, None, None)


def evaluation_from_pickles(
    database_path: str | Path, query_path: str | Path, name: str | None = None
) -> EvaluationSet:
    """Read a published ``<name>_evaluation_database/query.pickle`` pair (safely)."""
    dbp, qp = Path(database_path), Path(query_path)
    db_obj, q_obj = safe_load(dbp), safe_load(qp)
    for obj, p in ((db_obj, dbp), (q_obj, qp)):
        if not isinstance(obj, list):
            raise InputError(f"expected a list with one dict per run, got {type(obj).__name__}", p)
    if len(db_obj) != len(q_obj):
        raise InputError(f"{len(db_obj)} database runs but {len(q_obj)} query runs", qp)

    def run_of(entries: list[dict], p: Path, where: str) -> RunSubmaps:
        files = [e["query"] for e in entries]
        try:
            north = np.asarray([float(e.get("northing", math.nan)) for e in entries], np.float64)
            east = np.asarray([float(e.get("easting", math.nan)) for e in entries], np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: northing/easting must be numbers", p) from None
        parts = files[0].split("/") if files else []
        return RunSubmaps(parts[1] if len(parts) > 2 else "", files, north, east)

    database = [run_of(_entries(r, dbp, f"run {i}"), dbp, f"run {i}") for i, r in enumerate(db_obj)]
    queries, truth = [], []
    for j, r in enumerate(q_obj):
        entries = _entries(r, qp, f"run {j}")
        queries.append(run_of(entries, qp, f"run {j}"))
        t: dict[int, list[np.ndarray]] = {}
        for i in range(len(database)):
            if i == j:
                continue
            t[i] = []
            for k, e in enumerate(entries):
                if i not in e:
                    raise InputError(f"run {j} query {k}: no ground truth for run {i}", qp)
                t[i].append(_index_list(e[i], len(database[i]), qp, f"run {j} query {k} [{i}]"))
        truth.append(t)
    runs = [
        d.run or (q.run) or str(k) for k, (d, q) in enumerate(zip(database, queries, strict=True))
    ]
    guess = qp.name.removesuffix("_evaluation_query.pickle")
    return EvaluationSet(name or guess, runs, database, queries, truth, None)


def import_pickles(paths: Sequence[str | Path]) -> Splits:
    """Convert published pickles to ``Splits``. ``paths``: files or folders; recognised by name:
    ``*training_queries*.pickle`` (training tuples), ``*test_queries*.pickle`` (test tuples),
    ``<name>_evaluation_database.pickle`` with its ``<name>_evaluation_query.pickle``."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files.extend(sorted(p.glob("*.pickle")))
        elif p.is_file():
            files.append(p)
        else:
            raise InputError("no such file or folder", source=p)
    splits = Splits(params={"imported_from": [str(f) for f in files]})
    used = set()
    for f in files:
        if "training_queries" in f.name or "test_queries" in f.name:
            t = tuples_from_pickle(f)
            table = splits.training if "training_queries" in f.name else splits.test_tuples
            key = t.dataset if t.dataset not in table else f.stem
            table[key] = t
            used.add(f)
        elif f.name.endswith("_evaluation_database.pickle"):
            q = f.with_name(f.name.replace("_evaluation_database.", "_evaluation_query."))
            if q not in files and not q.is_file():
                raise InputError(f"no matching {q.name} beside it", source=f)
            es = evaluation_from_pickles(f, q)
            splits.evaluation[es.name] = es
            used.update({f, q})
    unknown = [f for f in files if f not in used]
    if not used:
        raise InputError(
            "no published pickle recognised by name", source=", ".join(map(str, paths))
        )
    for f in unknown:
        log.warning("%s: not a recognised benchmark pickle name, ignored", f)
    return splits
