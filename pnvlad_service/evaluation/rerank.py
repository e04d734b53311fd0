"""``pnvlad eval --rerank K``: what geometric verification adds on a benchmark.

For every ordered pair of runs of an area (database i, queries j), each query's K nearest
database submaps by descriptor are registered to it
(:func:`~pnvlad_service.localization.verify.verify.verify`, the server's own cascade) and
re-ranked by score. The report holds, averaged over pairs as the benchmark averages recall:

- recall@1 and recall@1% before and after re-ranking, and recall@K before (the ceiling);

and pooled over queries:

- the metric success rate: among the queries whose re-ranked top-1 is a true match, the share
  whose estimated query -> match transform is within 2 m and 5 degrees of the simulator's true
  relative pose (``inv(T_match) @ T_query``, from the frame sidecars' true poses), with the
  median translation and yaw errors; reversed-heading queries (true relative yaw beyond 90
  degrees) are reported on their own too;
- the precision and recall of ``verified`` (best score >= threshold): precision is the share
  of verified queries whose top-1 is a true match, coverage the share of all queries verified,
  recall the share of queries with a true top-1 that are verified;
- the threshold, when not given, chosen on the *training layout* (training submaps, outside
  the test regions; :func:`calibrate`): the smallest score whose precision there reaches
  ``target_precision``, with queries verified against far-off candidates standing in for
  the :data:`~.rerank_figures.OFF_MAP_SHARE` of queries whose place is not among their
  candidates (a model that fits its training places makes too few mistakes there to choose
  on). Test queries never choose it.

Both sides register the submaps' metres as a bundle stores them (float16 normalised points,
then the sidecar's centre and scale), so the figures are the server's. This module registers
the queries (:func:`rerank_pairs`), calibrates and assembles the report; the figures and the
threshold rule are pure functions of the outcomes in :mod:`.rerank_figures`.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun, read_submap
from pnvlad_service.data.frames import SubmapFrame
from pnvlad_service.errors import InputError
from pnvlad_service.evaluation import metrics
from pnvlad_service.evaluation.evaluate import embed_runs, exact_search
from pnvlad_service.evaluation.rerank_figures import (
    OFF_MAP_SHARE,
    SUCCESS_DEG,
    SUCCESS_M,
    TARGET_PRECISION,
    QueryOutcome,
    curve_value,
    off_map_curve,
    pose_error,
    pr_curve,
    summarise,
    threshold_on_curve,
    verified_figures,
)
from pnvlad_service.index.smoothing import Smoothing
from pnvlad_service.localization.verify.verify import Candidate, QueryCloud, VerifyConfig, verify

log = logging.getLogger(__name__)

#: Training-layout queries a run that choose the threshold. At a 99.5 % target a few wrong
#: answers move the chosen threshold: with 60 a run (1,196 queries on the benchmark preset)
#: the pose precision wobbled 99.37-99.52 % between thresholds 0.09 and 0.15 and the rule took
#: 0.15; with 150 (2,984) the curve is smooth and the rule takes 0.07 (docs/VERIFY.md).
CALIBRATION_QUERIES = 150
#: Training-layout queries a run verified as if off the map (:func:`calibrate`): each
#: registers all K candidates (none is the place), so fewer than the on-map ones.
OFF_MAP_QUERIES = 50
#: Off-map candidates are the database submaps farther than this from the query (m): twice
#: the benchmark's 25 m, so that none shares the query's place.
OFF_MAP_M = 50.0


def stored_metres(path: str | Path, frame: SubmapFrame) -> np.ndarray:
    """A submap's metres as a bundle keeps them: float16 normalised points, then the frame."""
    pts = read_submap(path).astype(np.float16).astype(np.float64)
    return frame.local_m(pts)


