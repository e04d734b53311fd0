"""``pnvlad eval``: the benchmark's recall of an encoder (a checkpoint, or the baseline).

Every unique submap of the evaluation set is read and embedded once (a query is also in its
run's database), streaming: only descriptors stay in memory (float32 [U, D], about 1 KiB a
submap), never the clouds. For each ordered pair of runs (database i, queries j), i != j, of
the same area, the queries' 25 nearest database descriptors come from a FAISS exact L2 index and
``metrics.pair_recall_from_neighbours`` scores them (recall@1..25, recall@1%, skipping queries
without ground truth); figures are averaged over pairs as BENCHMARK_FORMAT.md defines.

Extended evaluations of the paper: ``joint`` (one database of every run and area together; a
query's own run is left out of its search) and recall@1 as a function of the distance between
the query and its top-1 result.

The report is a JSON document (written atomically); ``plot_recall_curves`` and
``plot_query_map`` draw PNG figures with matplotlib (the ``plot`` extra, imported lazily).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun, load_clouds
from pnvlad_service.errors import InputError
from pnvlad_service.evaluation import metrics
from pnvlad_service.fileio import atomic_open, atomic_write_text
from pnvlad_service.index.smoothing import Smoothing
from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.models.embedding import EmbedFn, embed_in_chunks
from pnvlad_service.models.local_shape import shape_feature_fn

log = logging.getLogger(__name__)

FORMAT = "pnvlad-eval"
VERSION = 1
DEFAULT_THRESHOLDS = (2.5, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 50.0)


@dataclass(frozen=True)
class EvalEncoder:
    """What is evaluated: its embed function, the points a cloud it expects, the report's
    ``encoder`` record and the ``label`` that names it in the summary and the figures."""

    embed: EmbedFn
    num_points: int
    info: dict[str, Any]
    label: str


def model_encoder(
    model: str | Path, device: str | None = None, dtype: str = "float32"
) -> EvalEncoder:
    """A model directory or the training run that made it (``store.resolve_model_dir``),
    through the batch-norm-folded ``models.inference.Encoder`` in ``dtype`` (float32, or
    bfloat16 where the CPU has it natively); labelled with the model directory and its
    architecture. A model that turns clouds to their own heading embeds its databases at the
    headings a map is embedded at (:func:`~pnvlad_service.models.config.map_turns`), as
    ``pnvlad index build`` does."""
    from pnvlad_service.models.config import map_turns
    from pnvlad_service.models.embedding import turned_embedder
    from pnvlad_service.models.inference import Encoder
    from pnvlad_service.models.store import resolve_model_dir

    directory = resolve_model_dir(model)
    enc = Encoder.from_checkpoint(directory, device=device, batch_size=32, dtype=dtype)
    info = {
        "kind": "checkpoint",
        "path": str(directory),
        "weights_sha256": enc.weights_sha256,
        "arch": enc.cfg.arch,
        "dim": enc.dim,
        "dtype": enc.dtype,
        "map_turns": map_turns(enc.cfg),
    }
    embed = turned_embedder(enc.embed, map_turns(enc.cfg))
    return EvalEncoder(embed, enc.cfg.num_points, info, f"{directory} ({enc.cfg.arch})")


def baseline_encoder() -> EvalEncoder:
    """The training-free baseline descriptor, on whole 4096-point submaps."""
    from pnvlad_service.evaluation import baseline

    info = {"kind": "baseline", "name": "baseline"}
    return EvalEncoder(baseline.describe, SUBMAP_POINTS, info, "baseline")


def embed_paths(
    embed: EmbedFn,
    paths: Sequence[str | Path],
    num_points: int,
    *,
    chunk: int = 256,
    workers: int = 4,
    progress: bool = False,
    shape_k: int = 0,
) -> np.ndarray:
    """float32 [len(paths), D] descriptors, reading ``chunk`` submaps at a time (memory holds
    one chunk of clouds and the descriptors, never all the clouds). ``shape_k``: the clouds
    carry their local shape features, taken on the whole submaps (``load_clouds``)."""
    if not paths:
        raise InputError("nothing to embed", source="evaluation set")
    features = shape_feature_fn(shape_k)

    def load(start: int, stop: int) -> np.ndarray:
        return load_clouds(paths[start:stop], num_points, workers=workers, point_features=features)

    return embed_in_chunks(embed, len(paths), load, chunk=chunk, progress=progress)


def exact_search(db: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """int64 [Q, min(k, N)]: exact L2 nearest database rows of each query, nearest first.

    ``db`` float32 [N, T * D] holds T descriptors a row where its map was embedded at T
    headings (:func:`~pnvlad_service.models.embedding.turned_embedder`; ``queries`` [Q, D]):
    a row's distance is then its nearest heading's."""
    import faiss

    turns = db.shape[1] // queries.shape[1]
    flat = np.ascontiguousarray(db, dtype=np.float32).reshape(len(db) * turns, -1)
    index = faiss.IndexFlatL2(flat.shape[1])
    index.add(flat)
    k = min(k, len(db))
    _, idx = index.search(np.ascontiguousarray(queries, dtype=np.float32), k * turns)
    if turns == 1:
        return idx.astype(np.int64)
    return first_rows(idx // turns, k)


def first_rows(rows: np.ndarray, k: int) -> np.ndarray:
    """int64 [Q, k]: each row's first ``k`` distinct values of ``rows`` int [Q, M] (a map's
    entries met at several headings, nearest first), -1 where fewer."""
    out = np.full((len(rows), k), -1, dtype=np.int64)
    for q, row in enumerate(rows):
        seen = dict.fromkeys(int(r) for r in row if r >= 0)
        firsts = list(seen)[:k]
        out[q, : len(firsts)] = firsts
    return out


def _pairs_report(
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    members: list[int],
    thresholds: Sequence[float],
    query_hits: list[np.ndarray],
    query_counts: list[np.ndarray],
) -> dict[str, Any]:
    """Recall over ordered pairs among the runs ``members`` (indices into ``runs``)."""
    per_pair: list[metrics.PairRecall] = []
    skipped: list[tuple[int, int]] = []
    dist_curves: list[np.ndarray] = []
    for i in members:
        for j in members:
            if i == j:
                continue
            truth = [q.get(i, np.zeros(0, dtype=np.int64)) for q in runs[j].truth]
            if not any(len(t) for t in truth):
                skipped.append((i, j))
                continue
            nn = exact_search(db_desc[i], q_desc[j], metrics.NUM_NEIGHBOURS)
            pr = metrics.pair_recall_from_neighbours(nn, truth, len(db_desc[i]), db=i, query=j)
            assert pr is not None
            per_pair.append(pr)
            ev = pr.evaluated
            query_hits[j][ev] += pr.top1_correct
            query_counts[j][ev] += 1
            top1 = runs[i].db_positions[nn[ev, 0]]
            dist_curves.append(
                metrics.recall_at_1_by_distance(runs[j].query_positions[ev], top1, thresholds)
            )
    res = metrics.average_pairs(per_pair, skipped)
    out = res.to_dict()
    out["per_pair"] = [
        {**p, "db_run": runs[p["db"]].name, "query_run": runs[p["query"]].name}
        for p in out["per_pair"]
    ]
    out["recall_at_1_by_distance"] = (
        [float(x) for x in np.mean(dist_curves, axis=0)] if dist_curves else []
    )
    return out


def _joint_report(
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    thresholds: Sequence[float],
) -> dict[str, Any]:
    """One database of every run together; each query searches it without its own run."""
    offsets = np.cumsum([0] + [len(d) for d in db_desc])
    joint = np.concatenate(db_desc)
    owner = np.repeat(np.arange(len(runs)), [len(d) for d in db_desc])
    positions = np.concatenate([r.db_positions for r in runs])
    k = metrics.NUM_NEIGHBOURS
    hits = np.zeros(k)
    pct_hits = 0
    n_eval = 0
    q_xy, top1_xy = [], []
    for j, run in enumerate(runs):
        own = int(offsets[j + 1] - offsets[j])
        nn = exact_search(joint, q_desc[j], k + own)
        n1 = metrics.one_percent_n(len(joint) - own)
        for q, truth in enumerate(run.truth):
            true = np.concatenate(
                [offsets[i] + np.asarray(t, dtype=np.int64) for i, t in truth.items() if i != j]
                or [np.zeros(0, dtype=np.int64)]
            )
            if len(true) == 0:
                continue
            ranked = nn[q][(nn[q] >= 0) & (owner[nn[q]] != j)][:k]
            n_eval += 1
            where = np.flatnonzero(np.isin(ranked, true))
            if len(where):
                hits[where[0]] += 1
                pct_hits += where[0] < n1
            q_xy.append(run.query_positions[q])
            top1_xy.append(positions[ranked[0]])
    if n_eval == 0:
        return {"n_queries": 0}
    rec = np.cumsum(hits) / n_eval * 100
    return {
        "n_db": len(joint),
        "n_queries": n_eval,
        "recall_at_n": [float(x) for x in rec],
        "recall_at_1": float(rec[0]),
        "recall_at_1pct": pct_hits / n_eval * 100,
        "recall_at_1_by_distance": [
            float(x)
            for x in metrics.recall_at_1_by_distance(np.array(q_xy), np.array(top1_xy), thresholds)
        ],
    }


def evaluate_runs(
    embed: EmbedFn,
    runs: list[EvalRun],
    num_points: int,
    *,
    joint: bool = False,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    workers: int = 4,
    progress: bool = True,
    encoder_info: dict[str, Any] | None = None,
    shape_k: int = 0,
    smoothing: Smoothing | None = None,
) -> dict[str, Any]:
    """Evaluate an embedder on evaluation runs; returns the JSON-ready report.

    Top-level ``recall_at_n`` (25 floats, percent), ``recall_at_1``, ``recall_at_1pct`` average
    every scored pair of runs of the same area; ``per_area`` holds each area's figures;
    ``queries`` lists each run's query positions (UTM northing, easting) with the share of run
    pairs where its top-1 was right (for the map figure); ``joint`` the one-database figures.
    ``smoothing``: each run's database smoothed along the run (:mod:`~pnvlad_service.index.
    smoothing`), as ``pnvlad index build --smooth`` makes the map; recorded in the report.
    """
    if len(runs) < 2:
        raise InputError(f"need at least 2 runs to evaluate, got {len(runs)}", "evaluation set")
    t0 = time.monotonic()
    n_unique, db_desc, q_desc = embed_runs(
        embed, runs, num_points, workers, progress, shape_k, smoothing
    )
    return evaluate_embedded(
        runs,
        db_desc,
        q_desc,
        joint=joint,
        thresholds=thresholds,
        encoder_info=encoder_info,
        num_points=num_points,
        n_unique=n_unique,
        seconds_embedding=time.monotonic() - t0,
        smoothing=smoothing,
    )


def evaluate_embedded(
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    *,
    joint: bool = False,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    encoder_info: dict[str, Any] | None = None,
    num_points: int = SUBMAP_POINTS,
    n_unique: int = 0,
    seconds_embedding: float = 0.0,
    smoothing: Smoothing | None = None,
) -> dict[str, Any]:
    """:func:`evaluate_runs` from descriptors already made (:func:`embed_runs`; ``smoothing``
    the one they were made with, recorded in the report)."""
    t0 = time.monotonic() - seconds_embedding
    t_embed = seconds_embedding
    query_hits = [np.zeros(len(r.query_paths)) for r in runs]
    query_counts = [np.zeros(len(r.query_paths)) for r in runs]
    areas: dict[str, list[int]] = {}
    for k, r in enumerate(runs):
        areas.setdefault(r.area, []).append(k)
    per_area = {
        a: _pairs_report(runs, db_desc, q_desc, m, thresholds, query_hits, query_counts)
        for a, m in areas.items()
    }
    pairs = [p for rep in per_area.values() for p in rep["per_pair"]]
    ran, r1p, rdist = _overall(per_area)
    report: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "encoder": encoder_info or {},
        "num_points": num_points,
        "runs": [r.name for r in runs],
        "n_runs": len(runs),
        "n_db": int(sum(len(r.db_paths) for r in runs)),
        "n_queries": int(sum(len(r.query_paths) for r in runs)),
        "n_unique_submaps": n_unique,
        "n_pairs": len(pairs),
        "n_queries_evaluated": int(sum(p["n_queries"] for p in pairs)),
        "recall_at_n": [float(x) for x in ran],
        "recall_at_1": float(ran[0]),
        "recall_at_1pct": r1p,
        "distance_thresholds_m": [float(t) for t in thresholds],
        "recall_at_1_by_distance": rdist,
        "per_area": {
            a: {k: v for k, v in rep.items() if k != "per_pair"} for a, rep in per_area.items()
        },
        "per_pair": pairs,
        "queries": _query_records(runs, query_hits, query_counts),
        "seconds_embedding": round(t_embed, 3),
        "map_smoothing": None if smoothing is None else smoothing.to_json(),
    }
    if joint:
        report["joint"] = _joint_report(runs, db_desc, q_desc, thresholds)
    report["seconds"] = round(time.monotonic() - t0, 3)
    return report


def embed_runs(
    embed: EmbedFn,
    runs: list[EvalRun],
    num_points: int,
    workers: int,
    progress: bool,
    shape_k: int = 0,
    smoothing: Smoothing | None = None,
) -> tuple[int, list[np.ndarray], list[np.ndarray]]:
    """Embed every unique submap of the runs once (a query is also in its run's database):
    (unique submaps, each run's database descriptors, each run's query descriptors). An
    ``embed`` with ``turns`` (:func:`~pnvlad_service.models.embedding.turned_embedder`) gives
    database rows of every heading and queries as they are. ``smoothing``: each run's database
    smoothed along the run (:func:`smooth_databases`)."""
    unique: dict[str, int] = {}
    for r in runs:
        for p in [*r.db_paths, *r.query_paths]:
            unique.setdefault(str(p), len(unique))
    paths = list(unique)
    log.info("embedding %d unique submaps of %d runs", len(paths), len(runs))
    desc = embed_paths(
        embed, paths, num_points, workers=workers, progress=progress, shape_k=shape_k
    )
    width = desc.shape[1] // getattr(embed, "turns", 1)
    db_desc = [desc[[unique[str(p)] for p in r.db_paths]] for r in runs]
    q_desc = [desc[[unique[str(p)] for p in r.query_paths], :width] for r in runs]
    if smoothing is not None:
        db_desc = smooth_databases(runs, db_desc, width, smoothing)
    return len(paths), db_desc, q_desc


def smooth_databases(
    runs: list[EvalRun], db_desc: list[np.ndarray], dim: int, smoothing: Smoothing
) -> list[np.ndarray]:
    """Each run's database descriptors [M, turns * dim] smoothed along the run by its
    submaps' positions, as ``pnvlad index build --smooth`` smooths a map of those runs."""
    return [
        smoothing.apply(d, dim, np.zeros(len(d), dtype=np.int64), r.db_positions)
        for r, d in zip(runs, db_desc, strict=True)
    ]


def _overall(per_area: dict[str, dict[str, Any]]) -> tuple[np.ndarray, float, list[float]]:
    """recall@N, recall@1% and recall@1 by distance over every scored pair of every area (the
    areas' figures weighted by their pairs); NaN and ``[]`` when no pair was scored."""
    ks = [a for a, rep in per_area.items() if rep["n_pairs"]]
    if not ks:
        return np.full(metrics.NUM_NEIGHBOURS, np.nan), float("nan"), []
    weights = np.array([per_area[a]["n_pairs"] for a in ks], dtype=np.float64)
    ran = np.average([per_area[a]["recall_at_n"] for a in ks], axis=0, weights=weights)
    r1p = float(np.average([per_area[a]["recall_at_1pct"] for a in ks], weights=weights))
    dist = [per_area[a]["recall_at_1_by_distance"] for a in ks]
    return ran, r1p, [float(x) for x in np.average(dist, axis=0, weights=weights)]


def _query_records(
    runs: list[EvalRun], hits: list[np.ndarray], counts: list[np.ndarray]
) -> list[dict[str, Any]]:
    """Each run's query positions with the share of run pairs where the query's top-1 was
    right (``None`` where it was never scored)."""
    return [
        {
            "run": r.name,
            "area": r.area,
            "northing": [float(x) for x in r.query_positions[:, 0]],
            "easting": [float(x) for x in r.query_positions[:, 1]],
            "top1_correct_share": [
                float(h / c) if c else None for h, c in zip(hits[k], counts[k], strict=True)
            ],
        }
        for k, r in enumerate(runs)
    ]


def summary_lines(label: str, report: dict[str, Any]) -> list[str]:
    """The report in a few lines: ``label``'s recall over all run pairs, then each area's (when
    there are several) and the joint database's (when evaluated)."""
    sm = report.get("map_smoothing")
    smoothed = f", map smoothed ({sm['radius_m']:g} m, weight {sm['weight']:g})" if sm else ""
    lines = [
        f"{label}: {_fmt(report)} over {report['n_pairs']} run pairs "
        f"({report['n_queries_evaluated']} queries{smoothed})"
    ]
    if len(report["per_area"]) > 1:
        lines += [f"  {area}: {_fmt(a)}" for area, a in report["per_area"].items()]
    if "joint" in report and report["joint"].get("n_queries"):
        lines.append(f"  joint database: {_fmt(report['joint'])}")
    return lines


def _fmt(r: dict[str, Any]) -> str:
    return f"recall@1 {r['recall_at_1']:.2f} %, recall@1% {r['recall_at_1pct']:.2f} %"


def write_report(report: dict[str, Any], path: str | Path) -> Path:
    """Write the report as indented JSON, atomically (NaN written as null)."""

    def clean(x: Any) -> Any:
        if isinstance(x, float) and not np.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list):
            return [clean(v) for v in x]
        return x

    atomic_write_text(path, json.dumps(clean(report), indent=1) + "\n")
    return Path(path)


def read_report(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("report not found", path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc}", path) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} report", path)
    return doc


def _pyplot() -> Any:
    from pnvlad_service.extras import pyplot

    return pyplot("Evaluation figures")


def plot_recall_curves(
    reports: Sequence[tuple[str, dict[str, Any]]], path: str | Path, title: str = ""
) -> Path:
    """PNG of recall@N (N = 1..25) of one or more reports, one line each, labelled."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=120)
    for label, rep in reports:
        r = rep["recall_at_n"]
        ax.plot(range(1, len(r) + 1), r, marker="o", ms=3, label=f"{label} (@1 {r[0]:.1f})")
    ax.set_xlabel("N (number of top database candidates)")
    ax.set_ylabel("recall@N (%)")
    ax.set_xlim(1, 25)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)


def plot_query_map(report: dict[str, Any], path: str | Path) -> Path:
    """PNG map of the queries (easting, northing in metres) coloured by the share of run pairs
    where their top-1 was correct (green: always, red: never; grey: no ground truth)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 6), dpi=120)
    e, n, s = [], [], []
    for q in report["queries"]:
        e.extend(q["easting"])
        n.extend(q["northing"])
        s.extend(np.nan if v is None else v for v in q["top1_correct_share"])
    e_a, n_a, s_a = np.array(e), np.array(n), np.array(s, dtype=np.float64)
    none = np.isnan(s_a)
    if none.any():
        ax.scatter(e_a[none], n_a[none], s=6, c="lightgrey", label="no ground truth")
    sc = ax.scatter(e_a[~none], n_a[~none], s=8, c=s_a[~none], cmap="RdYlGn", vmin=0, vmax=1)
    fig.colorbar(sc, ax=ax, label="share of run pairs with a correct top-1")
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.set_title(f"queries: recall@1 {report['recall_at_1']:.1f} %")
    fig.tight_layout()
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)


def write_figures(
    label: str,
    report: dict[str, Any],
    folder: str | Path,
    others: Sequence[tuple[str, dict[str, Any]]] = (),
) -> None:
    """Into ``folder``: ``recall_at_n.png`` (``report`` as ``label`` beside the ``others``),
    ``query_map.png`` and, for several scored areas, ``recall_at_n_by_area.png``."""
    folder = Path(folder)
    plot_recall_curves([(label, report), *others], folder / "recall_at_n.png")
    plot_query_map(report, folder / "query_map.png")
    areas = [(a, r) for a, r in report["per_area"].items() if r.get("n_pairs")]
    if len(areas) > 1:
        plot_recall_curves(areas, folder / "recall_at_n_by_area.png", title=label)
