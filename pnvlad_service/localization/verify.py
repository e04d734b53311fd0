"""Geometric verification: re-rank the retrieved candidates by registering the query to each,
say whether the best one is sure, and give the query's pose on the map.

Retrieval (descriptor distances) is the first of two steps; this is the second. Each of the
top ``candidates`` database submaps is registered to the query
(:mod:`pnvlad_service.localization.registration`); its *score* is the registration's fitness,
the share of the query's points that land within the inlier distance of the candidate's
points. Candidates are re-ranked by score (retrieval order breaks ties); the answer is
``verified`` when the best score reaches ``threshold``, a figure chosen on training-layout
submaps (``pnvlad eval --rerank K`` reports the precision and recall of every threshold and
the one it would choose; see docs/VERIFY.md), never on test queries.

The pose: the registration gives ``T`` (query frame -> candidate's local frame, metres); the
bundle gives the candidate's local -> UTM pose ``M``; ``M @ T`` is the query frame's pose in
UTM. For a raw scan the query frame is the sensor's, so the pose is the sensor's. For a
preprocessed cloud the frame is centred on its centroid and the scale is the caller's (the
``scale`` of its frame sidecar), or estimated as the median of the candidates' scales; the
answer says which (``Pose.scale``).

Nothing here raises on a bad cloud: a degenerate query (all points on a line or a plane, or
too few distinct points) answers ``verified: false`` with the reason.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from pnvlad_service.localization import registration as reg

DEFAULT_CANDIDATES = 10


@dataclass(frozen=True)
class VerifyConfig:
    """How candidates are verified.

    ``candidates``: how many of the nearest (by descriptor) are registered (K);
    ``threshold``: the score at or above which the best match counts as verified;
    ``place_radius_m``: a candidate whose registration puts the query farther than this from
    its own origin is another place that shares some geometry with the query (a street seen
    from 30 m on): it ranks after the candidates that place the query within the radius;
    ``workers``: candidates registered at once (threads: small_gicp and NumPy's FFT release
    the GIL); ``registration``: the registration's settings.
    """

    candidates: int = DEFAULT_CANDIDATES
    threshold: float = 0.30
    place_radius_m: float = 25.0
    workers: int = 2
    registration: reg.RegistrationConfig = field(default_factory=reg.RegistrationConfig)

    def __post_init__(self) -> None:
        if not 1 <= self.candidates <= 100:
            raise ValueError(f"candidates must be 1..100, got {self.candidates}")
        if not 0.0 <= self.threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {self.threshold}")


@dataclass(frozen=True)
class QueryCloud:
    """A query's points in metres in its own frame.

    ``frame``: ``sensor`` (a raw scan through G: the pose is the sensor's) or ``centroid`` (a
    preprocessed cloud, centred on its centroid). ``scale``: ``measured`` (from G, or given by
    the caller) or ``estimated`` (from the candidates).
    """

    points_m: np.ndarray
    frame: Literal["sensor", "centroid"]
    scale: Literal["measured", "estimated"]

    @classmethod
    def from_normalised(
        cls,
        cloud: np.ndarray,
        *,
        centre: np.ndarray | None = None,
        scale: float | None = None,
        candidate_scales: Sequence[float] = (),
        sensor: bool = False,
    ) -> QueryCloud:
        """The metres of a normalised cloud: ``centre + scale * cloud``; without ``scale``,
        the median of ``candidate_scales`` (``estimated``)."""
        how: Literal["measured", "estimated"] = "measured"
        if scale is None:
            how = "estimated"
            scale = float(np.median(np.abs(candidate_scales))) if len(candidate_scales) else 1.0
        pts = np.asarray(cloud, dtype=np.float64) * scale
        if centre is not None:
            pts = pts + np.asarray(centre, dtype=np.float64)
        return cls(pts, "sensor" if sensor else "centroid", how)


@dataclass(frozen=True)
class Candidate:
    """One retrieved database submap to verify: its retrieval rank (1 = nearest descriptor),
    its points in metres (local frame), its local -> UTM pose float64 [4, 4], and a ``key``
    naming it in a ``cache`` of prepared clouds (see :func:`verify`)."""

    rank: int
    points_m: np.ndarray
    map_pose: np.ndarray
    key: Any = None


@dataclass(frozen=True)
class Check:
    """The registration of the query to one candidate (``transform``: query -> candidate
    local frame, float64 [4, 4])."""

    rank: int
    score: float
    rmse_m: float
    transform: np.ndarray


@dataclass(frozen=True)
class Pose:
    """The query frame's pose in UTM (metres; ``yaw_deg`` counter-clockwise from east) from
    the best verified match: ``transform`` float64 [4, 4] query frame -> UTM (easting,
    northing, height). ``fitness`` and ``rmse_m`` are that registration's; ``scale`` says
    whether the query's scale was measured or estimated."""

    easting: float
    northing: float
    height: float
    yaw_deg: float
    transform: np.ndarray
    fitness: float
    rmse_m: float
    frame: str
    scale: str

    @classmethod
    def from_check(cls, check: Check, cand: Candidate, query: QueryCloud) -> Pose:
        t = cand.map_pose @ check.transform
        return cls(
            easting=float(t[0, 3]),
            northing=float(t[1, 3]),
            height=float(t[2, 3]),
            yaw_deg=math.degrees(math.atan2(t[1, 0], t[0, 0])),
            transform=t,
            fitness=check.score,
            rmse_m=check.rmse_m,
            frame=query.frame,
            scale=query.scale,
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "northing": self.northing,
            "easting": self.easting,
            "height": self.height,
            "yaw_deg": self.yaw_deg,
            "transform": [[float(v) for v in row] for row in self.transform],
            "fitness": self.fitness,
            "rmse_m": self.rmse_m,
            "frame": self.frame,
            "scale": self.scale,
        }


