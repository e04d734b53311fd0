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

The factor is the candidate's: a wrong place finds the factor that suits it best, bounded, and
the confidence weighs it against the others as before (docs/VERIFY.md).
"""

from __future__ import annotations

from dataclasses import dataclass

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
    rounds, and one closer to 1 keeps the first registration as it is.
    """

    distances: tuple[float, ...] = (12.0, 8.0, 5.0, 3.0, 2.0, 1.0, 0.75)
    rounds: int = 8
    starts: tuple[float, ...] = (1.0,)
    bounds: tuple[float, float] = (0.7, 1.4)
    min_pairs: int = 30
    min_change: float = 0.002

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