@dataclass
class _Store:
    """Metres and prepared clouds of the submaps met so far (a submap is a candidate of many
    queries): cleared between areas."""

    frames: dict[str, SubmapFrame]
    metres: dict[str, np.ndarray] = field(default_factory=dict)
    prepared: dict[Any, Any] = field(default_factory=dict)

    def get(self, path: Path) -> tuple[np.ndarray, SubmapFrame]:
        key = str(Path(path).resolve())
        frame = self.frames.get(key)
        if frame is None:
            raise InputError("no frame sidecar row for this submap (rebuild the tree)", path)
        if key not in self.metres:
            self.metres[key] = stored_metres(path, frame)
        return self.metres[key], frame

    def clear(self) -> None:
        self.metres.clear()
        self.prepared.clear()


def _one_query(
    q_path: Path,
    db_paths: Sequence[Path],
    ranked: np.ndarray,
    store: _Store,
    config: VerifyConfig,
) -> tuple[Any, SubmapFrame, list[SubmapFrame]]:
    """Verify one query against its first K ranked database rows."""
    q_pts, q_frame = store.get(q_path)
    cands, frames = [], []
    for rank, row in enumerate(ranked[: config.candidates], 1):
        pts, frame = store.get(db_paths[row])
        frames.append(frame)
        cands.append(Candidate(rank, pts, frame.map_pose, key=str(db_paths[row])))
    query = QueryCloud(q_pts, "centroid", "measured")
    v = verify(query, cands, config, cache=store.prepared, query_key=str(q_path))
    return v, q_frame, frames


def _outcome(
    pair: int, ranked: np.ndarray, truth: np.ndarray, n1: int, v: Any, q: SubmapFrame, dbf: list
) -> QueryOutcome:
    k = len(v.checks)  # the first k in retrieval order (the cascade may stop before K)
    true = set(int(t) for t in truth)
    after = [int(ranked[c.rank - 1]) for c in v.checks] + [int(r) for r in ranked[k:]]
    out = QueryOutcome(
        pair=pair,
        r1_before=int(ranked[0]) in true,
        r1_after=after[0] in true,
        rk_before=any(int(r) in true for r in ranked[: max(v.candidates, k)]),
        r1p_before=any(int(r) in true for r in ranked[:n1]),
        r1p_after=any(r in true for r in after[:n1]),
        best_score=v.best_score,
        confidence=v.confidence,
        registered=v.registered,
    )
    best = v.checks[0]
    match = dbf[best.rank - 1]
    if q.true_pose is not None and match.true_pose is not None:
        rel = np.linalg.inv(match.true_pose) @ q.true_pose
        t_err, yaw_err = pose_error(best.transform, rel)
        out.pose_ok = t_err < SUCCESS_M and yaw_err < SUCCESS_DEG
        if out.r1_after:
            out.t_err, out.yaw_err = t_err, yaw_err
    return out


