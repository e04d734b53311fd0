"""Queries in the published format (no frame sidecar, so no scale) against the same queries
with their known scale: how often each verifies, and how often a verified answer is right.

    python benchmarks/scale_free_queries.py TREE --index MAP [--model MODEL] [--dataset D]
        [--run RUN ...] [--splits SPLITS] [--count N] [--sweep N] [--bounds LO,HI]
        [--sweep-bounds LO,HI,STEPS] [--stop-score S|none] [--alone-score S|none]
        [--json out.json]

TREE: a ``pnvlad synth`` tree (its frame sidecars give each query's scale and true pose);
MAP: a bundle with geometry built from the runs of TREE but the query run. The queries are
the query run's test submaps (``pointcloud_20m``; default: the last run of the first area,
as scripts/demo.sh holds it out; ``--run`` again for more runs, each left out of MAP);
with ``--splits`` only those that are queries of the area's evaluation set there (the
``oxford`` preset's: the test submaps inside the published test squares). Each is localised
twice in this process by :meth:`Localizer.localize`: with the scale of its frame sidecar
(``known``) and as the benchmark publishes it, without (``free``: the scale is estimated from
the candidates by registration, localization/verify/scale.py). ``--median`` adds a third
pass, ``median``: no scale given and the candidates' median scale taken as it is (the rigid
registration only, as verification did before the scale was free).

``--sweep N``: the candidates the free scale's one factor is fitted to (0: each candidate
keeps a factor of its own, as verification did before; localization/verify/scale.py);
``--bounds`` the range each candidate's own factor is held to, ``--sweep-bounds`` the
factors the one factor is chosen from (``ScaleConfig``), both relative to the starting scale.

``--stop-score`` / ``--alone-score``: the verification cascade's (``VerifyConfig``; ``none``
registers every candidate / never lets a first candidate stand alone).

``--off-map`` verifies each query once more as if the map did not hold its place (its
candidates the nearest by descriptor among those over 50 m away, as the threshold's
calibration makes them): every one verified there is a wrong answer the service would give.

Printed per mode: the share verified; the share of verified answers at the right place (the
pose within 25 m of the query's true position); the median (p90) translation and yaw error of
the verified answers' registration against the simulator's true relative pose; for ``free``,
the estimated scale's error against the sidecar's (median and p90 of |estimate / truth - 1|);
and the seconds of verification a query.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from entry import run

from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.evaluation.rerank_figures import pose_error
from pnvlad_service.io.submap import read_submap
from pnvlad_service.localization.query.config import LocalizerConfig
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.scale import ScaleConfig
from pnvlad_service.localization.verify.verify import VerifyConfig

RIGHT_M = 25.0
OFF_MAP_M = 50.0


def _centroid_frame(frame) -> np.ndarray:
    """The query's centroid frame in true UTM: its local frame's true pose moved to G's centre."""
    pose = frame.true_pose.copy()
    pose[:3, 3] += pose[:3, :3] @ frame.centre
    return pose


def select_queries(
    tree: BenchmarkTree, dataset: str, runs: list[str], splits: Path | None
) -> list[tuple]:
    """(submap, frame) of each test submap of ``runs``; with ``splits``, only those listed as
    queries of ``dataset``'s evaluation set there."""
    listed = None
    if splits is not None:
        sets = json.loads(splits.read_text()).get("evaluation", {})
        if dataset not in sets:
            raise SystemExit(f"{splits}: no evaluation set {dataset!r}")
        listed = {f for q in sets[dataset]["queries"] for f in q["files"]}
    out = []
    for run_name in runs:
        subs = tree.submaps(dataset, run_name, "test")
        frames = tree.frames(dataset, run_name, "test")
        if frames is None:
            raise SystemExit(f"{tree.root}: run {run_name} has no frame sidecar (no truth)")
        pairs = zip(subs, frames, strict=True)
        out += [(s, f) for s, f in pairs if listed is None or s.path in listed]
    return out


