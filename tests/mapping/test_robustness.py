"""Wrong closures injected on purpose (entries of other runs far apart, claimed to be one place
with the tight covariance of a good registration, as a fooled verification would hand them)
move no entry of the map more than 0.5 m from where the clean solution puts it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")


def wrong_closures(nodes, count: int, min_apart_m: float, seed: int = 0) -> list:
    """``count`` closures between nodes of different runs at least ``min_apart_m`` apart by
    their recorded poses, each claiming the two frames coincide (turned by a few degrees)."""
    from pnvlad_service.mapping.edges import Edge

    rng = np.random.default_rng(seed)
    xy = nodes.poses[:, :2, 3]
    out = []
    while len(out) < count:
        a, b = (int(v) for v in rng.integers(0, len(nodes), 2))
        far = np.hypot(*(xy[a] - xy[b])) >= min_apart_m
        if nodes.run_of[a] == nodes.run_of[b] or not far:
            continue
        t = np.eye(4)
        yaw = np.radians(rng.uniform(-5, 5))
        t[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        t[:2, 3] = rng.uniform(-1, 1, 2)
        cov = np.diag([0.03**2] * 3 + [np.radians(0.1) ** 2] * 3)
        out.append(Edge("closure", a, b, t, cov, 0.8, 0.3, 0.5))
    return out


def test_wrong_closures_do_not_bend_the_map(tiny: Path) -> None:
    from pnvlad_service.mapping.align import AlignConfig, _Timer, measure_edges
    from pnvlad_service.mapping.graph import solve
    from pnvlad_service.mapping.nodes import read_tree_nodes

    nodes = read_tree_nodes(tiny)
    config = AlignConfig()
    edges, _ = measure_edges(nodes, config, _Timer())
    clean = solve(nodes, edges, config.graph)
    injected = wrong_closures(nodes, count=8, min_apart_m=60.0)
    bent = solve(nodes, edges + injected, config.graph)
    moved = np.linalg.norm(bent.poses[:, :3, 3] - clean.poses[:, :3, 3], axis=1)
    assert moved.max() <= 0.5, f"an entry moved {moved.max():.2f} m"
    # the alignment itself moved the map (the check is not of a graph that cannot move)
    assert np.median(np.linalg.norm(clean.poses[:, :2, 3] - nodes.poses[:, :2, 3], axis=1)) > 0.2
    # and the wrong closures are left far off in the solution: set aside, not obeyed
    residuals = bent.residuals[len(edges) :]
    assert min(r for r in residuals if r is not None) > 10.0
    assert set(range(len(edges), len(edges) + 8)) <= set(bent.dropped)


def test_without_robust_kernels_the_same_closures_would_bend_it(tiny: Path) -> None:
    """The injected closures are strong enough to matter: under a plain Gaussian (a Huber
    kernel wide enough never to bend, nothing set aside) they drag entries metres."""
    from pnvlad_service.mapping.align import AlignConfig, _Timer, measure_edges
    from pnvlad_service.mapping.graph import GraphConfig, solve
    from pnvlad_service.mapping.nodes import read_tree_nodes

    nodes = read_tree_nodes(tiny)
    config = AlignConfig()
    edges, _ = measure_edges(nodes, config, _Timer())
    gaussian = GraphConfig(huber_k=1e9, cauchy_k=None, outlier_sigma=math.inf)
    clean = solve(nodes, edges, gaussian)
    bent = solve(nodes, edges + wrong_closures(nodes, count=8, min_apart_m=60.0), gaussian)
    moved = np.linalg.norm(bent.poses[:, :3, 3] - clean.poses[:, :3, 3], axis=1)
    assert moved.max() > 5.0


def test_odometry_steps_take_their_own_floor_and_a_fix_only_runs_the_closures(tiny: Path) -> None:
    """A run with recorded GNSS/INS poses has its steps floored at the odometry's floors; a
    fix-only run's steps (no recorded heading to check their turns) at the closures'."""
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, odometry_edges
    from pnvlad_service.mapping.nodes import read_tree_nodes

    nodes = read_tree_nodes(tiny)
    config = EdgeConfig(
        min_sigma_m=0.5, min_sigma_deg=2.0, odometry_min_sigma_m=0.2, odometry_min_sigma_deg=1.0
    )
    edges = odometry_edges(nodes, Clouds.for_odometry(nodes, config), config, frozenset({0}))
    by_run: dict[int, list[np.ndarray]] = {}
    for e in edges:
        if e.accepted:
            by_run.setdefault(int(nodes.run_of[e.source]), []).append(
                np.sqrt(np.diag(e.covariance))
            )
    assert set(by_run) == set(range(len(nodes.runs)))
    for run, stds in by_run.items():
        m, deg = (0.5, 2.0) if run == 0 else (0.2, 1.0)
        s = np.array(stds)
        # the registration's own std is millimetres and hundredths of a degree: the floor rules
        assert np.allclose(np.median(s[:, :3], axis=0), m, atol=0.02), (run, s[:, :3].min())
        assert np.allclose(np.degrees(np.median(s[:, 3:], axis=0)), deg, atol=0.1), run
