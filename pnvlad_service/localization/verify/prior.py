"""Registration near a prior pose: where the caller says it is, checked against the map there.

A robot that already knows roughly where it is (the pose of its last verified fix moved on by
its odometry: :mod:`~pnvlad_service.localization.drive.tracking`) need not ask the encoder at
all. The map's entries within a radius of the prior are found by a range search over the bundle's
positions (:class:`MapPositions`, no embedding); their points, from the bundle's geometry, are
laid together in the frame of the nearest (the *anchor*); the scan is registered to them from
the prior (:func:`~.registration.register` with ``init``: no yaw search) and the result is the
scan's pose on the map with its fitness and a covariance.

Which entries: those of the anchor's run only (``PriorConfig.same_run``). A map made of several
drives holds each drive's entries where that drive's own poses put them; two drives' entries
of one street disagree by their pose errors (metres, for GNSS/INS), and registering to both at
once fits neither. One drive's consecutive entries agree with each other to within its pose
error's change over a few metres. The anchor is the nearest entry of the prior's ``run`` (the
drive of the map the caller's last pose was registered to) when that drive has one within the
radius, else the nearest entry: a tracked robot stays in one drive's frame as long as it can,
instead of jumping by the drives' disagreement from one scan to the next.

The covariance (:func:`point_to_plane_covariance`) is the inverse of the point-to-plane
Gauss-Newton Hessian at the solution, scaled by the residuals' variance: in a street whose
facades leave the shift along it free, it is large along the street, which is what the caller
weighs (small_gicp's own Hessian is of normalised point covariances and says too little of
that). Order and units as ROS's ``PoseWithCovariance``: x (easting), y (northing), z (height)
in metres, then rotations about x, y, z in radians, about the sensor, in UTM axes.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.localization.verify.scale import drive_groups
from pnvlad_service.localization.verify.verify import Candidate, Check, Pose, QueryCloud

T = TypeVar("T")

#: Prepared targets near priors a localiser keeps (apart from verification's cache of single
#: candidates): a tracked robot's target changes every few metres and is not asked for again
#: once passed, so a few suffice; each holds up to ``max_submaps`` entries' points, prepared
#: (4 of the demo's keyframes: about 1.4 MB, measured by the resident memory of 20).
NEAR_CACHE_ENTRIES = 16

#: Radius a prior request searches when it gives none, metres (docs/TRACKING.md: the map's
#: keyframes are 5 m apart and a scan keeps 50 m; 20 m holds the 4-8 nearest of one drive).
DEFAULT_RADIUS_M = 20.0

#: Entries a prior registers to on a map whose drives agree (``pnvlad map align``): the nearest
#: of any of its drives, where one drive's would be 4 (docs/TRACKING.md, "On an aligned map").
ALIGNED_ENTRIES = 8
#: ... and the wider target a registration that fits under the threshold is tried once more
#: against: 8 entries of four drives, 2.5 m apart, cover about 5 m of a street that the scan
#: sees 50 m of, and fit some stretches under 0.4 where the pose is right (docs/TRACKING.md).
ALIGNED_RETRY_ENTRIES = 24
#: What the wider target's fit must exceed the threshold by. 0: with the 1 m limit below, a
#: margin of 0.05 only cost right poses (every benchmark run followed: 13 of 15 at 99 % within
#: 1 m and 2 degrees with 0, 12 with 0.05, none wrong with either); a wider stretch fits a prior
#: 5-15 m along the street more often, which the tracker's gates keep it from asking
#: (docs/TRACKING.md).
RETRY_MARGIN = 0.0
#: ... and how far at most it may move the sensor from the prior, metres: along a street the
#: wider stretch can also slide the right prior to a wrong place (a retry that moved a campus
#: drive's prediction 1.7 m along its street started 30 poses 4-6 m off; the rescues that keep
#: a drive tracked moved it 0.1-1.0 m: docs/TRACKING.md).
RETRY_MAX_CORRECTION_M = 1.0


@dataclass(frozen=True)
class Prior:
    """Where the caller says its sensor is: UTM ``northing`` and ``easting`` (metres), ``yaw_deg``
    (heading of the sensor's x axis, counter-clockwise from east), ``height`` (metres, as the
    map's poses have it; ``None``: the anchor entry's), the ``radius_m`` to search, and the
    ``run`` of the map (``dataset/run``) to register to when it has entries there."""

    northing: float
    easting: float
    yaw_deg: float
    radius_m: float = DEFAULT_RADIUS_M
    height: float | None = None
    run: str | None = None

    def matrix(self, height: float) -> np.ndarray:
        """float64 [4, 4] sensor -> UTM (easting, northing, height), level, at ``height``
        unless the prior gives its own."""
        return pose_matrix(
            self.easting, self.northing, self.height if self.height is not None else height,
            self.yaw_deg,
        )  # fmt: skip

    @classmethod
    def of_matrix(
        cls, pose: np.ndarray, radius_m: float = DEFAULT_RADIUS_M, run: str | None = None
    ) -> Prior:
        """The prior of a sensor -> UTM pose float [4, 4] (its yaw; roll and pitch dropped)."""
        t = np.asarray(pose, dtype=np.float64)
        return cls(
            northing=float(t[1, 3]),
            easting=float(t[0, 3]),
            yaw_deg=math.degrees(math.atan2(t[1, 0], t[0, 0])),
            radius_m=float(radius_m),
            height=float(t[2, 3]),
            run=run,
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "northing": self.northing,
            "easting": self.easting,
            "yaw_deg": self.yaw_deg,
            "height": self.height,
            "radius_m": self.radius_m,
            "run": self.run,
        }


def pose_matrix(easting: float, northing: float, height: float, yaw_deg: float) -> np.ndarray:
    """float64 [4, 4]: a level pose at (easting, northing, height), x axis ``yaw_deg`` from east."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = (easting, northing, height)
    return out