def localise_all(loc: Localizer, tree: BenchmarkTree, queries, known: bool) -> list[dict]:
    """One record per query: verified, right place, pose errors, scale used."""
    db_frames = tree.frames_by_path()
    out = []
    for sub, frame in queries:
        cloud = read_submap(tree.root / sub.path)
        t0 = time.perf_counter()
        ans = loc.localize(cloud, top_n=1, scale=frame.scale if known else None)
        seconds = time.perf_counter() - t0
        v = ans.verification
        rec = {
            "path": sub.path,
            "verified": bool(ans.verified),
            "seconds": seconds,
            "registered": v.registered if v else 0,
            "confidence": v.confidence if v else 0.0,
            "true_scale": abs(frame.scale),
        }
        if ans.verified and v is not None and v.pose is not None:
            truth_frame = _centroid_frame(frame)
            where = np.array([v.pose.easting, v.pose.northing])
            rec["off_m"] = float(np.linalg.norm(where - truth_frame[:2, 3]))
            rec["right"] = rec["off_m"] <= RIGHT_M
            best = ans.matches[0]
            dbf = db_frames[str((tree.root / best.path).resolve())]
            truth = np.linalg.inv(dbf.true_pose) @ truth_frame
            t_err, yaw_err = pose_error(v.checks[0].transform, truth)
            rec.update(t_err=t_err, yaw_err=yaw_err, scale=v.pose.metres_per_unit)
        out.append(rec)
    return out


def off_map(loc: Localizer, tree: BenchmarkTree, queries, known: bool) -> dict:
    """Each query verified as if the map did not hold its place (as the threshold's
    calibration does): its candidates the nearest by descriptor among the map's submaps over
    ``OFF_MAP_M`` from it, every one a wrong place. The share verified (all wrong)."""
    meta = loc.bundle.metadata
    where = np.c_[meta.northing, meta.easting]
    k = loc.verify_config.candidates
    verified = 0
    for sub, frame in queries:
        cloud = read_submap(tree.root / sub.path)
        prepared = loc.prepare(cloud, False, frame.scale if known else None)
        ids = loc.submit(prepared, loc.bundle.count).result().ids
        far = np.linalg.norm(where[ids] - [sub.northing, sub.easting], axis=1) > OFF_MAP_M
        verified += loc.verify_ids(prepared, [int(i) for i in ids[far][:k]]).verified
    return {"queries": len(queries), "verified": verified}


def summary(records: list[dict]) -> dict:
    """The figures of one mode."""
    n = len(records)
    ver = [r for r in records if r["verified"]]
    right = [r for r in ver if r["right"]]
    figs = {
        "queries": n,
        "verified": len(ver),
        "verified_share": len(ver) / n if n else 0.0,
        "right": len(right),
        "right_share": len(right) / len(ver) if ver else float("nan"),
        "seconds_median": float(np.median([r["seconds"] for r in records])) if n else 0.0,
        "registered_mean": float(np.mean([r["registered"] for r in records])) if n else 0.0,
    }
    if right:
        t = np.array([r["t_err"] for r in right])
        y = np.array([r["yaw_err"] for r in right])
        s = np.array([abs(r["scale"] / r["true_scale"] - 1.0) for r in right])
        figs.update(
            t_err_median=float(np.median(t)),
            t_err_p90=float(np.percentile(t, 90)),
            yaw_err_median=float(np.median(y)),
            yaw_err_p90=float(np.percentile(y, 90)),
            scale_err_median=float(np.median(s)),
            scale_err_p90=float(np.percentile(s, 90)),
        )
    return figs


def _line(mode: str, f: dict) -> str:
    text = (
        f"{mode:6s} verified {f['verified']}/{f['queries']} ({100 * f['verified_share']:.1f} %), "
        f"right place {f['right']}/{f['verified']} ({100 * f['right_share']:.1f} %)"
    )
    if "t_err_median" in f:
        text += (
            f", pose error {f['t_err_median']:.2f} m (p90 {f['t_err_p90']:.2f}) "
            f"{f['yaw_err_median']:.2f} deg (p90 {f['yaw_err_p90']:.2f}), "
            f"scale off {100 * f['scale_err_median']:.1f} % (p90 {100 * f['scale_err_p90']:.1f})"
        )
    return text + (f", {f['seconds_median']:.2f} s a query, {f['registered_mean']:.1f} registered")


def _score_or_none(text: str) -> float | None:
    """A score in [0, 1], or ``none``."""
    if text.lower() == "none":
        return None
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"a score in [0, 1] or none, got {text}")
    return value


