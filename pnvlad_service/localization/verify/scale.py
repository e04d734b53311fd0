"""The scale of a query that comes without one: registration with the scale as a free
parameter.

A submap as the benchmark publishes it is G's output alone: 4096 points centred and scaled to
a mean distance of 0.5, with no record of the metres per unit. The candidates' own scales say
roughly what it is (a place's submaps are of similar size), but only roughly: on the demo city
the median scale of a query's true candidates is within 5 % of the query's own for half the
queries and 13-20 % off for the worst tenth, and at 5 % a point 30 m from the centroid is
1.5 m out, three times the inlier distance the score counts. So each candidate registers the
query as a similarity:

1. the rigid registration (:func:`registration.register`: any heading, coarse, fine) of the
   query at the starting scale, the candidates' median;
2. from there, :func:`refine_scale`: rounds of closest points within a shrinking distance,
   each solved for scale, rotation and translation together (:func:`similarity`, Umeyama's
   least squares), the scale kept within ``ScaleConfig.bounds`` of the start;
3. the query rescaled by that factor, registered again from the refined pose (coarse, then
   fine), and kept if it scores at least as well as step 1.

That factor is the candidate's own: a wrong place finds the factor that suits it best. But a
query has one scale. :func:`common_factor` then chooses it: the factors of a sweep over
``ScaleConfig.sweep_bounds`` and the best candidates' own, each registered to those candidates
from their poses, the one with the highest fitness kept; verification registers every
candidate rigidly at it (docs/VERIFY.md).

The start comes from the map's drives where it can (:func:`track_scales`): a submap holds what
was recorded along a stretch of its drive, so its extent *along* the drive is about that
stretch wherever it is (19.0-20.8 m between the 10th and 90th percentile on the ``oxford``
preset), while its extent across it, and so G's scale, changes with what the sensor reached
into side streets. The query's extent along a candidate's direction of travel, against the
candidate's own in metres, gives its metres per unit to a few per cent at the right place
(:func:`along_track_scale`); a start that close lets the factor be held nearer to it
(:meth:`ScaleConfig.tracked`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from pnvlad_service.localization.verify import registration as reg


@dataclass(frozen=True)
class ScaleConfig:
    """How a query's scale is found by registration.

    ``distances``: the closest-point distances (metres) of :func:`refine_scale`, widest
    first; ``rounds``: the most rounds at each; ``starts``: the factors the rounds start
    from, each in turn, the one whose result scores best kept (far from the truth the rounds
    from 1 can stop short of it; more starts verified more on the demo city but made wrong
    candidates fit better, docs/results/verify.md);
    ``bounds``: the factor's range, relative to the starting scale (the candidates' median:
    on the demo city the true one was within 0.83-1.14 of it for 90 % of queries; wider
    bounds let wrong candidates fit better, docs/results/verify.md);
    ``min_pairs``: fewer closest-point pairs than this end the rounds (the factor stays);
    ``min_change``: a factor that moves less than this in a round ends that distance's
    rounds, and one closer to 1 keeps the first registration as it is;
    ``sweep_candidates``: how many of the best candidates :func:`common_factor` fits the
    query's one scale to (0: none, each candidate keeps its own factor);
    ``sweep_bounds`` and ``sweep_steps``: the factors it tries besides theirs, evenly in
    log between the bounds (relative to the starting scale);
    ``track_bounds`` and ``track_sweep_steps``: both bounds and the sweep's steps when the
    start came from the candidates' drives (:meth:`tracked`; that start is within 5.4 % of
    the truth for three queries in four on the ``oxford`` preset, the candidates' median
    within 24 %);
    ``track_spread``: the drives give the start only on a map whose submaps' extents along
    their drives are steady, the 90th percentile at most this times the 10th
    (:func:`along_drive_spread`; push-broom ``oxford`` maps 1.12-1.17, where a submap is what
    20 m of driving swept; the spinning ``benchmark`` 1.62 and ``demo`` 1.86, where it reaches
    as far as the sensor sees along the street); ``None``: never (:meth:`takes_tracks`).
    """

    distances: tuple[float, ...] = (12.0, 8.0, 5.0, 3.0, 2.0, 1.0, 0.75)
    rounds: int = 8
    starts: tuple[float, ...] = (1.0,)
    bounds: tuple[float, float] = (0.7, 1.4)
    min_pairs: int = 30
    min_change: float = 0.002
    sweep_candidates: int = 2
    sweep_bounds: tuple[float, float] = (0.7, 1.5)
    sweep_steps: int = 7
    track_bounds: tuple[float, float] = (0.85, 1.18)
    track_sweep_steps: int = 5
    track_spread: float | None = 1.3

    def __post_init__(self) -> None:
        lo, hi = self.bounds
        if not 0.0 < lo <= 1.0 <= hi:
            raise ValueError(f"bounds must satisfy 0 < low <= 1 <= high, got {self.bounds}")
        if not self.starts or not all(lo <= f <= hi for f in self.starts):
            raise ValueError(f"starts must lie within the bounds {self.bounds}, got {self.starts}")
        if self.rounds < 1:
            raise ValueError(f"rounds must be at least 1, got {self.rounds}")
        if not self.distances or min(self.distances) <= 0:
            raise ValueError(f"distances must be positive, got {self.distances}")
        if self.sweep_candidates < 0:
            raise ValueError(f"sweep_candidates must be >= 0, got {self.sweep_candidates}")
        s_lo, s_hi = self.sweep_bounds
        if not 0.0 < s_lo <= s_hi or self.sweep_steps < 1:
            raise ValueError(
                "sweep_bounds must satisfy 0 < low <= high and sweep_steps >= 1, got "
                f"{self.sweep_bounds}, {self.sweep_steps}"
            )

        if self.track_spread is not None and not self.track_spread >= 1.0:
            raise ValueError(f"track_spread must be at least 1 or None, got {self.track_spread}")
        t_lo, t_hi = self.track_bounds
        if not 0.0 < t_lo <= 1.0 <= t_hi or self.track_sweep_steps < 1:
            raise ValueError(
                "track_bounds must satisfy 0 < low <= 1 <= high and track_sweep_steps >= 1, "
                f"got {self.track_bounds}, {self.track_sweep_steps}"
            )

    def takes_tracks(self, tracks: DriveTracks) -> bool:
        """Whether a query without a scale starts from the map's drives (``tracks``, the
        map's :func:`map_tracks`): their extents spread no more than ``track_spread``."""
        return self.track_spread is not None and tracks.spread <= self.track_spread

    def tracked(self) -> ScaleConfig:
        """This config for a start from the candidates' drives (:func:`track_scales`): the
        factor held within ``track_bounds`` and swept over them in ``track_sweep_steps``."""
        starts = tuple(f for f in self.starts if self.track_bounds[0] <= f <= self.track_bounds[1])
        return replace(
            self,
            bounds=self.track_bounds,
            starts=starts or (1.0,),
            sweep_bounds=self.track_bounds,
            sweep_steps=self.track_sweep_steps,
        )

    def sweep(self) -> np.ndarray:
        """The factors :func:`common_factor` tries besides the candidates' own."""
        lo, hi = self.sweep_bounds
        return np.exp(np.linspace(np.log(lo), np.log(hi), self.sweep_steps))


