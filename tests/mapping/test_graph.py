"""The GNSS/INS walk in GTSAM's own factors is the first-order Gauss-Markov model it stands for:
the cost of any errors is the walk's, computed here from its textbook form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.mapping.graph import GnssModel, walk_weights


def walk_cost(e: np.ndarray, steps: np.ndarray, correlation: float) -> float:
    """``e_0^2 + sum (e_{k+1} - a_k e_k)^2 / (1 - a_k^2)``: the walk's negative log density
    (times two, unit stationary variance) of the errors ``e`` [N]."""
    a = np.exp(-steps / correlation)
    return float(e[0] ** 2 + np.sum((e[1:] - a * e[:-1]) ** 2 / (1 - a * a)))


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0.05, 400.0), min_size=0, max_size=30),
    st.floats(5.0, 200.0),
    st.integers(0, 2**31 - 1),
)
def test_priors_and_steps_are_the_walks_cost(steps: list, correlation: float, seed: int) -> None:
    steps_m = np.asarray(steps, np.float64)
    w, v = walk_weights(steps_m, GnssModel(correlation_m=correlation))
    assert w.shape == (len(steps) + 1,) and v.shape == (len(steps),)
    assert (w > 0).all() and (v >= 0).all()
    e = np.random.default_rng(seed).normal(0.0, 1.0, len(steps) + 1)
    cost = float(np.sum(w * e * e) + np.sum(v * np.diff(e) ** 2))
    assert cost == pytest.approx(walk_cost(e, steps_m, correlation), rel=1e-9, abs=1e-9)


def yaw_pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = [x, y, 0.0]
    return t


def test_the_graphs_gnss_cost_is_the_walks_for_a_whole_run() -> None:
    """A run recorded with yaw only, its poses moved by known position and heading errors: the
    GNSS/INS factors' error is half the walk's cost of those errors, axis by axis."""
    gtsam = pytest.importorskip("gtsam")
    from pnvlad_service.mapping.graph import _gnss_factors
    from pnvlad_service.mapping.nodes import MapNodes, RunNodes

    rng = np.random.default_rng(3)
    n = 40
    heading = np.cumsum(rng.normal(0, 8, n))
    xy = np.cumsum(5.0 * np.c_[np.cos(np.radians(heading)), np.sin(np.radians(heading))], 0)
    recorded = np.stack([yaw_pose(x, y, h) for (x, y), h in zip(xy, heading, strict=True)])
    run = RunNodes("d/r", np.arange(n, dtype=np.int64), recorded)
    model = GnssModel()
    graph = gtsam.NonlinearFactorGraph()
    _gnss_factors(gtsam, graph, MapNodes([run]), recorded, model)

    shift = rng.normal(0, 1.0, (n, 3))
    turn = np.radians(rng.normal(0, 0.8, n))  # heading errors only: exact in any axes
    values = gtsam.Values()
    for g in range(n):
        true = yaw_pose(*(xy[g] + shift[g, :2]), heading[g] + math.degrees(turn[g]))
        true[2, 3] = shift[g, 2]
        values.insert(g, gtsam.Pose3(true))
        values.insert(n + g, true[:3, 3].copy())
    values.insert(2 * n, np.zeros(3))

    steps = np.linalg.norm(np.diff(recorded[:, :3, 3], axis=0), axis=1)
    sig = model.sigmas()
    errors = [shift[:, 0], shift[:, 1], shift[:, 2], turn]
    scaled = [e / s for e, s in zip(errors, sig[[0, 1, 2, 5]], strict=True)]
    expected = sum(walk_cost(e, steps, model.correlation_m) for e in scaled)
    assert graph.error(values) == pytest.approx(expected / 2, rel=1e-6)