def rerank_pairs(
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    frames: dict[str, SubmapFrame],
    config: VerifyConfig,
    *,
    progress: bool = False,
    reversed_runs: frozenset[str] = frozenset(),
    off_map_m: float | None = None,
) -> tuple[list[QueryOutcome], list[tuple[int, int]]]:
    """Every evaluated query of every ordered run pair of each area, verified; and the pairs
    (db run, query run) in the order their outcomes are numbered. A query is ``reversed``
    when its run and the database's drove the route in opposite directions
    (``reversed_runs``: the runs that drove it backwards, from ``synth.json``).

    ``off_map_m``: verify each query as if the map did not hold its place: its candidates are
    the nearest database submaps by descriptor among those farther than this from it (every
    one a wrong answer, the hardest the descriptors offer), so the outcomes sample the
    confidences of queries from off the map."""
    from pnvlad_service.progress import tqdm

    areas: dict[str, list[int]] = {}
    for k, r in enumerate(runs):
        areas.setdefault(r.area, []).append(k)
    total = sum(len(runs[j].query_paths) * (len(m) - 1) for m in areas.values() for j in m)
    bar = tqdm(total=total, desc="re-rank", unit="query", disable=not progress)
    outcomes: list[QueryOutcome] = []
    pairs: list[tuple[int, int]] = []
    store = _Store(frames)
    for members in areas.values():
        store.clear()
        for i in members:
            n1 = metrics.one_percent_n(len(db_desc[i]))
            for j in members:
                if i == j:
                    continue
                k = max(config.candidates, n1, metrics.NUM_NEIGHBOURS)
                if off_map_m is not None:  # every row ranked, the near ones dropped below
                    k = len(db_desc[i])
                nn = exact_search(db_desc[i], q_desc[j], k)
                pairs.append((i, j))
                for q, truth in enumerate(runs[j].truth):
                    bar.update(1)
                    t = truth.get(i, np.zeros(0, dtype=np.int64))
                    if len(t) == 0:
                        continue
                    ranked = nn[q][nn[q] >= 0]
                    if off_map_m is not None:
                        far = np.linalg.norm(
                            runs[i].db_positions[ranked] - runs[j].query_positions[q], axis=1
                        )
                        ranked = ranked[far > off_map_m]
                        t = np.zeros(0, dtype=np.int64)
                        if len(ranked) == 0:
                            continue
                    v, qf, dbf = _one_query(
                        runs[j].query_paths[q], runs[i].db_paths, ranked, store, config
                    )
                    out = _outcome(len(pairs) - 1, ranked, t, n1, v, qf, dbf)
                    out.reversed = (runs[i].name in reversed_runs) != (
                        runs[j].name in reversed_runs
                    )
                    outcomes.append(out)
    bar.close()
    return outcomes, pairs


def rerank_report(
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    frames: dict[str, SubmapFrame],
    config: VerifyConfig,
    *,
    calibration: dict[str, Any] | None = None,
    progress: bool = False,
    reversed_runs: frozenset[str] = frozenset(),
) -> tuple[dict[str, Any], list[QueryOutcome]]:
    """The ``rerank`` section of an evaluation report, overall and per area."""
    t0 = time.monotonic()
    outcomes, pairs = rerank_pairs(
        runs, db_desc, q_desc, frames, config, progress=progress, reversed_runs=reversed_runs
    )
    area_of = [runs[j].area for _, j in pairs]
    per_area = {
        a: summarise(
            [o for o in outcomes if area_of[o.pair] == a], config.threshold, config.candidates
        )
        for a in dict.fromkeys(area_of)
    }
    rep = {
        **summarise(outcomes, config.threshold, config.candidates),
        "per_area": per_area,
        "pr_curve": pr_curve(outcomes),
        "calibration": calibration,
        "errors": [[o.t_err, o.yaw_err, o.reversed] for o in outcomes if o.t_err is not None],
        "seconds": round(time.monotonic() - t0, 3),
    }
    return rep, outcomes


# --------------------------------------------------------------------------------------------
# Choosing the threshold on the training layout
# --------------------------------------------------------------------------------------------


def training_runs(tuples: Any, root: Path, area: str, positives_m: float = 25.0) -> list[EvalRun]:
    """The training submaps of one dataset as evaluation runs (each run its own database and
    queries; truth: the other runs' submaps within ``positives_m``)."""
    files = list(tuples.files)
    if tuples.northing is None:
        raise InputError("training tuples without positions cannot choose a threshold", area)
    by_run: dict[str, list[int]] = {}
    for k, f in enumerate(files):
        by_run.setdefault(f.split("/")[1], []).append(k)
    names = sorted(by_run)
    pos = np.stack([tuples.northing, tuples.easting], 1)
    runs = []
    for name in names:
        idx = by_run[name]
        truth = []
        for k in idx:
            d = {}
            for i, other in enumerate(names):
                if other == name:
                    continue
                o = np.asarray(by_run[other])
                near = np.flatnonzero(np.linalg.norm(pos[o] - pos[k], axis=1) <= positives_m)
                d[i] = near.astype(np.int64)
            truth.append(d)
        paths = [root / files[k] for k in idx]
        runs.append(EvalRun(name, paths, pos[idx], paths, pos[idx], truth, area))
    return runs