DEFAULT_SCALE = ScaleConfig()


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The least-squares similarity ``dst ≈ s R src + t`` of paired points [N, 3] (Umeyama,
    1991): (s, R float64 [3, 3] a rotation, t float64 [3])."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    rot = (u * sign) @ vt
    var = float((a * a).sum() / len(src))
    s = float((d * sign).sum() / var) if var > 0 else 1.0
    return s, rot, mu_d - s * rot @ mu_s


def refine_scale(
    points: np.ndarray,
    target: reg.Prepared,
    transform: np.ndarray,
    config: ScaleConfig = DEFAULT_SCALE,
    threads: int = 1,
    start: float = 1.0,
) -> tuple[float, np.ndarray]:
    """The factor ``k`` by which ``points`` [N, 3] (the query's, metres at the starting scale)
    are rescaled about their origin, and the rigid 4x4 that then lays ``k * points`` on
    ``target``, from the rigid ``transform`` and the factor ``start``: closest points within
    each of ``config.distances`` in turn, solved by :func:`similarity` up to ``config.rounds`` times
    a distance (until the factor moves less than ``min_change``), ``k`` clipped to
    ``config.bounds``."""
    lo, hi = config.bounds
    k, rot, t = start, transform[:3, :3].copy(), transform[:3, 3].copy()
    for dist in config.distances:
        for _ in range(config.rounds):
            moved = k * points @ rot.T + t
            idx, sq = target.tree.batch_nearest_neighbor_search(moved, num_threads=threads)
            near = np.asarray(sq, dtype=np.float64).reshape(-1) <= dist * dist
            if near.sum() < config.min_pairs:
                break
            src, dst = points[near], target.points[np.asarray(idx, dtype=np.int64)[near]]
            s, rot, t = similarity(src, dst)
            if not np.isfinite(s) or s <= 0:
                s = k
            s = float(np.clip(s, lo, hi))
            # the translation that goes with the (clipped) factor
            t = dst.mean(axis=0) - s * rot @ src.mean(axis=0)
            moved_by = abs(s - k)
            k = s
            if moved_by < config.min_change:
                break
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, t
    return k, out