def _verify_config(base: VerifyConfig, args: argparse.Namespace) -> VerifyConfig:
    """``base`` with the command line's cascade and free-scale settings."""
    free = replace(base, stop_score=args.stop_score, alone_score=args.alone_score)
    scale = free.scale
    if args.sweep is not None:
        scale = replace(scale, sweep_candidates=args.sweep)
    if args.bounds:
        lo, hi = (float(f) for f in args.bounds.split(","))
        scale = replace(scale, bounds=(lo, hi))
    if args.starts:
        scale = replace(scale, starts=tuple(float(f) for f in args.starts.split(",")))
    if args.sweep_bounds:
        lo, hi, steps = args.sweep_bounds.split(",")
        scale = replace(scale, sweep_bounds=(float(lo), float(hi)), sweep_steps=int(steps))
    return replace(free, scale=scale)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("root", type=Path, help="a pnvlad synth tree (frame sidecars with truth)")
    ap.add_argument("--index", required=True, type=Path, help="a bundle with geometry")
    ap.add_argument("--model", type=Path, help="the model (default: the bundle's)")
    ap.add_argument("--dataset", help="the area (default: the tree's first)")
    ap.add_argument(
        "--run", action="append", help="a query run (repeatable; default: the area's last)"
    )
    ap.add_argument(
        "--splits", type=Path, help="only the queries of the area's evaluation set in this file"
    )
    ap.add_argument("--count", type=int, help="at most this many queries (default: all)")
    ap.add_argument("--json", type=Path, help="write the figures and every record here")
    ap.add_argument(
        "--off-map",
        action="store_true",
        help=f"also verify each query against only candidates over {OFF_MAP_M:g} m away",
    )
    ap.add_argument(
        "--median", action="store_true", help="also: the candidates' median scale, not refined"
    )
    ap.add_argument(
        "--starts",
        help="the free scale's starting factors, comma-separated (default: the shipped 1.0)",
    )
    ap.add_argument(
        "--bounds",
        help="the free scale's factor bounds LO,HI (default: the shipped 0.7,1.4)",
    )
    ap.add_argument(
        "--sweep-bounds",
        help="the factors the query's one scale is swept over, LO,HI,STEPS (default: the "
        "shipped 0.7,1.5,7)",
    )
    ap.add_argument(
        "--sweep",
        type=int,
        help="candidates the query's one scale is fitted to (default: the shipped 2; 0: each "
        "candidate keeps its own factor)",
    )
    ap.add_argument(
        "--stop-score",
        type=_score_or_none,
        default=VerifyConfig.stop_score,
        help="the cascade stops at a candidate this sure; none: every candidate registered "
        f"(default: the shipped {VerifyConfig.stop_score})",
    )
    ap.add_argument(
        "--alone-score",
        type=_score_or_none,
        default=VerifyConfig.alone_score,
        help=f"a first candidate this sure stands alone; none: never (default: the shipped "
        f"{VerifyConfig.alone_score})",
    )
    return ap


def main() -> int:
    args = _parser().parse_args()
    tree = BenchmarkTree(args.root)
    dataset = args.dataset or tree.datasets[0]
    query_runs = args.run or [tree.runs(dataset)[-1]]
    queries = select_queries(tree, dataset, query_runs, args.splits)[: args.count]
    print(f"{len(queries)} test submaps of {dataset}/{'+'.join(query_runs)} against {args.index}")
    report: dict = {"dataset": dataset, "run": query_runs, "index": str(args.index)}
    modes = [("known", True), ("free", False)] + [("median", False)] * args.median
    with Localizer.load(args.index, args.model, LocalizerConfig()) as loc:
        free = _verify_config(loc.verify_config, args)
        for mode, known in modes:
            rigid = ScaleConfig(bounds=(1.0, 1.0), sweep_candidates=0, track_spread=None)
            fixed = replace(free, scale=rigid)
            loc.verify_config = fixed if mode == "median" else free
            records = localise_all(loc, tree, queries, known)
            figs = summary(records)
            print(_line(mode, figs))
            report[mode] = {"figures": figs, "records": records}
            if args.off_map:
                figs["off_map"] = off_map(loc, tree, queries, known)
                o = figs["off_map"]
                print(f"{'':6s} off the map: {o['verified']}/{o['queries']} verified (all wrong)")
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    run(main)