@dataclass(frozen=True)
class PriorConfig:
    """How a scan is registered near a prior.

    ``max_submaps``: the nearest entries within the radius laid together (of the anchor's run
    with ``same_run``); ``min_fitness``: the share of the scan's points within
    ``registration.inlier_m`` of the map after registration at or above which the pose is
    verified; ``max_sigma_m``: ... and the largest horizontal standard deviation of the
    covariance at most this (``None``: not checked); ``sigma_scale``: the point-to-plane
    covariance's standard deviations are multiplied by this (its residuals are not independent:
    neighbouring points share the map's own errors, and unscaled it put the demo's errors at
    about 20 of its standard deviations); ``max_correction_m``: a registration
    that moves the sensor farther than this from the prior is refused (it slid to another
    place; ``None``: the radius); ``registration``: the registration's settings (it starts
    from the prior: no yaw search). The defaults are measured (docs/TRACKING.md).
    """

    max_submaps: int = 4
    same_run: bool = True
    min_fitness: float = 0.4
    max_sigma_m: float | None = 1.0
    sigma_scale: float = 18.0
    max_correction_m: float | None = None
    retry_submaps: int = 0
    retry_margin: float = RETRY_MARGIN
    retry_max_correction_m: float = RETRY_MAX_CORRECTION_M
    registration: reg.RegistrationConfig = field(default_factory=reg.RegistrationConfig)

    def __post_init__(self) -> None:
        if not 1 <= self.max_submaps <= 64:
            raise ValueError(f"max_submaps must be 1..64, got {self.max_submaps}")
        if self.retry_submaps and not self.max_submaps < self.retry_submaps <= 64:
            raise ValueError(
                f"retry_submaps must be 0 or more than max_submaps ({self.max_submaps}) and at "
                f"most 64, got {self.retry_submaps}"
            )
        if not 0.0 <= self.retry_margin <= 1.0:
            raise ValueError(f"retry_margin must be in [0, 1], got {self.retry_margin}")
        if not self.retry_max_correction_m > 0:
            raise ValueError(
                f"retry_max_correction_m must be > 0, got {self.retry_max_correction_m}"
            )
        if not 0.0 <= self.min_fitness <= 1.0:
            raise ValueError(f"min_fitness must be in [0, 1], got {self.min_fitness}")
        if self.max_sigma_m is not None and not self.max_sigma_m > 0:
            raise ValueError(f"max_sigma_m must be > 0 or None, got {self.max_sigma_m}")
        if not self.sigma_scale > 0:
            raise ValueError(f"sigma_scale must be > 0, got {self.sigma_scale}")


@dataclass(frozen=True)
class Nearby:
    """The map entries a prior registers against: bundle ``rows`` nearest first (``rows[0]``
    the anchor, whose frame the others are laid in) and their horizontal ``distances_m``
    from the prior."""

    rows: tuple[int, ...]
    distances_m: tuple[float, ...]

    @property
    def anchor(self) -> int:
        return self.rows[0]


