"""``pnvlad map align``: a map's runs aligned into one map that agrees with itself.

The stages, each timed:

1. **nodes**: every run's entries (keyframes by default) and the poses they were laid with
   (:mod:`.nodes`; a run whose poses jump is refused, naming it);
2. **embed** (with a model): each node's descriptor, for retrieval;
3. **candidates**: per query node and other run, the nodes that may show its place, by
   retrieval and by the recorded poses (:mod:`.candidates`);
4. **odometry**: each node registered onto the one before it (:mod:`.edges`); for the runs
   whose scans are skewed by the sweep and have a sweep rate (``sweep_hz``, or the synthetic
   tree's sensor's), each node's scan first de-skewed (:mod:`.deskew`) by the motion its
   recording gave it, or where it has none by the motion a first odometry pass measures
   (then registered again); the closures use the de-skewed scans too;
5. **closures**: each candidate group verified, the best match gated (:mod:`.edges`); a run
   that shares no accepted closure with any other run is refused, naming it (nothing ties it
   to the map: ``allow_alone`` keeps it on its own fixes);
6. **solve**: the pose graph (:mod:`.graph`); a run that holds position fixes only (its poses
   KISS-ICP odometry laid onto them) is held to its fixes, and its odometry steps that failed
   to register are KISS-ICP's own (:mod:`.fixes`);
7. **write**: the tree re-laid into ``out`` (:mod:`.relay`), the report and the plot
   (:mod:`.report`).

Nothing is written before stage 7, and the recorded tree is only read.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from pnvlad_service.data.tree import Kind
from pnvlad_service.errors import InputError
from pnvlad_service.mapping.candidates import (
    CandidateConfig,
    embed_nodes,
    merged,
    nearby_candidates,
    query_nodes,
    retrieval_candidates,
)
from pnvlad_service.mapping.deskew import run_motion
from pnvlad_service.mapping.edges import Clouds, Edge, EdgeConfig, closure_edges, odometry_edges
from pnvlad_service.mapping.fixes import (
    FixConfig,
    FixRun,
    measured_nodes,
    odometry_fallback,
    read_fix_runs,
)
from pnvlad_service.mapping.graph import GraphConfig, Solution, solve
from pnvlad_service.mapping.nodes import MapNodes, RunNodes, read_tree_nodes
from pnvlad_service.mapping.relay import write_aligned_tree
from pnvlad_service.mapping.report import (
    edge_report,
    plot_alignment,
    run_corrections,
    write_report,
)

log = logging.getLogger(__name__)

T = TypeVar("T")

REPORT = "align_report.json"
PLOT = "align.png"


@dataclass(frozen=True)
class AlignConfig:
    """Every setting of an alignment: the ``kind`` of entries that are the graph's nodes,
    whether a run without a closure to another run is kept on its own fixes
    (``allow_alone``), the sensors' sweeps a second (``sweep_hz``: the scans of the runs whose
    nodes are single scans given as fired, :attr:`~.nodes.RunNodes.skewed`, are de-skewed at
    that rate; 0: none; ``None``, the default: each at its sensor's rate where the tree
    records it, :attr:`~.nodes.RunNodes.sensor_hz`, a synthetic tree's, and a recording's
    not at all), and each stage's settings."""

    kind: Kind = "keyframe"
    allow_alone: bool = False
    sweep_hz: float | None = None
    candidates: CandidateConfig = field(default_factory=CandidateConfig)
    edges: EdgeConfig = field(default_factory=EdgeConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    fixes: FixConfig = field(default_factory=FixConfig)


@dataclass
class Alignment:
    """The outcome in memory: the nodes, the edges, the solution, the report (a dict) and
    the seconds of each stage."""

    nodes: MapNodes
    edges: list[Edge]
    solution: Solution
    report: dict[str, Any]
    seconds: dict[str, float]


class _Timer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    def run(self, name: str, fn: Callable[[], T]) -> T:
        t0 = time.perf_counter()
        out = fn()
        self.seconds[name] = round(self.seconds.get(name, 0.0) + time.perf_counter() - t0, 3)
        log.info("stage %s: %.1f s", name, self.seconds[name])
        return out


def check_overlap(nodes: MapNodes, edges: list[Edge]) -> list[str]:
    """The runs that share no accepted closure with another run (names, in order)."""
    tied: set[int] = set()
    for e in edges:
        if e.kind == "closure" and e.accepted:
            a, b = int(nodes.run_of[e.source]), int(nodes.run_of[e.target])
            if a != b:
                tied |= {a, b}
    return [r.name for k, r in enumerate(nodes.runs) if k not in tied]


def deskewed_nodes(nodes: MapNodes, odometry: list[Edge], config: AlignConfig) -> MapNodes | None:
    """``nodes`` whose scans give their points de-skewed (:mod:`.deskew`) by the motion
    their recording gave each node (:attr:`~.nodes.RunNodes.recorded_motion`), else by the
    motion that ``odometry`` (each run's steps, in order) measured, the recorded step where it
    failed, at :func:`sweep_rate`; runs whose scans are not :attr:`~.nodes.RunNodes.skewed`
    or have no rate as they are. ``None`` when no run is to be de-skewed.

    The recording's motion is preferred: its poses come at every scan, while the odometry's
    steps join keyframes a few metres apart and cannot follow a corner turned in a second."""
    if not any(sweep_rate(r, config) > 0 for r in nodes.runs):
        return None
    runs = []
    at = 0
    for run in nodes.runs:
        steps = odometry[at : at + len(run) - 1]
        at += len(run) - 1
        hz = sweep_rate(run, config)
        if hz <= 0:
            runs.append(run)
            continue
        if run.recorded_motion is not None:
            motion = run.recorded_motion
        else:
            rel = [e.transform if e.accepted else None for e in steps]
            motion = run_motion(run.stamps, rel, run.poses)
        runs.append(replace(run, motion=motion, sweep_hz=hz))
    return MapNodes(runs)


def sweep_rate(run: RunNodes, config: AlignConfig) -> float:
    """The sweeps a second ``run``'s scans are de-skewed at: 0 unless they are skewed;
    ``config.sweep_hz`` where given, else the run's :attr:`~.nodes.RunNodes.sensor_hz` (0
    where the tree does not record it)."""
    if not run.skewed:
        return 0.0
    if config.sweep_hz is not None:
        return config.sweep_hz
    return run.sensor_hz or 0.0


def measure_edges(
    nodes: MapNodes,
    config: AlignConfig,
    timer: _Timer,
    descriptors: np.ndarray | None = None,
    fix_only: frozenset[int] = frozenset(),
) -> tuple[list[Edge], dict[str, int]]:
    """Stages 3-5: candidates, odometry and closures of ``nodes`` (``descriptors`` float32
    [N, D] add the retrieved candidates; ``fix_only``: the indices of the runs with position
    fixes only). Returns the edges and the candidates' counts."""
    cc = config.candidates

    def candidates() -> tuple[list[tuple[int, list[int]]], dict[str, int]]:
        queries = query_nodes(nodes, cc.every)
        sources = []
        counts = {"queries": len(queries)}
        if descriptors is not None:
            found = retrieval_candidates(nodes, descriptors, queries, cc)
            counts["retrieved"] = sum(len(g) for g in found.values())
            sources.append(found)
        near = nearby_candidates(nodes, queries, cc)
        counts["nearby"] = sum(len(g) for g in near.values())
        sources.append(near)
        groups = merged(*sources, per_group=cc.per_group)
        counts["groups"] = len(groups)
        counts["verified"] = sum(len(g) for _, g in groups)
        return groups, counts

    groups, counts = timer.run("candidates", candidates)

    def register(on: MapNodes) -> list[Edge]:
        steps = Clouds.for_odometry(on, config.edges)
        return timer.run("odometry", lambda: odometry_edges(on, steps, config.edges, fix_only))

    recorded = all(r.recorded_motion is not None for r in nodes.runs if sweep_rate(r, config) > 0)
    if recorded:  # every sweep's motion is recorded: de-skew before the one odometry pass
        nodes = deskewed_nodes(nodes, [], config) or nodes
    odometry = register(nodes)
    moving = None if recorded else deskewed_nodes(nodes, odometry, config)
    if moving is not None:  # the first pass measured the motion: register the de-skewed scans
        nodes = moving
        odometry = register(nodes)
    clouds = Clouds(nodes, config.edges)
    closures = timer.run("closures", lambda: closure_edges(nodes, clouds, groups, config.edges))
    return odometry + closures, counts


def align_nodes(
    nodes: MapNodes,
    config: AlignConfig,
    descriptors: np.ndarray | None = None,
    timer: _Timer | None = None,
    extra_edges: list[Edge] | None = None,
    fix_runs: list[FixRun] | None = None,
) -> Alignment:
    """Stages 3-6 on ``nodes`` in memory (``extra_edges`` are added as given: a test's
    injected closures; ``fix_runs``: the runs with position fixes only, :mod:`.fixes`).
    ``InputError`` naming the runs no closure ties to the others."""
    timer = timer or _Timer()
    fix_runs = fix_runs or []
    fix_only = frozenset(f.run for f in fix_runs)
    edges, counts = measure_edges(nodes, config, timer, descriptors, fix_only)
    edges = odometry_fallback(nodes, edges, fix_runs, config.fixes)
    edges += extra_edges or []
    alone = check_overlap(nodes, edges)
    if alone and len(nodes.runs) > 1:
        message = (
            f"{len(alone)} run(s) share no verified place with the other runs: "
            f"{', '.join(alone)} (no closure accepted; runs of one map must overlap)"
        )
        if not config.allow_alone:
            raise InputError(message + "; allow_alone keeps them on their own fixes", alone[0])
        log.warning("%s: kept on their own fixes", message)
    measured = measured_nodes(nodes, fix_runs)
    solution = timer.run("solve", lambda: solve(measured, edges, config.graph))
    for i in solution.dropped:
        reason = f"left over {config.graph.outlier_sigma:g} sigma off by the robust solve"
        edges[i] = replace(edges[i], reason=reason)
    report: dict[str, Any] = {
        "format": "pnvlad-align",
        "version": 1,
        "runs": [r.name for r in nodes.runs],
        "nodes": len(nodes),
        "candidates": counts,
        **edge_report(nodes, edges, solution),
        "runs_alone": alone,
        "fix_runs": {
            "runs": [nodes.runs[f.run].name for f in fix_runs],
            "kiss_icp_steps": sum(e.kind == "odometry-kiss-icp" for e in edges),
        },
        "corrections": run_corrections(nodes, solution.poses),
        "settings": _settings(config),
    }
    return Alignment(nodes, edges, solution, report, timer.seconds)


def _settings(config: AlignConfig) -> dict[str, Any]:
    out = asdict(config)
    out["edges"].pop("verify", None)
    return out


def align_map(
    root: str | Path,
    out: str | Path,
    *,
    model: str | Path | None = None,
    config: AlignConfig | None = None,
    overwrite: bool = False,
) -> Alignment:
    """Align the runs of the tree at ``root`` and write the aligned tree to ``out`` with
    ``align_report.json`` and ``align.png`` in it (see the module doc). ``model``: the encoder
    whose retrieval adds closure candidates (without one, only the recorded poses propose
    them). ``InputError`` (nothing written) on a run that cannot be aligned."""
    config = config or AlignConfig()
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: already exists (pass overwrite to replace it)")
    if Path(root).resolve() == out.resolve():
        raise InputError("the aligned tree must go beside the recorded one, not over it", "out")
    timer = _Timer()
    nodes = timer.run("nodes", lambda: read_tree_nodes(root, config.kind))
    fix_runs = read_fix_runs(root, nodes, config.graph.gnss.position_std_m)
    desc = None
    if model is not None:
        desc = timer.run("embed", lambda: embed_nodes(nodes, model))
    result = align_nodes(nodes, config, desc, timer, fix_runs=fix_runs)
    counts = timer.run(
        "write", lambda: write_aligned_tree(root, out, nodes, result.solution.poses, overwrite)
    )
    timer.run(
        "plot", lambda: plot_alignment(out / PLOT, nodes, result.edges, result.solution.poses)
    )
    result.report["relaid"] = counts
    result.report["model"] = None if model is None else str(model)
    result.report["seconds"] = timer.seconds
    write_report(out / REPORT, result.report)
    return result
