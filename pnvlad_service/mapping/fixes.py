"""Runs with position fixes only, in the pose graph: their fixes as the priors, their LiDAR
odometry as the steps.

A run prepared from fixes and KISS-ICP (:class:`~pnvlad_service.data.sources.fix_odometry.
FixOdometryDrive`) keeps its fixes beside it (``fixes.csv``: each fix and where the run's
poses put the sensor at its time). Its entries were laid by the odometry fitted to the fixes;
what the graph must hold them to is the fixes themselves, with their error model, and what
ties one entry to the next is the odometry. So, for such a run:

- **Priors**: each node's measured position is where it was laid plus the fixes' error
  against the laid odometry, linear in time between the fixes about it
  (:func:`measured_nodes`): the fixes carried to the node's time by the odometry between
  them (centimetres over the few metres between a fix and a node). These enter the graph as
  the GNSS chain of every run does (:mod:`.graph`: a Gauss-Markov walk of ``--position-std``
  over ``--correlation`` metres), the laid heading as its heading.
- **Steps**: each node's registration onto the one before it (:mod:`.edges`), started from the
  laid relative pose, which is KISS-ICP's. Where that registration fails (not where it is
  gated out against KISS-ICP's step), the KISS-ICP step itself is the edge
  (:func:`odometry_fallback`), with a covariance of
  :attr:`FixConfig.step_sigma_m` plus :attr:`FixConfig.step_sigma_per_m` of the step (each
  axis) and :attr:`FixConfig.step_sigma_deg`: looser than a registration's, since KISS-ICP's
  errors between keyframes 5 m apart are a few centimetres at the median with a tail of
  decimetres where the drive turns sharply; the robust kernels take what is left.
- **Bad fixes**: a run whose fixes jump against its odometry is refused, naming it
  (:func:`~pnvlad_service.data.sources.fixes.check_jumps`), before anything is written.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from pnvlad_service.data.sources.fixes import (
    Fixes,
    check_jumps,
    fix_residuals_at,
    read_run_fixes,
)
from pnvlad_service.mapping.edges import Edge
from pnvlad_service.mapping.nodes import MapNodes

log = logging.getLogger(__name__)

#: How :func:`~.edges.odometry_edges` words a registration gated out against the laid step.
GATED = "moved the step"


@dataclass(frozen=True)
class FixConfig:
    """The KISS-ICP step's standard deviations where it stands in for a failed registration:
    ``step_sigma_m`` + ``step_sigma_per_m`` times the step's length (metres, each axis) and
    ``step_sigma_deg`` (each axis of the turn)."""

    step_sigma_m: float = 0.05
    step_sigma_per_m: float = 0.02
    step_sigma_deg: float = 0.5


@dataclass(frozen=True)
class FixRun:
    """One fix-only run of a map: its index among the map's runs, its fixes and where its
    poses laid the sensor at each fix's time (float64 [F, 3])."""

    run: int
    fixes: Fixes
    laid: np.ndarray


def read_fix_runs(root: str | Path, nodes: MapNodes, default_std_m: float = 1.5) -> list[FixRun]:
    """The runs of the tree at ``root`` that hold ``fixes.csv`` (fix-only runs), each checked:
    ``InputError`` naming the run whose fixes jump against its odometry or whose file is
    damaged."""
    out = []
    for k, run in enumerate(nodes.runs):
        found = read_run_fixes(Path(root) / run.name)
        if found is None:
            continue
        fixes, laid = found
        check_jumps(fixes, laid, run.name, default_std_m)
        out.append(FixRun(k, fixes, laid))
    if out:
        log.info("%d fix-only runs: %s", len(out), ", ".join(nodes.runs[f.run].name for f in out))
    return out


def measured_nodes(nodes: MapNodes, fix_runs: list[FixRun]) -> MapNodes:
    """``nodes`` as the graph measures them: a fix-only run's node poses moved by the fixes'
    error against the laid odometry at each node's time (the module doc); the other runs as
    they are. The laid poses (``nodes``) stay what the entries are re-laid from."""
    if not fix_runs:
        return nodes
    runs = list(nodes.runs)
    for f in fix_runs:
        run = runs[f.run]
        poses = run.poses.copy()
        poses[:, :3, 3] += fix_residuals_at(f.fixes, f.laid, run.stamps)
        runs[f.run] = replace(run, poses=poses)
    return MapNodes(runs)


def odometry_fallback(
    nodes: MapNodes, edges: list[Edge], fix_runs: list[FixRun], config: FixConfig
) -> list[Edge]:
    """``edges`` with each odometry step of a fix-only run whose registration failed (too
    low a fitness, no convergence, too little overlap) replaced by the laid (KISS-ICP) relative
    pose, accepted with :class:`FixConfig`'s covariance, as kind ``odometry-kiss-icp``. A
    registration gated out for moving the step far from KISS-ICP's is not replaced: one of the
    two lost its way, most often KISS-ICP in a sharp turn, and the fixes and the closures
    span that step."""
    fixed = {f.run for f in fix_runs}
    poses = nodes.poses
    out = []
    swapped = 0
    for e in edges:
        gated = (e.reason or "").startswith(GATED)
        failed = e.kind == "odometry" and not e.accepted and not gated
        if failed and int(nodes.run_of[e.source]) in fixed:
            rel = np.linalg.inv(poses[e.target]) @ poses[e.source]
            step = float(np.linalg.norm(rel[:3, 3]))
            sm = config.step_sigma_m + config.step_sigma_per_m * step
            sr = math.radians(config.step_sigma_deg)
            cov = np.diag([sm**2] * 3 + [sr**2] * 3)
            e = Edge("odometry-kiss-icp", e.target, e.source, rel, cov, e.fitness, e.constraint)
            swapped += 1
        out.append(e)
    if swapped:
        log.info("%d failed odometry steps of fix-only runs taken from KISS-ICP", swapped)
    return out
