"""What an alignment did, for a person: a JSON report and a PNG of the runs before and after.

The report lists the candidates, every closure with its fitness and whether it was accepted
(and why not), the odometry steps that failed, each run's correction, the edges' residuals
after the solve, the graph's error and the time of each stage.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.extras import pyplot
from pnvlad_service.fileio import atomic_write_text
from pnvlad_service.mapping.edges import Edge
from pnvlad_service.mapping.graph import Solution
from pnvlad_service.mapping.nodes import MapNodes


def _quantiles(x: np.ndarray | list[float]) -> dict[str, float]:
    a = np.asarray(x, dtype=np.float64)
    if not len(a):
        return {}
    p = np.percentile(a, [50, 90, 99])
    return {
        "median": round(float(p[0]), 4),
        "p90": round(float(p[1]), 4),
        "p99": round(float(p[2]), 4),
        "max": round(float(a.max()), 4),
    }


def run_corrections(nodes: MapNodes, solved: np.ndarray) -> list[dict[str, Any]]:
    """Per run: how far the solve moved its nodes (metres, horizontally) and turned them."""
    out = []
    for start, run in zip(nodes.starts(), nodes.runs, strict=True):
        a, b = run.poses, solved[start : start + len(run)]
        moved = np.linalg.norm(b[:, :2, 3] - a[:, :2, 3], axis=1)
        turned = np.degrees(np.abs(np.arctan2(b[:, 1, 0], b[:, 0, 0])))
        mean = (b[:, :2, 3] - a[:, :2, 3]).mean(axis=0)
        out.append(
            {
                "run": run.name,
                "nodes": len(run),
                "moved_m": _quantiles(moved),
                "turned_deg": _quantiles(turned),
                "mean_shift_en_m": [round(float(v), 4) for v in mean],
            }
        )
    return out


def edge_report(nodes: MapNodes, edges: list[Edge], solution: Solution) -> dict[str, Any]:
    """The closures (each), the odometry (counts and the rejected steps), the residuals."""
    closures = [e for e in edges if e.kind == "closure"]
    odometry = [e for e in edges if e.kind == "odometry"]
    res = dict(zip((id(e) for e in edges), solution.residuals, strict=True))
    rows = []
    for e in closures:
        row = e.to_json(nodes)
        if res[id(e)] is not None:
            row["residual_m"] = round(float(res[id(e)]), 4)  # type: ignore[arg-type]
        rows.append(row)
    by_kind = {}
    for name, group in (("odometry", odometry), ("closure", closures)):
        vals = [res[id(e)] for e in group if res[id(e)] is not None]
        by_kind[name] = _quantiles(vals)  # type: ignore[arg-type]
    return {
        "closures": {
            "verified_candidates": len(closures),
            "accepted": sum(e.accepted for e in closures),
            "rejected": sum(not e.accepted for e in closures),
            "fitness_accepted": _quantiles([e.fitness for e in closures if e.accepted]),
            "fitness_rejected": _quantiles([e.fitness for e in closures if not e.accepted]),
            "list": rows,
        },
        "odometry": {
            "steps": len(odometry),
            "accepted": sum(e.accepted for e in odometry),
            "rejected": [e.to_json(nodes) for e in odometry if not e.accepted],
        },
        "residuals_m": by_kind,
        "graph": {
            "error_before_after": [[round(a, 3), round(b, 3)] for a, b in solution.errors],
            "iterations": solution.iterations,
        },
    }


def write_report(path: str | Path, report: dict[str, Any]) -> Path:
    path = Path(path)
    atomic_write_text(path, json.dumps(report, indent=1, sort_keys=False) + "\n")
    return path


def plot_alignment(
    path: str | Path, nodes: MapNodes, edges: list[Edge], solved: np.ndarray
) -> Path:
    """Two panels: the runs as recorded (closures drawn: accepted green, rejected red) and as
    aligned; with the simulator's truth, each node's error as a colour."""
    plt = pyplot("the alignment's plot")
    recorded = nodes.poses
    truth = nodes.truth
    fig, axes = plt.subplots(1, 2, figsize=(14, 7), sharex=True, sharey=True)
    origin = recorded[:, :2, 3].min(axis=0)
    for ax, poses, title in ((axes[0], recorded, "recorded"), (axes[1], solved, "aligned")):
        xy = poses[:, :2, 3] - origin
        if truth is not None:
            err = np.linalg.norm(poses[:, :2, 3] - truth[:, :2, 3], axis=1)
            sc = ax.scatter(xy[:, 0], xy[:, 1], c=err, s=3, cmap="viridis", vmin=0, vmax=2.5)
            title += f": error median {np.median(err):.2f} m, p99 {np.percentile(err, 99):.2f} m"
        else:
            for start, run in zip(nodes.starts(), nodes.runs, strict=True):
                part = xy[start : start + len(run)]
                ax.plot(part[:, 0], part[:, 1], lw=0.8, label=run.name)
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlabel(f"easting - {origin[0]:.0f} (m)")
    xy0 = recorded[:, :2, 3] - origin
    for e in edges:
        if e.kind != "closure":
            continue
        a, b = xy0[e.source], xy0[e.target]
        axes[0].plot([a[0], b[0]], [a[1], b[1]], lw=0.6, color="g" if e.accepted else "r")
    axes[0].set_ylabel(f"northing - {origin[1]:.0f} (m)")
    if truth is not None:
        fig.colorbar(sc, ax=list(axes), label="position error against the truth (m)", shrink=0.8)
    else:
        axes[1].legend(fontsize=6)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
