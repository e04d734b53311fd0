"""The pose graph of a map's runs, solved by GTSAM.

Why GTSAM: the factor graph LIO-SAM and lt-mapper build their maps with, kept by its authors,
on PyPI for this Python (extra ``align``): its robust noise models, its Levenberg-Marquardt and
its factors are what this stage needs, and no solver is written here. Every factor is one of
GTSAM's own (C++): a Python factor costs a call into the interpreter per factor and
linearisation, seconds an iteration for a district's 3,000 nodes.

The variables are the nodes' true poses ``X`` (float64 [4, 4], local frame -> UTM, about a map
origin subtracted for conditioning). The factors:

- **The GNSS/INS chain** of each run (:class:`GnssModel`). A recording's error ``e`` (its
  position minus the true one, and the true frame's turn against the laid one) is a
  stationary walk that decorrelates over ``correlation_m`` (first-order Gauss-Markov: the
  simulator draws exactly that, an Ornstein-Uhlenbeck walk over the distance driven). So the
  first node has the prior ``e_0 ~ N(0, std^2)`` and each next one the factor
  ``e_{k+1} - a e_k ~ N(0, (1 - a^2) std^2)``, ``a = exp(-d / correlation_m)`` for the ``d``
  metres between them. This is every fix and every recorded step in one honest model: a run's
  kilometre of fixes is worth its correlated information, not one fix a node. The same cost is
  written as a prior on each node's error and a between factor on each step's change of it
  (:func:`walk_weights`), so that GTSAM's own factors carry it.
- **Odometry and closures** (:mod:`.edges`): ``BetweenFactorPose3`` with the registration's
  covariance under a robust kernel: Huber for a first solve from the recorded poses (where
  every closure is metres off and a redescending kernel would ignore the good ones too), then
  Cauchy from that solution (a wrong closure left metres off pulls with almost no force).
  Each solve after the first starts from the one before it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pnvlad_service.extras import require
from pnvlad_service.mapping.edges import Edge
from pnvlad_service.mapping.nodes import MapNodes

log = logging.getLogger(__name__)

#: The walk's largest step correlation (``1 - a^2`` at least 1e-6: two nodes at one place).
A_MAX = math.sqrt(1.0 - 1e-6)
#: How tightly a node's position variable is tied to its pose's translation (metres).
TIE_M = 1e-3
#: The standard deviation that leaves a factor's translation free (metres).
FREE_M = 1e4


@dataclass(frozen=True)
class GnssModel:
    """The recorded poses' error as a Gauss-Markov walk over distance: ``position_std_m``
    (horizontal, both axes together: 1.5 m is ~1.06 m an axis), ``height_std_m``,
    ``heading_std_deg``, ``tilt_std_deg`` (roll and pitch), ``correlation_m``. The defaults are
    the simulator's (``RunConditions``); a receiver's datasheet gives a real one's."""

    position_std_m: float = 1.5
    height_std_m: float = 0.5
    heading_std_deg: float = 0.8
    tilt_std_deg: float = 0.5
    correlation_m: float = 60.0

    def sigmas(self) -> np.ndarray:
        """float64 [6]: the stationary std of (east, north, height, roll, pitch, yaw) error."""
        xy = self.position_std_m / math.sqrt(2.0)
        tilt, yaw = math.radians(self.tilt_std_deg), math.radians(self.heading_std_deg)
        return np.array([xy, xy, self.height_std_m, tilt, tilt, yaw])


@dataclass(frozen=True)
class GraphConfig:
    """``gnss``: the recorded poses' error model; ``huber_k`` / ``cauchy_k``: the kernels'
    widths in standard deviations of an edge (``cauchy_k`` None: Huber only);
    ``outlier_sigma``: a closure the first solve leaves more than this many standard deviations
    off is set aside and the Huber solve run again, until the set holds (at most
    ``outlier_rounds`` times: a closure set aside while the map was bent comes back once it is
    not; a wrong closure pulls a Huber solve with a bounded force, and a Cauchy solve started
    from the bend may keep some of it); ``iterations`` and
    ``tolerance`` (relative decrease of the error): Levenberg-Marquardt's stops per solve."""

    gnss: GnssModel = field(default_factory=GnssModel)
    huber_k: float = 1.345
    cauchy_k: float | None = 1.0
    outlier_sigma: float = 10.0
    outlier_rounds: int = 3
    iterations: int = 100
    tolerance: float = 1e-6


@dataclass
class Solution:
    """The solved poses float64 [N, 4, 4] (local -> UTM) of every node, the graph's error
    before and after each solve, the iterations, each edge's residual after the last solve
    (metres; ``None`` for an edge rejected before the solve) and the edges (their indices)
    the solve set aside as outliers."""

    poses: np.ndarray
    errors: list[tuple[float, float]]
    iterations: list[int]
    residuals: list[float | None]
    seconds: float
    dropped: list[int] = field(default_factory=list)


