"""The pose graph of a map's runs, solved by GTSAM.

Why GTSAM: the factor graph LIO-SAM and lt-mapper build their maps with, kept by its authors,
on PyPI for this Python (extra ``align``): its robust noise models, its Levenberg-Marquardt and
its custom factors are what this stage needs, and no solver is written here.

The variables are the nodes' true poses ``X`` (float64 [4, 4], local frame -> UTM, about a map
origin subtracted for conditioning). The factors:

- **The GNSS/INS chain** of each run (:class:`GnssModel`). A recording's error ``e`` (its
  position minus the true one, and the true frame's turn against the laid one) is a
  stationary walk that decorrelates over ``correlation_m`` (first-order Gauss-Markov: the
  simulator draws exactly that, an Ornstein-Uhlenbeck walk over the distance driven). So the
  first node has the prior ``e_0 ~ N(0, std^2)`` and each next one the factor
  ``e_{k+1} - a e_k ~ N(0, (1 - a^2) std^2)``, ``a = exp(-d / correlation_m)`` for the ``d``
  metres between them. This is every fix and every recorded step in one honest model: a run's
  kilometre of fixes is worth its correlated information, not one fix a node.
- **Odometry and closures** (:mod:`.edges`): ``BetweenFactorPose3`` with the registration's
  covariance under a robust kernel: Huber for a first solve from the recorded poses (where
  every closure is metres off and a redescending kernel would ignore the good ones too), then
  Cauchy from that solution (a wrong closure left metres off pulls with almost no force).
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


def _jr_inv(phi: np.ndarray) -> np.ndarray:
    """The inverse right Jacobian of SO(3) at ``phi``: float64 [3, 3]."""
    theta = float(np.linalg.norm(phi))
    K = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if theta < 1e-6:
        return np.eye(3) + 0.5 * K
    c = 1.0 / theta**2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    return np.eye(3) + 0.5 * K + c * K @ K


def _error(pose: np.ndarray, recorded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The recording's error of a node (recorded position minus the true one; the true frame's
    turn against the laid one, negated) [6], and its Jacobian [6, 6] in GTSAM's Pose3
    tangent (rotation, then translation; right perturbation)."""
    R, t = pose[:3, :3], pose[:3, 3]
    phi = _log_rot(R @ recorded[:3, :3].T)
    e = np.concatenate([recorded[:3, 3] - t, -phi])
    J = np.zeros((6, 6))
    J[:3, 3:] = -R
    J[3:, :3] = -_jr_inv(phi) @ recorded[:3, :3]
    return e, J


def _matrix(value: Any) -> np.ndarray:
    return np.asarray(value.matrix(), dtype=np.float64)


def _gnss_factors(
    gtsam: Any, graph: Any, nodes: MapNodes, poses: np.ndarray, model: GnssModel
) -> None:
    """The GNSS/INS chain of every run: a prior on its first node's error, then the walk."""
    sig = model.sigmas()
    for start, run in zip(nodes.starts(), nodes.runs, strict=True):
        rec0 = poses[start]

        def prior(this: Any, values: Any, H: Any, rec: np.ndarray = rec0) -> np.ndarray:
            e, J = _error(_matrix(values.atPose3(this.keys()[0])), rec)
            if H is not None:
                H[0] = J
            return e

        noise = gtsam.noiseModel.Diagonal.Sigmas(sig)
        graph.add(gtsam.CustomFactor(noise, [int(start)], prior))
        for k in range(len(run) - 1):
            a_g, b_g = start + k, start + k + 1
            d = float(np.linalg.norm(poses[b_g, :3, 3] - poses[a_g, :3, 3]))
            a = math.exp(-d / model.correlation_m)
            step = sig * math.sqrt(max(1.0 - a * a, 1e-6))

            def walk(
                this: Any,
                values: Any,
                H: Any,
                ra: Any = poses[a_g],
                rb: Any = poses[b_g],
                a: float = a,
            ) -> np.ndarray:
                keys = this.keys()
                ea, Ja = _error(_matrix(values.atPose3(keys[0])), ra)
                eb, Jb = _error(_matrix(values.atPose3(keys[1])), rb)
                if H is not None:
                    H[0] = -a * Ja
                    H[1] = Jb
                return eb - a * ea

            graph.add(gtsam.CustomFactor(gtsam.noiseModel.Diagonal.Sigmas(step), [a_g, b_g], walk))


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
    start = gtsam.Values()
    for g, pose in enumerate(recorded):
        start.insert(g, gtsam.Pose3(pose))
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
        values = run(huber, start)
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
