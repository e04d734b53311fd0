"""The measured edges of the pose graph: each a registration between two nodes' clouds.

- **Odometry**: each node registered onto the one before it in its run, started from the
  recorded relative pose (:func:`odometry_edges`). The recorded poses already enter the graph
  as the GNSS/INS chain (:mod:`.graph`); the registration is the LiDAR's own measure of the
  step, centimetres where the GNSS/INS error changes by decimetres between keyframes.
- **Closures**: a node registered onto the nodes of another run (or of its own, farther along)
  that are candidates for the same place (:mod:`.candidates`), judged by the project's
  verification (:func:`~pnvlad_service.localization.verify.verify.verify`: any heading, the
  rival test and the constraint), then by the recorded poses: a verified closure that puts the
  two frames farther apart than the GNSS/INS error allows is rejected (``gate_m``).

Each accepted edge carries the point-to-plane covariance of its registration
(:func:`~pnvlad_service.localization.verify.prior.point_to_plane_covariance`, scaled): large
along a straight street whose facades leave the shift free.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.localization.verify.prior import NearTarget, point_to_plane_covariance
from pnvlad_service.localization.verify.verify import (
    Candidate,
    PreparedCache,
    QueryCloud,
    VerifyConfig,
    verify,
)
from pnvlad_service.mapping.nodes import MapNodes

log = logging.getLogger(__name__)


#: The verification of closures: the localiser's, each registration on one thread (one call at
#: a time here; two OpenMP threads on two busy cores wait at small_gicp's barriers: 37 ms a
#: registration against 3 ms on one, measured on a loaded 2-core machine).
MAPPING_VERIFY = VerifyConfig(registration=reg.RegistrationConfig(threads=1))

#: The odometry's registration: the verification's, at the keyframes' own resolution (0.5 m
#: voxels for the fine stage and its voxel map, where a keyframe's 4,096 points lie 0.2 to
#: 0.3 m apart; the verification's 1 m grid keeps a sixth of them). A facade's windows, where a
#: real sensor's rays pass the glass and return from behind it, lie deeper along each ray the
#: more squarely they are seen: averaged into 1 m voxels with the frames about them they make
#: tilted surfaces whose tilt turns with the view, and two scans 5 m apart then register about
#: 0.1 to 0.2 % longer than the step (measured on the simulator's sensors with each failure
#: switched off in turn: the glass alone makes it). Resolved at 0.5 m the bias is a third to
#: a half of it and the steps' spread smaller (docs/results/align.md).
ODOMETRY_REGISTRATION = reg.RegistrationConfig(threads=1, fine_voxel_m=0.5, vgicp_leaf_m=0.5)


@dataclass(frozen=True)
class EdgeConfig:
    """How edges are measured and judged.

    ``odometry_min_fitness``: an odometry registration scoring less is dropped (the GNSS/INS
    chain alone spans that step); ``odometry_gate_m`` / ``odometry_gate_deg``: ... as is one
    that moves the step farther than this from the recorded one (the GNSS/INS error changes by
    about half a metre between keyframes 5 m apart); ``gate_m``: a verified closure whose
    relative pose is farther than this from the recorded poses' is rejected (4 standard
    deviations of the difference of two independent GNSS/INS errors of 1.5 m); ``sigma_scale``:
    the point-to-plane standard deviations are multiplied by this (1: most edges then sit on
    the floors; on the demo city 1 left the map's p99 error at 0.88 m where 3 left 0.98 and 10
    1.29, the robust kernels taking the tail); ``min_sigma_m`` / ``min_sigma_deg``: floors of
    a closure's standard deviations, ``odometry_min_sigma_m`` / ``odometry_min_sigma_deg`` of an
    odometry edge's: about the edges' errors against the truth (odometry median 1 cm and 0.01
    degree, closures 2 cm and 0.02, docs/results/align.md); the odometry's turn floored at 0.1
    degree, five times its error, let the GNSS/INS fixes bend a run's last street 1.2 m where
    they were off together; ``verify``: the verification's settings; ``odometry``: the odometry's
    registration (:data:`ODOMETRY_REGISTRATION`); ``cache_entries``: prepared clouds kept."""

    odometry_min_fitness: float = 0.2
    odometry_gate_m: float = 3.0
    odometry_gate_deg: float = 5.0
    gate_m: float = 8.5
    sigma_scale: float = 1.0
    min_sigma_m: float = 0.03
    min_sigma_deg: float = 0.1
    odometry_min_sigma_m: float = 0.01
    odometry_min_sigma_deg: float = 0.01
    verify: VerifyConfig = field(default_factory=lambda: MAPPING_VERIFY)
    odometry: reg.RegistrationConfig = ODOMETRY_REGISTRATION
    cache_entries: int = 600

    def floors(self, odometry: bool) -> tuple[float, float]:
        """The floors (metres, degrees) of an odometry edge's or a closure's std."""
        if odometry:
            return self.odometry_min_sigma_m, self.odometry_min_sigma_deg
        return self.min_sigma_m, self.min_sigma_deg


@dataclass(frozen=True)
class Edge:
    """A measured relative pose: ``transform`` float64 [4, 4] lays node ``source``'s local
    frame into node ``target``'s; ``covariance`` float64 [6, 6] (translation in metres, then
    rotation in radians; target axes, about the source's origin), ``None`` when rejected;
    ``fitness``, ``constraint`` the registration's, ``confidence`` the verification's (closures);
    ``reason`` why it was rejected, else ``None``."""

    kind: str
    target: int
    source: int
    transform: np.ndarray
    covariance: np.ndarray | None
    fitness: float
    constraint: float
    confidence: float = 0.0
    reason: str | None = None

    @property
    def accepted(self) -> bool:
        return self.reason is None

    def to_json(self, nodes: MapNodes) -> dict[str, Any]:
        t = self.transform
        return {
            "kind": self.kind,
            "target": nodes.name(self.target),
            "source": nodes.name(self.source),
            "accepted": self.accepted,
            "reason": self.reason,
            "fitness": round(self.fitness, 4),
            "constraint": round(self.constraint, 5),
            "confidence": round(self.confidence, 4),
            "shift_m": [round(float(v), 4) for v in t[:3, 3]],
            "yaw_deg": round(math.degrees(math.atan2(t[1, 0], t[0, 0])), 4),
        }


class Clouds:
    """Prepared clouds of nodes (registration's :func:`~.registration.prepare`, role both, with
    each fine point's normal for the covariance), made once and kept in a bounded cache; by
    ``registration`` (default: the verification's, which the closures use;
    :meth:`for_odometry`: the odometry's), with the yaw search's spectra unless ``search`` is
    False (the odometry starts every step from the recorded one)."""

    def __init__(
        self,
        nodes: MapNodes,
        config: EdgeConfig,
        registration: reg.RegistrationConfig | None = None,
        search: bool = True,
    ) -> None:
        self.nodes = nodes
        self.config = registration or config.verify.registration
        self.search = search
        self.cache = PreparedCache(config.cache_entries)

    @classmethod
    def for_odometry(cls, nodes: MapNodes, config: EdgeConfig) -> Clouds:
        """The clouds :func:`odometry_edges` registers: prepared by ``config.odometry``."""
        return cls(nodes, config, config.odometry, search=False)

    def get(self, g: int) -> NearTarget:
        made = self.cache.get(g)
        if made is None:
            made = NearTarget.of(
                reg.prepare(self.nodes.metres(g), self.config, "both", self.search)
            )
            self.cache[g] = made
        return made


def edge_covariance(
    clouds: Clouds,
    source: int,
    target: int,
    transform: np.ndarray,
    config: EdgeConfig,
    odometry: bool = False,
) -> np.ndarray | None:
    """The scaled point-to-plane covariance of ``transform`` (source -> target), floored by
    the odometry's floors or the closures', or ``None`` when too few points overlap."""
    src = clouds.get(source).prepared
    inlier_m = clouds.config.inlier_m
    cov = point_to_plane_covariance(src.points, clouds.get(target), transform, inlier_m)
    if cov is None:
        return None
    cov = cov * config.sigma_scale**2
    m, deg = config.floors(odometry)
    return cov + np.diag([m**2] * 3 + [math.radians(deg) ** 2] * 3)


def odometry_edges(
    nodes: MapNodes, clouds: Clouds, config: EdgeConfig, fix_only: frozenset[int] = frozenset()
) -> list[Edge]:
    """Each node of each run registered onto the one before it, from the recorded relative
    pose, by ``clouds``' registration (:meth:`Clouds.for_odometry`: ``config.odometry``); an
    edge whose registration fails the fitness or the gate is kept, rejected, with its reason
    (the report lists it). The steps of the runs ``fix_only`` (indices; position fixes only,
    no recorded heading to check their turns) take the closures' floors."""
    from pnvlad_service.progress import tqdm

    poses = nodes.poses
    pairs = [
        (s + k, s + k + 1)
        for s, run in zip(nodes.starts(), nodes.runs, strict=True)
        for k in range(len(run) - 1)
    ]
    edges = []
    for target, source in tqdm(pairs, desc="odometry", unit="step", disable=None):
        recorded = np.linalg.inv(poses[target]) @ poses[source]
        r = reg.register(
            clouds.get(source).prepared, clouds.get(target).prepared, clouds.config, init=recorded
        )
        metres, degrees = reg.apart(r.transform, recorded)
        reason = r.reason
        if reason is None and r.fitness < config.odometry_min_fitness:
            reason = f"fitness {r.fitness:.2f} < {config.odometry_min_fitness}"
        if reason is None and (
            metres > config.odometry_gate_m or degrees > config.odometry_gate_deg
        ):
            reason = f"moved the step {metres:.2f} m, {degrees:.2f} deg from the recorded one"
        held = int(nodes.run_of[source]) not in fix_only
        cov = None if reason else edge_covariance(clouds, source, target, r.transform, config, held)
        if reason is None and cov is None:
            reason = "too few points overlap for a covariance"
        edges.append(
            Edge(
                "odometry", target, source, r.transform, cov, r.fitness, r.constraint, reason=reason
            )
        )
    return edges


def closure_edges(
    nodes: MapNodes,
    clouds: Clouds,
    candidates: Iterable[tuple[int, list[int]]],
    config: EdgeConfig,
) -> list[Edge]:
    """One closure per (query node, candidate group): the query verified against the group's
    nodes (verification's cascade and confidence), the best verified match gated by the
    recorded poses. Rejected ones are kept with their best fitness and the reason."""
    from pnvlad_service.progress import tqdm

    poses = nodes.poses
    edges = []
    groups = list(candidates)
    for query, group in tqdm(groups, desc="closures", unit="query", disable=None):
        src = clouds.get(query)
        q = QueryCloud(src.prepared.points, "sensor", "measured")
        cands = [
            Candidate(rank, np.empty((0, 3)), poses[g], key=g) for rank, g in enumerate(group, 1)
        ]
        cache = _Lookup(clouds)
        v = verify(q, cands, config.verify, cache=cache, query_key=query)
        if not v.checks:
            continue
        best = v.checks[0]
        target = group[best.rank - 1]
        edges.append(_judged(v, best, query, target, poses, clouds, config))
    return edges


def _judged(
    v: Any,
    best: Any,
    query: int,
    target: int,
    poses: np.ndarray,
    clouds: Clouds,
    config: EdgeConfig,
) -> Edge:
    """The closure edge of one verification: accepted, or rejected with its reason."""
    recorded = np.linalg.inv(poses[target]) @ poses[query]
    metres, _ = reg.apart(best.transform, recorded)
    reason = v.reason
    if reason is None and not v.verified:
        reason = f"not verified (confidence {v.confidence:.3f} < {v.threshold})"
    if reason is None and metres > config.gate_m:
        reason = f"{metres:.1f} m from the recorded poses (gate {config.gate_m:g} m)"
    cov = None if reason else edge_covariance(clouds, query, target, best.transform, config)
    if reason is None and cov is None:
        reason = "too few points overlap for a covariance"
    return Edge(
        "closure",
        target,
        query,
        best.transform,
        cov,
        best.score,
        best.constraint,
        v.confidence,
        reason,
    )


class _Lookup(dict):  # type: ignore[type-arg]
    """What :func:`verify` sees as its cache: every node's prepared cloud, made on demand by
    :class:`Clouds` (role both serves as source and as target)."""

    def __init__(self, clouds: Clouds) -> None:
        super().__init__()
        self.clouds = clouds

    def get(self, key: Any, default: Any = None) -> Any:
        g, _role = key
        return self.clouds.get(int(g)).prepared

    def __setitem__(self, key: Any, value: Any) -> None:  # made by Clouds already
        return None