def _gtsam() -> Any:
    return require("gtsam", "gtsam", "align", "aligning a map's runs (pnvlad map align)")


def _log_rot(R: np.ndarray) -> np.ndarray:
    """so(3) log of a rotation matrix: float64 [3] (angle-axis)."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    theta = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return 0.5 * w if theta < 1e-9 else theta / (2.0 * math.sin(theta)) * w


def walk_weights(steps_m: np.ndarray, model: GnssModel) -> tuple[np.ndarray, np.ndarray]:
    """The Gauss-Markov walk of a run's error as node priors and step differences.

    The walk's cost ``e_0^2 + sum_k (e_{k+1} - a_k e_k)^2 / (1 - a_k^2)`` (in units of the
    stationary variance; ``a_k = exp(-steps_m[k] / correlation_m)``) is, for any ``e``,
    exactly ``sum_k w_k e_k^2 + sum_k v_k (e_{k+1} - e_k)^2`` with ``v_k = a_k / (1 - a_k^2)``
    and ``w_k = 1 / (1 + a_{k-1}) - a_k / (1 + a_k)`` (the first node without the first
    term and the last without the second, each then ``1 / (1 + a)``; a lone node 1): every
    ``w_k`` and ``v_k`` is at least 0, so both are plain priors and between factors with
    standard deviations ``std / sqrt(w)``. Returns ``w`` float64 [N] and ``v`` [N - 1] for
    the ``N - 1`` ``steps_m``."""
    a = np.minimum(np.exp(-np.asarray(steps_m, np.float64) / model.correlation_m), A_MAX)
    w = np.ones(len(a) + 1)
    w[1:] = 1.0 / (1.0 + a)
    w[:-1] -= a / (1.0 + a)
    return w, a / (1.0 - a * a)


def _matrix(value: Any) -> np.ndarray:
    return np.asarray(value.matrix(), dtype=np.float64)


def _diag(gtsam: Any, sigmas: np.ndarray) -> Any:
    return gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigmas, np.float64))


def _gnss_factors(
    gtsam: Any, graph: Any, nodes: MapNodes, poses: np.ndarray, model: GnssModel
) -> None:
    """The GNSS/INS chain of every run in GTSAM's own factors (see :func:`walk_weights`).

    A node's position error is its position variable ``P`` (float [3], tied to the pose's
    translation by a ``ReferenceFrameFactor`` against one shared zero point) minus the
    recorded position: a ``PriorFactorPoint3`` per node and a ``BetweenFactorPoint3`` per step,
    world axes. Its heading and tilt error is the pose's turn against the recorded one: a
    ``PoseRotationPrior3D`` per node and a ``BetweenFactorPose3`` per step (the recorded
    relative pose) whose translation is left free; both take the turn about the recorded
    frame's axes, the same as about the world's for a recording whose roll and pitch are zero
    and otherwise up to the tilt's mix of the heading and tilt standard deviations."""
    sig = model.sigmas()
    n = len(poses)
    zero = 2 * n
    pin = gtsam.noiseModel.Isotropic.Sigma(3, TIE_M)
    graph.add(gtsam.PriorFactorPoint3(zero, np.zeros(3), pin))
    tie = gtsam.noiseModel.Isotropic.Sigma(3, TIE_M)
    free = np.full(3, FREE_M)
    for start, run in zip(nodes.starts(), nodes.runs, strict=True):
        stop = start + len(run)
        centres = poses[start:stop, :3, 3]
        prior_w, step_w = walk_weights(np.linalg.norm(np.diff(centres, axis=0), axis=1), model)
        for g in range(start, stop):
            graph.add(gtsam.ReferenceFrameFactorPoint3Pose3(zero, g, n + g, tie))
            s = sig / math.sqrt(prior_w[g - start])
            graph.add(gtsam.PriorFactorPoint3(n + g, poses[g, :3, 3], _diag(gtsam, s[:3])))
            turn = gtsam.Rot3(poses[g, :3, :3])
            graph.add(gtsam.PoseRotationPrior3D(g, turn, _diag(gtsam, s[3:])))
        for k, w in enumerate(step_w):
            if w <= 0.0:
                continue
            a_g, b_g = start + k, start + k + 1
            s = sig / math.sqrt(w)
            d = poses[b_g, :3, 3] - poses[a_g, :3, 3]
            graph.add(gtsam.BetweenFactorPoint3(n + a_g, n + b_g, d, _diag(gtsam, s[:3])))
            rel = gtsam.Pose3(np.linalg.inv(poses[a_g]) @ poses[b_g])
            noise = _diag(gtsam, np.r_[s[3:], free])
            graph.add(gtsam.BetweenFactorPose3(a_g, b_g, rel, noise))


