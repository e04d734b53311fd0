"""Single raw scans as queries: the benchmark's recall for what a robot actually sends.

The benchmark's queries are 20 m submaps accumulated offline. Here each query is the raw scan
at a query submap's place (``raw_scans/`` of the run, :mod:`pnvlad_service.data.scans`): the
scans inside the evaluation set's test regions, run through the filter G as the server runs a
raw scan against that map (the map folder's recorded G: a range crop for keyframe maps), in the
sensor's own frame (so an encoder must not care which way the vehicle faced). The database is
the map of the splits given: the test-layout submaps (``splits.json``) or the keyframe maps
(``splits_keyframes.json``). Ground truth: the database entries within the truth radius (25 m)
of the scan's recorded position, as for submaps.

Queries are also told apart by direction: a query is *opposite* to a database run when that
run passed the same place facing more than 90 degrees away (from the runs' own raw-scan poses),
so that reversed runs are reported apart.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.data.dataset import EvalRun
from pnvlad_service.data.frames import SubmapFrame
from pnvlad_service.data.run_folder import recorded_g_config
from pnvlad_service.data.scans import RawScan, has_raw_scans, read_raw_scans
from pnvlad_service.data.splits.geometry import within_radius
from pnvlad_service.data.splits.regions import TestRegions
from pnvlad_service.errors import InputError
from pnvlad_service.preprocess.filter_g import GConfig, scan_config

log = logging.getLogger(__name__)

#: Beyond this heading difference (degrees) a database run passed the query's place the other way.
OPPOSITE_DEG = 90.0


@dataclass
class ScanQuerySet:
    """Evaluation runs whose queries are raw scans: ``runs`` (``query_paths`` the raw scans until
    :func:`preprocess_queries` replaces them with G's output), ``scans[j]`` run j's query scans,
    ``opposite[j][i]`` bool [Q_j]: whether run i (keyed as in the truth) passed each query of
    run j the other way, the
    ``map_kind`` ("submap" or "keyframe") and the map's G (what a raw scan goes through)."""

    runs: list[EvalRun]
    scans: list[list[RawScan]]
    opposite: list[dict[int, np.ndarray]]
    map_kind: str
    g_config: GConfig
    g_frames: dict[str, tuple[list[float], float]] = field(default_factory=dict)
    window: dict[str, Any] | None = None
    drift_m: list[float] = field(default_factory=list)


def _run_dir(root: Path, db_file: str) -> Path:
    """The run folder of a database file ``dataset/run/folder/ts.bin``."""
    parts = str(db_file).split("/")
    if len(parts) < 4:
        raise InputError(f"cannot tell the run of {db_file!r}", "splits")
    return root.joinpath(*parts[:2])


def map_g_config(run_dir: Path, folder: str, map_kind: str) -> GConfig:
    """The G a map folder's entries went through (recorded by prepare), else the default of
    its kind: plain G for submaps, :func:`scan_config` for keyframes."""
    recorded = recorded_g_config(run_dir, folder)
    if recorded is not None:
        return GConfig.model_validate(recorded)
    return scan_config() if map_kind == "keyframe" else GConfig()


def _yaw(pose: np.ndarray) -> float:
    return math.degrees(math.atan2(pose[1, 0], pose[0, 0]))


def scan_query_set(
    root: str | Path, splits: Any, sets: Sequence[str] | None = None
) -> ScanQuerySet:
    """The evaluation runs of ``splits`` (``splits.Splits``; every set, or those named in
    ``sets``) with raw scans as queries; those of its ``query_runs`` alone where it names them,
    searched in the other runs. ``InputError`` naming the run when a run has no raw scans (made
    before them: regenerate, or ``pnvlad data prepare --scans``)."""
    root = Path(root)
    map_kind = str(splits.params.get("kind", "submap"))
    names = list(sets) if sets else list(splits.evaluation)
    runs: list[EvalRun] = []
    scans: list[list[RawScan]] = []
    opposite: list[dict[int, np.ndarray]] = []
    g_config: GConfig | None = None
    held = set(splits.params.get("query_runs") or ())
    for name in names:
        if name not in splits.evaluation:
            raise InputError(f"no evaluation set {name!r}", "sets")
        es = splits.evaluation[name]
        if name not in splits.params.get("regions", {}):
            raise InputError(f"the splits record no test regions for {name!r}", "splits")
        regions = TestRegions.from_dict(splits.params["regions"][name])
        offset = len(runs)
        run_dirs = [_run_dir(root, db.files[0]) for db in es.database]
        if g_config is None:
            g_config = map_g_config(run_dirs[0], es.database[0].files[0].split("/")[2], map_kind)
        raw: list[list[RawScan]] = []
        for run_dir in run_dirs:
            if not has_raw_scans(run_dir):
                raise InputError(
                    "no raw_scans.csv: this run keeps no raw scans (made before single-scan "
                    "queries: regenerate it, or pnvlad data prepare --scans)",
                    run_dir,
                )
            raw.append(read_raw_scans(run_dir))
        q_scans = []
        for run, all_scans in zip(es.runs, raw, strict=True):
            n = np.array([s.northing for s in all_scans])
            e = np.array([s.easting for s in all_scans])
            inside = regions.contains(n, e) & (not held or run in held)
            q_scans.append([s for s, k in zip(all_scans, inside, strict=True) if k])
        for j, qs in enumerate(q_scans):
            qn = np.array([s.northing for s in qs])
            qe = np.array([s.easting for s in qs])
            truth: list[dict[int, np.ndarray]] = [{} for _ in qs]
            opp: dict[int, np.ndarray] = {}
            for i, db in enumerate(es.database):
                if i == j:
                    continue
                found = within_radius(db.northing, db.easting, qn, qe, es.truth_radius or 25.0)
                if es.runs[i] in held:  # a query run is never another's map
                    found = [np.empty(0, np.int64)] * len(qs)
                for q, f in enumerate(found):
                    truth[q][offset + i] = np.asarray(f, dtype=np.int64)
                # the other run's heading at the place: its raw scan nearest the query
                rn = np.array([s.northing for s in raw[i]])
                re_ = np.array([s.easting for s in raw[i]])
                opp[offset + i] = np.zeros(len(qs), dtype=bool)
                for q, s in enumerate(qs):
                    k = int(np.argmin((rn - s.northing) ** 2 + (re_ - s.easting) ** 2))
                    turn = (_yaw(s.pose) - _yaw(raw[i][k].pose) + 180.0) % 360.0 - 180.0
                    opp[offset + i][q] = abs(turn) > OPPOSITE_DEG
            db = es.database[j]
            runs.append(
                EvalRun(
                    name=es.runs[j],
                    db_paths=[root.joinpath(*f.split("/")) for f in db.files],
                    db_positions=np.stack([db.northing, db.easting], axis=1).reshape(-1, 2),
                    query_paths=[s.path for s in qs],
                    query_positions=np.stack([qn, qe], axis=1).reshape(-1, 2),
                    truth=truth,
                    area=name,
                )
            )
            scans.append(qs)
            opposite.append(opp)
    if not runs:
        raise InputError("the splits hold no evaluation sets", "splits")
    assert g_config is not None
    return ScanQuerySet(runs, scans, opposite, map_kind, g_config)


def _g_one(args: tuple[str, str, dict[str, Any]]) -> tuple[list[float], float]:
    """G of one raw scan (KITTI .bin) written as a benchmark submap: G's centre and scale."""
    from pnvlad_service.io.readers import read_points
    from pnvlad_service.io.submap import write_submap
    from pnvlad_service.preprocess.filter_g import apply_g

    src, dst, cfg = args
    g = apply_g(read_points(src, "kitti"), GConfig.model_validate(cfg), seed=0)
    write_submap(dst, g.points)
    return [float(v) for v in g.centre], float(g.scale)


def preprocess_queries(
    qs: ScanQuerySet, out_dir: str | Path, *, workers: int | None = None, progress: bool = True
) -> list[EvalRun]:
    """The runs with each query scan replaced by its G output (a 4096-point submap file under
    ``out_dir``), G run in ``workers`` processes (default: the CPUs); G's centre and scale of
    each go to ``qs.g_frames`` (for :func:`query_frames`)."""
    from pnvlad_service.progress import tqdm

    out_dir = Path(out_dir)
    cfg = qs.g_config.model_dump(mode="json")
    jobs, runs = [], []
    for run, scans in zip(qs.runs, qs.scans, strict=True):
        paths = []
        for s in scans:
            dst = out_dir / run.area / run.name / f"{s.timestamp}.bin"
            dst.parent.mkdir(parents=True, exist_ok=True)
            jobs.append((str(s.path), str(dst), cfg))
            paths.append(dst)
        runs.append(replace(run, query_paths=paths))
    n = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    bar = tqdm(total=len(jobs), desc="G of query scans", unit="scan", disable=not progress)
    if n == 1:
        results = []
        for job in jobs:
            results.append(_g_one(job))
            bar.update()
    else:
        with ProcessPoolExecutor(n, mp_context=get_context("spawn")) as pool:
            results = []
            for res in pool.map(_g_one, jobs, chunksize=8):
                results.append(res)
                bar.update()
    bar.close()
    qs.g_frames = {
        str(Path(dst).resolve()): r for (_, dst, _), r in zip(jobs, results, strict=True)
    }
    return runs


def query_frames(qs: ScanQuerySet, runs: list[EvalRun]) -> dict[str, SubmapFrame]:
    """Each preprocessed query's frame record (absolute path -> :class:`SubmapFrame`), as
    re-ranking reads a submap's: metres = G's centre + scale x points, in the sensor frame;
    its true pose the scan's true sensor pose (``None`` where the run has none)."""
    from pnvlad_service.data.drive import snap_m

    out = {}
    for run, scans in zip(runs, qs.scans, strict=True):
        for path, s in zip(run.query_paths, scans, strict=True):
            key = str(Path(path).resolve())
            centre, scale = qs.g_frames[key]
            t = s.true_pose
            out[key] = SubmapFrame(
                s.timestamp,
                snap_m(s.pose[:3, 3]),
                np.asarray(centre),
                scale,
                "enu",
                None if t is None else t[:3, 3].copy(),
                None if t is None else _yaw(t),
            )
    return out


def direction_subsets(qs: ScanQuerySet, runs: list[EvalRun], opposite: bool) -> list[EvalRun]:
    """``runs`` with each query's ground truth kept only in the database runs that passed it
    the same way (``opposite`` False) or the other way (True): the pairs of other runs then
    count as having no truth for that query and are not scored."""
    out = []
    for run, opp in zip(runs, qs.opposite, strict=True):
        truth = [
            {i: t for i, t in tr.items() if bool(opp[i][q]) == opposite}
            for q, tr in enumerate(run.truth)
        ]
        out.append(replace(run, truth=truth))
    return out


def scan_report(
    qs: ScanQuerySet,
    runs: list[EvalRun],
    db_desc: list[np.ndarray],
    q_desc: list[np.ndarray],
    num_points: int,
) -> dict[str, Any]:
    """What a scan-query report adds to :func:`~.evaluate.evaluate_embedded`'s: ``queries_kind``
    "scan", the ``map_kind``, the queries' G and ``direction``: recall@1 and recall@1% of the
    queries whose database run passed them the same way and the other way."""
    from pnvlad_service.evaluation.evaluate import evaluate_embedded

    out: dict[str, Any] = {
        "queries_kind": "window" if qs.window else "scan",
        "map_kind": qs.map_kind,
        "query_g_config": qs.g_config.model_dump(mode="json"),
        "direction": {},
    }
    if qs.window:
        drift = np.asarray(qs.drift_m, dtype=np.float64)
        out["window"] = {**qs.window, "n": int(sum(len(x) for x in qs.scans))}
        if len(drift):
            out["window"]["drift_m"] = {
                "median": float(np.median(drift)),
                "p90": float(np.percentile(drift, 90)),
                "max": float(drift.max()),
            }
    for name, opposite in (("same", False), ("opposite", True)):
        rep = evaluate_embedded(
            direction_subsets(qs, runs, opposite), db_desc, q_desc, num_points=num_points
        )
        out["direction"][name] = {
            k: rep[k] for k in ("recall_at_1", "recall_at_1pct", "n_pairs", "n_queries_evaluated")
        }
    return out
