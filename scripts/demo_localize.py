"""The last step of the demo: localise held-out submaps of one run against a running server.

Picks ``--count`` query submaps of ``--run`` (a run that is not in the server's index) inside the
dataset's test regions, sends each to ``POST /localize`` as a binary float64 body (with its
frame sidecar's scale, so the pose is metric), prints its top-N matches with UTM coordinates,
descriptor distances and verification scores, and says whether the best match lies within
``--radius`` metres of where the query really was (the benchmark's 25 m rule). When the server
verified the answer it prints the query's pose on the map and its error against the
simulator's truth (the true pose of the query's frame, before the GNSS/INS error).
With ``--scans`` the queries are the run's raw single scans at those places instead (its
``raw_scans/``: what a robot's sensor sends, in the sensor's frame), sent raw (``kind=scan``)
to a server of a keyframe map; a verified pose is the sensor's, compared with its true pose.
Exits non-zero if the server cannot be reached.

    python scripts/demo_localize.py --url http://127.0.0.1:8000 --root runs/demo/city \
        --dataset business --run 2026-03-18-09-00-00 --count 8 [--scans]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_cli.localize import verdict
from pnvlad_service.client import LocalizeClient
from pnvlad_service.data.frames import SubmapFrame
from pnvlad_service.data.splits import resolve_regions
from pnvlad_service.data.tree import BenchmarkTree
from pnvlad_service.errors import PnvladError
from pnvlad_service.io.readers import read_points


def pose_line(answer: dict, frame: SubmapFrame | None) -> str:
    """`pnvlad localize`'s verdict line, and for a verified answer the pose's error against
    the truth (the true pose of the query's frame, its origin moved to the centroid)."""
    line = "  " + verdict(answer)
    if answer.get("verified") and frame is not None and frame.true_pose is not None:
        p = answer["pose"]
        true = frame.true_pose
        centroid = true[:3, :3] @ frame.centre + true[:3, 3]  # the query frame's true origin
        err = math.hypot(p["easting"] - centroid[0], p["northing"] - centroid[1])
        dyaw = (p["yaw_deg"] - frame.true_yaw_deg + 180.0) % 360.0 - 180.0
        line += f"; off the truth by {err:.2f} m and {abs(dyaw):.2f} deg"
    return line


def scan_pose_line(answer: dict, true_pose: np.ndarray | None) -> str:
    """The verdict line of a raw scan, and for a verified answer the error of the sensor's
    pose against its true pose."""
    line = "  " + verdict(answer)
    if answer.get("verified") and true_pose is not None:
        p = answer["pose"]
        err = math.hypot(p["easting"] - true_pose[0, 3], p["northing"] - true_pose[1, 3])
        yaw = math.degrees(math.atan2(true_pose[1, 0], true_pose[0, 0]))
        dyaw = (p["yaw_deg"] - yaw + 180.0) % 360.0 - 180.0
        line += f"; off the truth by {err:.2f} m and {abs(dyaw):.2f} deg"
    return line


def verified_line(verified: int, wrong: int) -> str:
    """The summary's verdict: how many answers were verified, and how many of those wrongly
    (their top-1 not within the radius: a wrong place the registration accepted)."""
    if not wrong:
        return f"{verified} verified with a pose, all at the right place"
    return f"{verified} verified with a pose, {wrong} of them at a WRONG place"


def report(q: Any, answer: dict, radius: float, pose: str, kind: str = "submap") -> bool:
    """Print one query's matches and ``pose`` (its verdict line); whether its top-1 lies
    within ``radius`` metres of it. ``q``: a :class:`Submap` or a raw scan (``run`` and
    ``timestamp``, ``northing``, ``easting``)."""
    best = answer["matches"][0]
    err = math.hypot(best["northing"] - q.northing, best["easting"] - q.easting)
    ok = err <= radius
    print(
        f"\n{kind} {q.run}/{q.timestamp}  true N {q.northing:.1f} E {q.easting:.1f}  "
        f"(embed {answer['timings_ms']['embed']:.1f} ms, search "
        f"{answer['timings_ms']['search']:.2f} ms)"
    )
    print(
        f"  {'rank':>4}  {'run':<20} {'northing':>12} {'easting':>11} {'dist':>7} {'score':>6} "
        f"{'off':>8}"
    )
    for m in answer["matches"]:
        off = math.hypot(m["northing"] - q.northing, m["easting"] - q.easting)
        score = "-" if m.get("score") is None else f"{m['score']:.2f}"
        print(
            f"  {m['rank']:>4}  {m['run']:<20} {m['northing']:>12.1f} {m['easting']:>11.1f} "
            f"{m['distance']:>7.3f} {score:>6} {off:>6.1f} m"
        )
    print(f"  top-1 is {err:.1f} m from the truth: {'WITHIN' if ok else 'NOT within'} {radius:g} m")
    print(pose)
    return ok


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", required=True)
    ap.add_argument("--root", type=Path, required=True, help="benchmark tree root")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--run", required=True, help="held-out run whose submaps are the queries")
    ap.add_argument("--count", type=int, default=8)
    ap.add_argument("--top-n", type=int, default=5)
    ap.add_argument("--radius", type=float, default=25.0)
    ap.add_argument("--scans", action="store_true", help="ask with the run's raw single scans")
    args = ap.parse_args(argv)
    if args.scans:
        return localize_scans(args)

    tree = BenchmarkTree(args.root)
    submaps = tree.submaps(args.dataset, args.run, "test")
    # Queries come from the test regions, which training never saw.
    regions = resolve_regions(tree, args.dataset, args.dataset)
    inside = regions.contains(
        np.array([s.northing for s in submaps]), np.array([s.easting for s in submaps])
    )
    submaps = [s for s, keep in zip(submaps, inside, strict=True) if keep]
    if not submaps:
        print(f"no query submaps for {args.dataset}/{args.run} under {args.root}", file=sys.stderr)
        return 2
    frames = dict(
        zip(
            [s.timestamp for s in tree.submaps(args.dataset, args.run, "test")],
            tree.frames(args.dataset, args.run, "test") or [],
            strict=False,
        )
    )
    step = max(len(submaps) // args.count, 1)
    chosen = submaps[::step][: args.count]

    hits = verified = wrong = 0
    with LocalizeClient(args.url, timeout=60) as client:
        for q in chosen:
            pts = read_points(args.root / q.path, reader="benchmark").astype(np.float64)
            frame = frames.get(q.timestamp)
            try:
                # A negated tree (GConfig.negate) has a negative scale: the server estimates it.
                scale = frame.scale if frame is not None and frame.scale > 0 else None
                answer = client.localize(pts, args.top_n, scale=scale)
            except PnvladError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
            hit = report(q, answer, args.radius, pose_line(answer, frame))
            hits += hit
            verified += bool(answer.get("verified"))
            wrong += bool(answer.get("verified")) and not hit
    print(
        f"\n{hits}/{len(chosen)} queries localised within {args.radius:g} m by their top-1 match; "
        f"{verified_line(verified, wrong)}."
    )
    return 0


def localize_scans(args: argparse.Namespace) -> int:
    """``--scans``: the held-out run's raw scans inside the test regions, sent raw."""
    from types import SimpleNamespace

    from pnvlad_service.data.scans import read_raw_scans

    tree = BenchmarkTree(args.root)
    regions = resolve_regions(tree, args.dataset, args.dataset)
    scans = read_raw_scans(args.root / args.dataset / args.run)
    inside = regions.contains(
        np.array([s.northing for s in scans]), np.array([s.easting for s in scans])
    )
    scans = [s for s, keep in zip(scans, inside, strict=True) if keep]
    if not scans:
        print(f"no raw scans for {args.dataset}/{args.run} under {args.root}", file=sys.stderr)
        return 2
    chosen = scans[:: max(len(scans) // args.count, 1)][: args.count]
    hits = verified = wrong = 0
    with LocalizeClient(args.url, timeout=60) as client:
        for s in chosen:
            pts = read_points(s.path, reader="kitti")
            try:
                answer = client.localize(pts, args.top_n, kind="scan")
            except PnvladError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
            q = SimpleNamespace(
                run=args.run, timestamp=s.timestamp, northing=s.northing, easting=s.easting
            )
            print(f"\n{len(pts):,} points in the sensor's frame, matched to {answer['map_kind']}s:")
            hit = report(q, answer, args.radius, scan_pose_line(answer, s.true_pose), "scan")
            hits += hit
            verified += bool(answer.get("verified"))
            wrong += bool(answer.get("verified")) and not hit
    print(
        f"\n{hits}/{len(chosen)} single scans localised within {args.radius:g} m by their top-1 "
        f"match; {verified_line(verified, wrong)}."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
