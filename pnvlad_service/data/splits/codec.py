"""Our JSON format of the splits (docs/SPLITS.md): plain or packed index lists, read strictly.

Every error reading a file names the file and the field (``training.oxford.positives[3]``).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.splits.build import Splits
from pnvlad_service.data.splits.evaluation import EvaluationSet, RunSubmaps
from pnvlad_service.data.splits.tuples import TrainingTuples
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text

log = logging.getLogger(__name__)

SPLITS_FORMAT = "pnvlad-splits"
SPLITS_VERSION = 1

#: ``save_splits`` packs index lists (docs/SPLITS.md, "Our splits file") above this many.
PACK_THRESHOLD = 100_000
_PACKING = "delta-zlib-base64"


def _floats(a: np.ndarray | None) -> list[float | None] | None:
    if a is None:
        return None
    return [None if math.isnan(x) else x for x in np.asarray(a, np.float64).tolist()]


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