class MapPositions:
    """A range search over the map's positions (UTM northing, easting [N]); ``groups`` [N]:
    which drive each entry comes from (entries of one group are laid together)."""

    def __init__(self, northing: np.ndarray, easting: np.ndarray, groups: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        ne = np.c_[np.asarray(northing, np.float64), np.asarray(easting, np.float64)]
        if not len(ne):
            raise ValueError("a map of no entries")
        self._origin = ne.mean(axis=0)  # the tree in local metres: UTM's 5.7e6 in float64 is fine,
        self._tree = cKDTree(ne - self._origin)  # but keeps distances exact to the millimetre
        self._groups = np.asarray(groups)

    @classmethod
    def of_metadata(cls, metadata: Any) -> MapPositions:
        """The positions of a bundle's metadata, grouped by dataset and run."""
        return cls(metadata.northing, metadata.easting, drive_groups(metadata))

    def __len__(self) -> int:
        return int(self._tree.n)

    def nearest_m(self, northing: float, easting: float) -> float:
        """Horizontal distance from (northing, easting) to the nearest entry, metres."""
        d, _ = self._tree.query(np.array([northing, easting]) - self._origin)
        return float(d)

    def near(self, prior: Prior, max_submaps: int, same_run: bool = True) -> Nearby | None:
        """The entries within ``prior.radius_m`` of the prior, nearest first, at most
        ``max_submaps``; with ``same_run`` of one group only: ``prior.run``'s when it has one
        there, else the nearest entry's. ``None`` when there is none."""
        at = np.array([prior.northing, prior.easting]) - self._origin
        ids = self._tree.query_ball_point(at, prior.radius_m)
        if not ids:
            return None
        ids = np.asarray(ids, dtype=np.int64)
        d = np.hypot(*(self._tree.data[ids] - at).T)
        order = np.lexsort((ids, d))
        ids, d = ids[order], d[order]
        if same_run:
            group = self._groups[ids[0]]
            if prior.run is not None and (self._groups[ids] == prior.run).any():
                group = prior.run
            keep = self._groups[ids] == group
            ids, d = ids[keep], d[keep]
        ids, d = ids[:max_submaps], d[:max_submaps]
        return Nearby(tuple(int(i) for i in ids), tuple(float(x) for x in d))


@dataclass(frozen=True)
class PriorFit:
    """The outcome of registering a scan near a prior.

    ``verified``: the fit is good enough to be the scan's pose (``PriorConfig``); ``pose``: the
    registered pose (``None`` when the registration could not run); ``fitness``, ``rmse_m``,
    ``constraint``: the registration's; ``covariance`` float64 [6, 6] (see the module doc) or
    ``None``; ``sigma_m``: the largest horizontal standard deviation of it; ``rows``: the map
    entries registered against (anchor first); ``correction_m`` / ``correction_yaw_deg``: how
    far the registration moved the sensor from the prior; ``reason``: why it is not verified.
    """

    verified: bool
    prior: Prior
    pose: Pose | None = None
    fitness: float = 0.0
    rmse_m: float = float("nan")
    constraint: float = 0.0
    covariance: np.ndarray | None = None
    sigma_m: float | None = None
    rows: tuple[int, ...] = ()
    correction_m: float | None = None
    correction_yaw_deg: float | None = None
    reason: str | None = None
    seconds: float = 0.0
    threshold: float = 0.0
    uncertain: bool = False


def no_map_near(prior: Prior, nearest_m: float, threshold: float) -> PriorFit:
    """The answer for a prior with no map entry within its radius."""
    return PriorFit(
        False,
        prior,
        reason=f"no map within {prior.radius_m:g} m of the prior (the nearest entry is "
        f"{nearest_m:.0f} m away): off the map, or a wrong prior",
        threshold=threshold,
    )


def laid_together(geometry: Any, rows: tuple[int, ...]) -> np.ndarray:
    """The points in metres [sum N_i, 3] of bundle ``rows`` in the local frame of ``rows[0]``
    (each entry's frame has UTM axes at its origin: a shift lays it into the anchor's)."""
    anchor = geometry.map_pose(rows[0])[:3, 3]
    parts = [geometry.metres(r) + (geometry.map_pose(r)[:3, 3] - anchor) for r in rows]
    return np.concatenate(parts)


@dataclass(frozen=True, eq=False)
class NearTarget:
    """A prepared target (entries laid together, or one map node) with the unit normal of each
    of its fine points (float64 [M, 3], from small_gicp's covariances) for the covariance."""

    prepared: reg.Prepared
    normals: np.ndarray

    @classmethod
    def of(cls, prepared: reg.Prepared) -> NearTarget:
        if prepared.reason is not None:
            return cls(prepared, np.empty((0, 3)))
        return cls(prepared, plane_normals(np.asarray(prepared.fine.covs())[:, :3, :3]))


def plane_normals(covs: np.ndarray) -> np.ndarray:
    """float64 [M, 3] unit eigenvectors of the smallest eigenvalue of covariances [M, 3, 3],
    sign arbitrary. small_gicp regularises every covariance to eigenvalues (1e-3, 1, 1), so
    ``I - C`` is a multiple of ``n n^T`` and its column of the largest diagonal entry lies along
    ``n``: a column instead of an eigen-decomposition (a twentieth of numpy's batched ``eigh``,
    which took as long as the registration). A covariance not of that form (its trace not
    2.001) goes to ``eigh``."""
    covs = np.asarray(covs, dtype=np.float64)
    rest = np.eye(3) - covs
    diagonal = np.einsum("nii->ni", rest)
    k = np.argmax(diagonal, axis=1)
    cols = rest[np.arange(len(rest)), :, k]
    length = np.linalg.norm(cols, axis=1)
    normals = cols / np.maximum(length, 1e-300)[:, None]
    odd = np.abs(np.einsum("nii->n", covs) - REGULARISED_TRACE) > 1e-9
    if odd.any():
        normals[odd] = np.linalg.eigh(covs[odd])[1][:, :, 0]
    return normals


#: The trace of a covariance as small_gicp regularises it (eigenvalues 1e-3, 1, 1).
REGULARISED_TRACE = 2.001


def prepare_target(points_m: np.ndarray, config: reg.RegistrationConfig) -> NearTarget:
    """The points in metres as a target registered to from a prior (no yaw search's spectra)."""
    return NearTarget.of(reg.prepare(points_m, config, "target", search=False))


#: A horizontal direction of the shift whose information is below this share of the other's is
#: taken as unconstrained: the normals of a wall, estimated from a few neighbours, lean by a
#: fraction of a degree (more where walls meet the floor), and over thousands of points that
#: leaning alone would seem to pin the shift along the wall (a synthetic street of two walls:
#: 2e-3 of the across-street information; on the demo city 1 % of the scans were below 0.03).
MIN_INFO_SHARE = 1e-2
#: The variance given to an unconstrained direction, m^2 (or rad^2).
UNCONSTRAINED = 1e6


def point_to_plane_covariance(
    source_points: np.ndarray,
    target: NearTarget,
    transform: np.ndarray,
    inlier_m: float,
    min_sigma_m: float = 0.02,
) -> np.ndarray | None:
    """float64 [6, 6] (translation, then rotation; target axes, about the source frame's origin)
    of the registration ``transform`` (source -> target): ``sigma^2 inv(J^T J)`` over the
    source points with a target point within ``inlier_m``, J the point-to-plane Jacobian, sigma
    the RMS of the plane residuals (at least ``min_sigma_m``). ``None`` with fewer than 6
    such points. A horizontal direction the planes do not constrain (:data:`MIN_INFO_SHARE`)
    gets a variance of :data:`UNCONSTRAINED`."""
    tree = target.prepared.tree
    if tree is None or not len(source_points) or not len(target.normals):
        return None
    moved = source_points @ transform[:3, :3].T + transform[:3, 3]
    idx, sq = tree.batch_nearest_neighbor_search(moved)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    inside = np.asarray(sq, dtype=np.float64).reshape(-1) <= inlier_m**2
    if inside.sum() < 6:
        return None
    p = moved[inside]
    n = target.normals[idx[inside]]
    q = target.prepared.points[idx[inside]]
    residual = np.einsum("ij,ij->i", n, p - q)
    jac = np.c_[n, np.cross(p - transform[:3, 3], n)]  # d residual / d (shift, turn)
    sigma2 = max(float(np.mean(residual**2)), min_sigma_m**2)
    info = jac.T @ jac / sigma2
    w, v = np.linalg.eigh(info)
    w = np.maximum(w, 1.0 / UNCONSTRAINED)
    cov = (v / w) @ v.T
    hw, hv = np.linalg.eigh(info[:2, :2])  # the horizontal shift's weak direction
    if hw[0] < MIN_INFO_SHARE * max(hw[1], 0.0):
        cov[:2, :2] += UNCONSTRAINED * np.outer(hv[:, 0], hv[:, 0])
    return cov


def horizontal_sigma(covariance: np.ndarray) -> float:
    """The largest horizontal standard deviation of a [6, 6] covariance, metres."""
    return float(math.sqrt(max(np.linalg.eigvalsh(covariance[:2, :2])[-1], 0.0)))


def register_near(
    query: QueryCloud,
    geometry: Any,
    nearby: Nearby,
    prior: Prior,
    config: PriorConfig,
    *,
    cache: Any = None,
) -> PriorFit:
    """Register the scan ``query`` (metres, sensor frame) to the map entries ``nearby`` of a
    bundle's ``geometry``, starting from ``prior``: the :class:`PriorFit`. ``cache`` (a dict or
    :class:`~.verify.PreparedCache`) keeps prepared targets by their rows. Never raises on a
    degenerate scan: the fit then says why."""
    t0 = time.perf_counter()
    anchor_pose = geometry.map_pose(nearby.anchor)
    rc = config.registration

    def target() -> NearTarget:
        key = ("near", nearby.rows)
        made = None if cache is None else cache.get(key)
        if made is None:
            made = prepare_target(laid_together(geometry, nearby.rows), rc)
            if cache is not None:
                cache[key] = made
        return made

    def done(**kw: Any) -> PriorFit:
        return PriorFit(
            prior=prior, rows=nearby.rows, seconds=time.perf_counter() - t0,
            threshold=config.min_fitness, **kw,
        )  # fmt: skip

    source = reg.prepare(query.points_m, rc, "source", search=False)
    if source.reason is not None:
        return done(verified=False, reason=f"query: {source.reason}")
    tgt = target()
    if tgt.prepared.reason is not None:
        return done(verified=False, reason=f"map near the prior: {tgt.prepared.reason}")
    start = prior.matrix(float(anchor_pose[2, 3]))
    init = np.linalg.inv(anchor_pose) @ start
    r = reg.register(source, tgt.prepared, rc, init=init)
    if r.reason is not None:
        return done(verified=False, reason=r.reason)
    check = Check(1, float(r.fitness), float(r.rmse_m), r.transform, r.constraint)
    pose = Pose.from_check(check, Candidate(1, np.empty((0, 3)), anchor_pose), query)
    cov = point_to_plane_covariance(source.points, tgt, r.transform, rc.inlier_m)
    if cov is not None:
        cov = cov * config.sigma_scale**2
    sigma = None if cov is None else horizontal_sigma(cov)
    moved = math.hypot(pose.easting - prior.easting, pose.northing - prior.northing)
    turned = abs((pose.yaw_deg - prior.yaw_deg + 180.0) % 360.0 - 180.0)
    reason = None
    uncertain = False
    limit = config.max_correction_m if config.max_correction_m is not None else prior.radius_m
    if r.fitness < config.min_fitness:
        reason = f"fitness {r.fitness:.2f} < {config.min_fitness:g}"
    elif moved > limit:
        reason = f"the registration moved {moved:.1f} m from the prior (more than {limit:g} m)"
    elif config.max_sigma_m is not None and (sigma is None or sigma > config.max_sigma_m):
        what = "unknown" if sigma is None else f"{sigma:.2f} m"
        reason = f"position uncertain along a direction: sigma {what} > {config.max_sigma_m:g} m"
        uncertain = True
    return done(
        verified=reason is None,
        pose=pose,
        fitness=float(r.fitness),
        rmse_m=float(r.rmse_m),
        constraint=float(r.constraint),
        covariance=cov,
        sigma_m=sigma,
        correction_m=moved,
        correction_yaw_deg=turned,
        reason=reason,
        uncertain=uncertain,
    )


class Once(Generic[T]):
    """A value made on first use (thread-safe): a server that never gets a prior never
    builds the map's :class:`MapPositions`, nor one never asked a query without a scale its
    drives' directions."""

    def __init__(self, make: Callable[[], T]) -> None:
        self._make = make
        self._lock = threading.Lock()
        self._made = False
        self._value: T

    def get(self) -> T:
        with self._lock:
            if not self._made:
                self._value, self._made = self._make(), True
            return self._value