def subsample_queries(runs: list[EvalRun], per_run: int, seed: int = 0) -> list[EvalRun]:
    """The same runs with at most ``per_run`` queries each (seeded), databases whole."""
    rng = np.random.default_rng(seed)
    out = []
    for r in runs:
        keep = np.sort(rng.permutation(len(r.query_paths))[:per_run])
        out.append(
            EvalRun(
                r.name,
                r.db_paths,
                r.db_positions,
                [r.query_paths[k] for k in keep],
                r.query_positions[keep],
                [r.truth[k] for k in keep],
                r.area,
            )
        )
    return out


def calibrate(
    embed_runs: Callable[[list[EvalRun]], tuple[list[np.ndarray], list[np.ndarray]]],
    runs: list[EvalRun],
    frames: dict[str, SubmapFrame],
    config: VerifyConfig,
    *,
    target: float = TARGET_PRECISION,
    progress: bool = False,
    off_map_runs: list[EvalRun] | None = None,
    off_map_share: float = OFF_MAP_SHARE,
) -> dict[str, Any]:
    """Choose the threshold on training-layout ``runs`` (:func:`training_runs`): verify their
    queries as the test is verified and take :func:`choose_threshold`; with ``off_map_runs``
    (training-layout runs too, fewer queries) and ``off_map_share`` > 0, their queries are
    also verified against candidates farther than :data:`OFF_MAP_M` and weigh in as a
    ``off_map_share`` of queries off the map (:func:`off_map_curve`)."""
    db_desc, q_desc = embed_runs(runs)
    outcomes, _ = rerank_pairs(runs, db_desc, q_desc, frames, config, progress=progress)
    off: list[QueryOutcome] = []
    if off_map_runs and off_map_share > 0.0:
        turns = getattr(embed_runs, "turns", 1)
        off_db, off_q = _descriptors_of(off_map_runs, runs, db_desc, embed_runs, turns)
        off, _ = rerank_pairs(
            off_map_runs, off_db, off_q, frames, config, progress=progress, off_map_m=OFF_MAP_M
        )
    curve = pr_curve(outcomes)
    mixed = off_map_curve(curve, off, off_map_share) if off else curve
    # Pose precision when every frame has a true pose, else place precision.
    threshold = threshold_on_curve(mixed, target)
    at = verified_figures(outcomes, threshold)
    report: dict[str, Any] = {
        "threshold": threshold,
        "target_precision": target * 100.0,
        "n_queries": len(outcomes),
        "at_threshold": at,
        "pr_curve": curve,
    }
    if off:
        row = next(c for c in mixed if c["threshold"] == threshold)  # a grid threshold
        at["off_map_accept"] = row["off_map_accept"]
        at["expected_precision"] = curve_value(row, "pose_precision")
        report["off_map"] = {
            "share": off_map_share,
            "distance_m": OFF_MAP_M,
            "n_queries": len(off),
            "curve": [[c["threshold"], c["off_map_accept"]] for c in mixed],
        }
    return report