def register_scaled(
    query_m: np.ndarray,
    source: reg.Prepared,
    target: reg.Prepared,
    config: reg.RegistrationConfig = reg.DEFAULT,
    scale: ScaleConfig = DEFAULT_SCALE,
) -> tuple[reg.Registration, float]:
    """Register ``query_m`` [N, 3] (metres at the starting scale; ``source`` is it prepared)
    to ``target`` with its scale free (see the module doc): the registration of the rescaled
    query and the factor ``k`` (its points are ``k * query_m``); the rigid one and 1.0 when
    rescaling scores no better."""
    first = reg.register(source, target, config)
    if first.reason is not None or first.fitness == 0.0:
        return first, 1.0
    best_k, best_fit, start_t = 1.0, -1.0, first.transform
    for factor in scale.starts:
        k, moved = refine_scale(
            source.points, target, first.transform, scale, config.threads, factor
        )
        fit, _ = reg.fitness(source.points * k, target, moved, config.inlier_m, config.threads)
        if fit > best_fit:
            best_k, best_fit, start_t = k, fit, moved
    if abs(best_k - 1.0) < scale.min_change:
        return first, 1.0
    rescaled = reg.prepare(query_m * best_k, config, "source")
    second = reg.register(rescaled, target, config, init=start_t)
    if second.reason is not None or second.fitness < first.fitness:
        return first, 1.0
    return second, best_k


def common_factor(
    query_m: np.ndarray,
    tops: Sequence[tuple[reg.Prepared, Any]],
    config: reg.RegistrationConfig = reg.DEFAULT,
    scale: ScaleConfig = DEFAULT_SCALE,
) -> float:
    """The one factor of a query without a scale: of :meth:`ScaleConfig.sweep`'s factors and
    the ``tops``' own (each a prepared candidate and its check: ``scale`` and ``transform``
    from :func:`register_scaled`), the one whose rescaled ``query_m`` [N, 3] registered to a
    candidate from that candidate's pose (coarse, then fine) has the highest fitness; 1.0 when
    nothing registers. Measured on the push-broom ``oxford`` preset: the candidates' own
    factors lead wrong places to fit as well as the right one (docs/VERIFY.md)."""
    factors = np.unique(np.r_[scale.sweep(), [float(c.scale) for _, c in tops]])
    best_fit, best_k = 0.0, 1.0
    for k in factors:
        source = reg.prepare(query_m * k, config, "source", search=False)
        if source.reason is not None:
            continue
        for target, check in tops:
            r = reg.register(source, target, config, init=check.transform)
            if r.reason is None and r.fitness > best_fit:
                best_fit, best_k = float(r.fitness), float(k)
    return best_k


def _extent(values: np.ndarray) -> float:
    """The spread of ``values`` between their 0.5th and 99.5th percentiles (a few stray
    points do not count)."""
    lo, hi = np.percentile(values, [0.5, 99.5])
    return float(hi - lo)


def along_track_scale(
    cloud: np.ndarray, candidate_m: np.ndarray, direction: np.ndarray
) -> float | None:
    """The metres per unit of ``cloud`` [N, 3] (normalised, axes as the map's) that make its
    extent along ``direction`` (a horizontal unit vector, east and north) equal to
    ``candidate_m``'s [M, 3] (metres); ``None`` without a direction or when the cloud has no
    extent along it. Always positive (an extent has no sign)."""
    d = np.asarray(direction, dtype=np.float64)
    if d.shape != (2,) or not np.all(np.isfinite(d)):
        return None
    units = _extent(np.asarray(cloud, dtype=np.float64)[:, :2] @ d)
    if units <= 1e-6:
        return None
    return _extent(np.asarray(candidate_m, dtype=np.float64)[:, :2] @ d) / units