def _edge_covariance(edge: Edge) -> np.ndarray:
    """The edge's covariance in GTSAM's tangent of the measured pose: float64 [6, 6]
    (rotation, then translation, source axes)."""
    R = edge.transform[:3, :3]
    rot = np.zeros((6, 6))
    rot[:3, :3] = rot[3:, 3:] = R.T
    cov = rot @ edge.covariance @ rot.T  # type: ignore[operator]
    order = [3, 4, 5, 0, 1, 2]
    cov = cov[np.ix_(order, order)]
    return (cov + cov.T) / 2


def mahalanobis(edge: Edge, poses: np.ndarray) -> float:
    """How many standard deviations (Mahalanobis) ``poses`` [N, 4, 4] leave ``edge`` off."""
    d = np.linalg.inv(edge.transform) @ np.linalg.inv(poses[edge.target]) @ poses[edge.source]
    xi = np.concatenate([_log_rot(d[:3, :3]), d[:3, 3]])
    return float(math.sqrt(max(xi @ np.linalg.solve(_edge_covariance(edge), xi), 0.0)))


def _optimise(
    gtsam: Any,
    nodes: MapNodes,
    recorded: np.ndarray,
    edges: list[Edge],
    kernel: Any,
    start: Any,
    config: GraphConfig,
) -> tuple[Any, tuple[float, float], int]:
    """One Levenberg-Marquardt solve of the GNSS/INS chains and ``edges`` under ``kernel``
    from ``start``: the values, the error before and after, the iterations."""
    graph = gtsam.NonlinearFactorGraph()
    _gnss_factors(gtsam, graph, nodes, recorded, config.gnss)
    for e in edges:
        noise = gtsam.noiseModel.Gaussian.Covariance(_edge_covariance(e))
        robust = gtsam.noiseModel.Robust.Create(kernel, noise)
        graph.add(gtsam.BetweenFactorPose3(e.target, e.source, gtsam.Pose3(e.transform), robust))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.iterations)
    params.setRelativeErrorTol(config.tolerance)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, start, params)
    values = optimizer.optimize()
    return values, (float(graph.error(start)), float(graph.error(values))), optimizer.iterations()


def _poses(values: Any, n: int) -> np.ndarray:
    return np.stack([_matrix(values.atPose3(g)) for g in range(n)])


def solve(
    nodes: MapNodes, edges: list[Edge], config: GraphConfig, origin: np.ndarray | None = None
) -> Solution:
    """Solve the graph of ``nodes`` (their recorded poses the start) and the accepted
    ``edges``: Huber from the recorded poses; the closures that solution leaves more than
    ``outlier_sigma`` off set aside (``Solution.dropped``) and Huber again without them; then
    Cauchy from there (see the module doc). Poses come back in UTM."""
    gtsam = _gtsam()
    started = time.perf_counter()
    recorded = nodes.poses.copy()
    shift = recorded[0, :3, 3].copy() if origin is None else np.asarray(origin, np.float64)
    recorded[:, :3, 3] -= shift
    kept = [i for i, e in enumerate(edges) if e.accepted]
    n = len(recorded)
    start = gtsam.Values()
    for g, pose in enumerate(recorded):
        start.insert(g, gtsam.Pose3(pose))
        start.insert(n + g, pose[:3, 3].copy())
    start.insert(2 * n, np.zeros(3))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k)
    errors, iterations = [], []

    def run(kernel: Any, initial: Any) -> Any:
        values, err, its = _optimise(
            gtsam, nodes, recorded, [edges[i] for i in kept], kernel, initial, config
        )
        errors.append(err)
        iterations.append(int(its))
        return values

    values = run(huber, start)
    accepted = list(kept)
    for _ in range(config.outlier_rounds):
        solved = _poses(values, len(recorded))
        within = [
            i for i in accepted
            if edges[i].kind != "closure" or mahalanobis(edges[i], solved) <= config.outlier_sigma
        ]  # fmt: skip
        if within == kept:
            break
        kept = within
        values = run(huber, values)
    dropped = [i for i in accepted if i not in set(kept)]
    if dropped:
        log.info("%d closures over %g sigma off: set aside", len(dropped), config.outlier_sigma)
    if config.cauchy_k is not None:
        values = run(gtsam.noiseModel.mEstimator.Cauchy.Create(config.cauchy_k), values)
    poses = _poses(values, len(recorded))
    poses[:, :3, 3] += shift
    residuals = _residuals(edges, poses)
    log.info("graph: %d nodes, %d edges; error %s", len(poses), len(kept), errors)
    return Solution(poses, errors, iterations, residuals, time.perf_counter() - started, dropped)


def _residuals(edges: list[Edge], poses: np.ndarray) -> list[float | None]:
    """Each accepted edge's residual after the solve: how far (metres) the solved poses put
    the source's origin from where the edge measured it; ``None`` for a rejected edge."""
    out: list[float | None] = []
    for e in edges:
        if not e.accepted:
            out.append(None)
            continue
        solved = np.linalg.inv(poses[e.target]) @ poses[e.source]
        out.append(float(np.linalg.norm(solved[:3, 3] - e.transform[:3, 3])))
    return out