def _descriptors_of(
    wanted: list[EvalRun],
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    embed_runs: Callable[[list[EvalRun]], tuple[list[np.ndarray], list[np.ndarray]]],
    turns: int = 1,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The database and query descriptors of ``wanted``, taken from ``runs``' database
    descriptors where every submap of ``wanted`` is among them (the off-map queries are the
    calibration's own training layout), else embedded. ``turns``: database rows hold that many
    headings' descriptors, a query only the first."""
    rows = {
        str(p): d[k] for r, d in zip(runs, db_desc, strict=True) for k, p in enumerate(r.db_paths)
    }
    if not all(str(p) in rows for r in wanted for p in (*r.db_paths, *r.query_paths)):
        return embed_runs(wanted)
    empty = np.zeros((0, db_desc[0].shape[1]), np.float32)

    def stack(ps: list[Path]) -> np.ndarray:
        return np.stack([rows[str(p)] for p in ps]) if ps else empty

    width = db_desc[0].shape[1] // turns
    return [stack(r.db_paths) for r in wanted], [stack(r.query_paths)[:, :width] for r in wanted]


def evaluate_rerank(
    embed: Any,
    num_points: int,
    runs: list[EvalRun],
    descriptors: tuple[list[np.ndarray], list[np.ndarray]],
    root: Path,
    training: dict[str, Any],
    *,
    candidates: int,
    threshold: float | None = None,
    calibration_queries: int | None = None,
    off_map_share: float | None = None,
    workers: int = 4,
    progress: bool = False,
    query_frames: dict[str, Any] | None = None,
    smoothing: Smoothing | None = None,
) -> dict[str, Any]:
    """The ``rerank`` section of ``pnvlad eval --rerank K``: ``query_frames`` (absolute path
    -> :class:`SubmapFrame`) for queries that are not the tree's submaps (raw scans through G,
    :func:`pnvlad_service.evaluation.scan_queries.query_frames`); the threshold (``threshold``, or
    chosen on ``calibration_queries`` (None: :data:`CALIBRATION_QUERIES`) training-layout
    queries a run of each dataset of ``training``, with :data:`OFF_MAP_QUERIES` a run
    verified as if off the map weighing in as ``off_map_share`` of the queries (None:
    :data:`OFF_MAP_SHARE`; 0: none); the calibration's maps smoothed as the evaluation's
    with ``smoothing``), then :func:`rerank_report` on the evaluation runs."""
    from pnvlad_service.data.tree import BenchmarkTree

    frames = BenchmarkTree(root).frames_by_path() | (query_frames or {})
    reversed_runs = _reversed_runs(Path(root))
    if not frames:
        raise InputError(
            "re-ranking needs the tree's frame sidecars (pnvlad synth / pnvlad data prepare "
            "write them); this tree has none",
            root,
        )
    calibration = None
    if threshold is None:
        per_run = CALIBRATION_QUERIES if calibration_queries is None else calibration_queries
        cal_runs, off_runs = [], []
        for area, tuples in training.items():
            layout = training_runs(tuples, Path(root), area)
            cal_runs += subsample_queries(layout, per_run)
            off_runs += subsample_queries(layout, min(per_run, OFF_MAP_QUERIES), seed=1)

        def embed_cal(rs: list[EvalRun]) -> tuple[list[np.ndarray], list[np.ndarray]]:
            _, db, q = embed_runs(embed, rs, num_points, workers, progress, smoothing=smoothing)
            return db, q

        embed_cal.turns = getattr(embed, "turns", 1)  # type: ignore[attr-defined]

        calibration = calibrate(
            embed_cal,
            cal_runs,
            frames,
            VerifyConfig(candidates=candidates),
            progress=progress,
            off_map_runs=off_runs,
            off_map_share=OFF_MAP_SHARE if off_map_share is None else off_map_share,
        )
        threshold = calibration["threshold"]
        log.info("verification threshold %.2f, chosen on the training layout", threshold)
    config = VerifyConfig(candidates=candidates, threshold=threshold)
    rep, _ = rerank_report(
        runs,
        *descriptors,
        frames,
        config,
        calibration=calibration,
        progress=progress,
        reversed_runs=reversed_runs,
    )
    # How the registration's OpenMP threads waited (``pnvlad eval --rerank`` sets PASSIVE
    # unless the user chose): it decides the run's time on shared cores, not its figures.
    rep["omp_wait_policy"] = os.environ.get("OMP_WAIT_POLICY")
    return rep


def _reversed_runs(root: Path) -> frozenset[str]:
    """The runs of a ``pnvlad synth`` tree that drove their route backwards (its
    ``synth.json``); empty for other trees."""
    import json

    path = root / "synth.json"
    if not path.is_file():
        return frozenset()
    try:
        doc = json.loads(path.read_text())
        return frozenset(str(r["run"]) for r in doc.get("runs", []) if r.get("reverse"))
    except (ValueError, KeyError, TypeError, AttributeError):
        log.warning("%s: cannot read the runs' directions", path)
        return frozenset()