@dataclass(frozen=True)
class Verification:
    """The outcome: ``checks`` best score first (the re-ranked order), ``verified`` when the
    best reaches the threshold, ``pose`` from it (``None`` unless verified), ``reason`` when
    nothing could be verified (a degenerate query)."""

    verified: bool
    checks: tuple[Check, ...]
    pose: Pose | None
    threshold: float
    reason: str | None = None
    seconds: float = 0.0

    @property
    def order(self) -> list[int]:
        """Retrieval ranks in the re-ranked order."""
        return [c.rank for c in self.checks]

    @property
    def best_score(self) -> float:
        return self.checks[0].score if self.checks else 0.0


_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """One shared pool of ``workers`` threads (a process verifies with few threads, whatever
    the number of requests in flight: the cores are the limit)."""
    with _POOLS_LOCK:
        if workers not in _POOLS:
            _POOLS[workers] = ThreadPoolExecutor(workers, thread_name_prefix="pnvlad-verify")
        return _POOLS[workers]


def rerank(checks: Sequence[Check], place_radius_m: float = math.inf) -> tuple[Check, ...]:
    """Candidates that place the query within ``place_radius_m`` of their origin first, each
    group best score first; the retrieval rank breaks ties (stable)."""

    def far(c: Check) -> bool:
        return bool(np.hypot(c.transform[0, 3], c.transform[1, 3]) > place_radius_m)

    return tuple(sorted(checks, key=lambda c: (far(c), -c.score, c.rank)))


def verify(
    query: QueryCloud,
    candidates: Sequence[Candidate],
    config: VerifyConfig,
    *,
    cache: dict[Any, Any] | None = None,
    query_key: Any = None,
) -> Verification:
    """Register ``query`` to each candidate, re-rank, decide and pose (see the module doc).

    ``cache`` (evaluation, where a submap is a candidate of many queries): prepared clouds by
    ``Candidate.key`` and ``query_key``, filled as they are made."""
    t0 = time.perf_counter()

    def refused(reason: str) -> Verification:
        checks = tuple(Check(c.rank, 0.0, math.inf, np.eye(4)) for c in candidates)
        return Verification(False, checks, None, config.threshold, reason, time.perf_counter() - t0)

    if not candidates:
        return refused("no candidates")

    def prepared(points: np.ndarray, key: Any, role: str) -> Any:
        if cache is None or key is None:
            return reg.prepare(points, config.registration, role)  # type: ignore[arg-type]
        if (key, role) not in cache:
            cache[(key, role)] = reg.prepare(points, config.registration, role)  # type: ignore[arg-type]
        return cache[(key, role)]

    source = prepared(query.points_m, query_key, "source")
    if source.reason is not None:  # a line, a plane, too few distinct points (reg.prepare)
        return refused(f"query: {source.reason}")

    def check(cand: Candidate) -> Check:
        r = reg.register(source, prepared(cand.points_m, cand.key, "target"), config.registration)
        return Check(cand.rank, float(r.fitness), float(r.rmse_m), r.transform)

    if config.workers > 1 and len(candidates) > 1:
        checks = list(_pool(config.workers).map(check, candidates))
    else:
        checks = [check(c) for c in candidates]
    ordered = rerank(checks, config.place_radius_m)
    best = ordered[0]
    verified = best.score >= config.threshold
    pose = None
    if verified:
        cand = next(c for c in candidates if c.rank == best.rank)
        pose = Pose.from_check(best, cand, query)
    return Verification(verified, ordered, pose, config.threshold, None, time.perf_counter() - t0)
