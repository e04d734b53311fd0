"""The published pickles: written from our splits and read, safely, into them.

``training_queries_*.pickle`` / ``test_queries_*.pickle`` hold ``{index: {'query', 'positives',
'negatives'}}``; ``<name>_evaluation_database.pickle`` and ``<name>_evaluation_query.pickle``
one dict per run. They are read with :func:`pnvlad_service.io.pickles.safe_load`, which refuses
every class, and checked (keys 0..n-1, indices in range).
"""

from __future__ import annotations

import io
import logging
import math
import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.splits.build import Splits
from pnvlad_service.data.splits.evaluation import EvaluationSet, RunSubmaps
from pnvlad_service.data.splits.tuples import TrainingTuples
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_open
from pnvlad_service.io.pickles import dump_plain, safe_load

log = logging.getLogger(__name__)


def _write_tuples_pickle(path: Path, t: TrainingTuples, progress: bool = False) -> None:
    """Stream ``{i: {'query', 'positives', 'negatives'}}`` as a protocol-2 pickle, one entry at
    a time: the negatives of a big training set do not fit in memory as Python lists."""
    n = len(t)
    it: Any = range(n)
    if progress:
        from pnvlad_service.progress import tqdm

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