def track_scales(
    cloud: np.ndarray,
    scales: Sequence[float],
    metres: Sequence[Callable[[], np.ndarray]],
    directions: np.ndarray,
) -> list[float] | None:
    """Each candidate's estimate of the metres per unit of ``cloud`` (a query without a
    scale) from its extent along the candidate's drive (:func:`along_track_scale`), with the
    sign of the candidate's own ``scales`` (G negates a map's clouds when its config says
    so); ``metres[i]()`` reads candidate ``i``'s points, ``directions`` [K, 2] its direction
    of travel (NaN where the map has none). A candidate without a direction keeps its own
    scale; ``None`` when no candidate has one (the start is then the candidates' median)."""
    out: list[float] = []
    found = False
    for scale, read, direction in zip(scales, metres, directions, strict=True):
        k = along_track_scale(cloud, read(), direction) if np.all(np.isfinite(direction)) else None
        found |= k is not None
        out.append(float(scale) if k is None else math.copysign(k, scale))
    return out if found else None


def track_directions(
    groups: np.ndarray,
    timestamp: np.ndarray,
    easting: np.ndarray,
    northing: np.ndarray,
    max_gap_m: float = 60.0,
) -> np.ndarray:
    """float64 [N, 2]: each map entry's direction of travel (a unit vector, east and north)
    from its drive's entries before and after it in time (``groups``: which drive each entry
    comes from), the one side alone where the other is more than ``max_gap_m`` away; NaN for
    an entry with neither (a drive of one entry, or a gap both ways). The sense of travel
    does not matter to an extent."""
    xy = np.c_[np.asarray(easting, np.float64), np.asarray(northing, np.float64)]
    out = np.full((len(xy), 2), np.nan)
    if not len(xy):
        return out
    _, drive = np.unique(np.asarray(groups), return_inverse=True)
    order = np.lexsort((np.asarray(timestamp), drive))  # by drive, then time (stable)
    step = np.diff(xy[order], axis=0)
    same = drive[order][1:] == drive[order][:-1]
    step *= (same & (np.hypot(*step.T) <= max_gap_m))[:, None]
    d = np.zeros_like(xy)
    d[1:] += step  # from the entry before
    d[:-1] += step  # to the entry after
    length = np.hypot(*d.T)
    good = length > 1e-6
    out[order[good]] = d[good] / length[good, None]
    return out


def drive_groups(metadata: Any) -> np.ndarray:
    """Which drive each entry of a bundle's metadata comes from: ``dataset/run``."""
    return np.char.add(
        np.char.add(np.asarray(metadata.dataset, dtype=str), "/"),
        np.asarray(metadata.run, dtype=str),
    )


def along_drive_spread(
    directions: np.ndarray, metres: Callable[[int], np.ndarray], sample: int = 200
) -> float:
    """How alike a map's submaps span along their drives: of up to ``sample`` entries with a
    direction (spread evenly over the map), the 90th percentile of their extents along it
    (metres; ``metres(i)`` reads entry ``i``) over the 10th; infinite with fewer than 10
    such entries."""
    have = np.flatnonzero(np.isfinite(directions[:, 0]))
    if len(have) < 10:
        return math.inf
    pick = have[np.linspace(0, len(have) - 1, min(sample, len(have))).astype(np.int64)]
    ext = np.array([_extent(metres(int(i))[:, :2] @ directions[i]) for i in pick])
    lo, hi = np.percentile(ext, [10, 90])
    return float(hi / lo) if lo > 0 else math.inf


@dataclass(frozen=True)
class DriveTracks:
    """What a map's drives say of its entries: each one's direction of travel
    (``directions`` float64 [N, 2], :func:`track_directions`) and how alike the submaps span
    along them (``spread``, :func:`along_drive_spread`)."""

    directions: np.ndarray
    spread: float


def map_tracks(metadata: Any, metres: Callable[[int], np.ndarray]) -> DriveTracks:
    """The :class:`DriveTracks` of a bundle: its metadata's drives, times and positions, and
    its entries' points (``metres(i)``, for the spread). A map property: whether a query
    starts from them is its config's (:meth:`ScaleConfig.takes_tracks`)."""
    directions = track_directions(
        drive_groups(metadata), metadata.timestamp, metadata.easting, metadata.northing
    )
    return DriveTracks(directions, along_drive_spread(directions, metres))
