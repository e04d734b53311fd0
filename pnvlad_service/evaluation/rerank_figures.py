"""The figures of ``pnvlad eval --rerank K`` from the outcomes of its queries, and the rule that
chooses the verification threshold from them: pure functions of :class:`QueryOutcome` records
(:mod:`.rerank` makes those by registering queries; :mod:`.rerank_report` shows the figures).

- :func:`summarise`: recall@1 and recall@1% before and after re-ranking (averaged over run
  pairs), the metric success against the true poses (:func:`pose_error`), and
  :func:`verified_figures`: the precision, coverage and recall of ``verified`` at a threshold;
- :func:`choose_threshold` / :func:`threshold_on_curve`: the smallest threshold whose
  precision reaches the target with enough coverage, on the curve of :func:`pr_curve`, with
  off-map queries weighed in by :func:`off_map_curve` (docs/VERIFY.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

SUCCESS_M = 2.0
SUCCESS_DEG = 5.0
TARGET_PRECISION = 0.995
#: The least share of the calibration queries (percent) a chosen threshold must verify.
MIN_COVERAGE = 85.0
#: The share of queries the threshold is chosen to expect whose place is not among their
#: candidates (off the map, or missed by retrieval): an assumption about where the service
#: runs, not a measurement. The training layout cannot measure it: a model knows its
#: training places (run 29 of docs/results/training.md answered 0.8 % of them wrongly before
#: verification, the test queries 5.8 %; its recall@10 misses 2.1 % of the test queries).
OFF_MAP_SHARE = 0.05


def yaw_deg(t: np.ndarray) -> float:
    return math.degrees(math.atan2(t[1, 0], t[0, 0]))


def wrap_deg(a: float) -> float:
    """An angle in (-180, 180]."""
    return -((-a + 180.0) % 360.0 - 180.0)


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation error m, yaw error degrees) of a 4x4 estimate against the truth."""
    t = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
    return t, abs(wrap_deg(yaw_deg(estimate) - yaw_deg(truth)))


@dataclass
class QueryOutcome:
    """One query of one run pair, before and after re-ranking."""

    pair: int
    r1_before: bool
    r1_after: bool
    rk_before: bool
    r1p_before: bool
    r1p_after: bool
    best_score: float
    confidence: float = 0.0  # what verified is decided on (verify.confidence)
    registered: int = 0  # candidates the cascade registered
    t_err: float | None = None
    yaw_err: float | None = None
    reversed: bool = False
    pose_ok: bool | None = None  # the best candidate's pose within 2 m and 5 degrees


def _pair_mean(outcomes: list[QueryOutcome], attr: str) -> float:
    """Percent, averaged over run pairs (as the benchmark averages recall)."""
    by_pair: dict[int, list[bool]] = {}
    for o in outcomes:
        by_pair.setdefault(o.pair, []).append(getattr(o, attr))
    if not by_pair:
        return float("nan")
    return float(np.mean([np.mean(v) for v in by_pair.values()]) * 100.0)


def verified_figures(outcomes: list[QueryOutcome], threshold: float) -> dict[str, Any]:
    """Precision, coverage and recall of ``verified`` at ``threshold`` (pooled, percent).

    ``precision``: the share of verified answers whose top-1 is the right place (within the
    benchmark's 25 m); ``pose_precision``: the share whose pose is right (< 2 m and < 5
    degrees of the truth, whichever submap gave it: what a robot acting on ``verified``
    relies on). ``recall``: the share of right top-1s that are verified; ``coverage``: the
    share of all queries verified."""
    n = len(outcomes)
    ver = [o for o in outcomes if o.confidence >= threshold]
    right = [o for o in outcomes if o.r1_after]
    good = [o for o in ver if o.r1_after]
    posed = [o for o in ver if o.pose_ok is not None]
    return {
        "threshold": threshold,
        "n_verified": len(ver),
        "precision": 100.0 * len(good) / len(ver) if ver else float("nan"),
        "pose_precision": (
            100.0 * sum(bool(o.pose_ok) for o in posed) / len(posed) if posed else float("nan")
        ),
        "coverage": 100.0 * len(ver) / n if n else float("nan"),
        "recall": 100.0 * len(good) / len(right) if right else float("nan"),
    }


def pr_curve(outcomes: list[QueryOutcome], thresholds: np.ndarray | None = None) -> list[dict]:
    """``verified_figures`` over a grid of thresholds (0 to 1 by 0.01)."""
    grid = np.round(np.arange(0.0, 1.0001, 0.01), 2) if thresholds is None else thresholds
    return [verified_figures(outcomes, float(t)) for t in grid]


def off_map_curve(
    curve: list[dict[str, Any]], off_map: list[QueryOutcome], share: float
) -> list[dict[str, Any]]:
    """``curve`` (:func:`pr_curve` of on-map outcomes) with the precisions a service would see
    if a ``share`` of its queries were like ``off_map`` (:func:`rerank_pairs` with
    ``off_map_m``: every candidate a wrong place): at each threshold, ``off_map_accept`` (%
    of the off-map queries verified, each a wrong answer and a wrong pose) joins the wrong
    answers in the proportion ``share : 1 - share``; coverage and recall stay the on-map
    figures (what the coverage floor is about)."""
    out = []
    m = len(off_map)
    for c in curve:
        t = c["threshold"]
        accept = sum(o.confidence >= t for o in off_map) / m if m else 0.0
        row = {**c, "off_map_accept": 100.0 * accept}
        verified = c["coverage"] / 100.0  # on-map share verified
        wrong = share * accept
        for key in ("precision", "pose_precision"):
            p = c[key]
            if math.isnan(p) or verified == 0.0:
                continue
            right = (1.0 - share) * verified * p / 100.0
            row[key] = 100.0 * right / ((1.0 - share) * verified + wrong)
        out.append(row)
    return out


def choose_threshold(
    outcomes: list[QueryOutcome],
    target: float = TARGET_PRECISION,
    key: str = "pose_precision",
    *,
    off_map: list[QueryOutcome] | None = None,
    off_map_share: float = OFF_MAP_SHARE,
) -> float:
    """The smallest grid threshold whose ``key`` precision (``pose_precision``: the pose is
    right, what ``verified`` promises; or ``precision``: the place is) reaches ``target``
    while verifying at least :data:`MIN_COVERAGE` % of the queries, and stays there for every
    higher threshold that verifies enough answers to tell (at least ``1 / (1 - target)``: 200
    at 99.5 %, below which one wrong answer alone takes a set under the target; the handful
    of surest answers is no measure of precision); when no threshold does, the most precise
    one that still covers that share (1.0 when none covers it).

    ``off_map``: outcomes of queries verified as if off the map; the precisions are then
    those of :func:`off_map_curve` with ``off_map_share`` of such queries (a model that knows
    its training places gives too few wrong answers there to choose on: run 29's 0.04 chosen
    without them verified 98.7 % right on the test queries)."""
    curve = pr_curve(outcomes)
    if off_map:
        curve = off_map_curve(curve, off_map, off_map_share)
    return threshold_on_curve(curve, target, key)


def curve_value(c: dict[str, Any], key: str) -> float:
    """A curve row's ``key`` precision, its place precision where that is NaN (no true poses)."""
    v = c[key]
    return c["precision"] if math.isnan(v) else v


def threshold_on_curve(
    curve: list[dict[str, Any]], target: float = TARGET_PRECISION, key: str = "pose_precision"
) -> float:
    """:func:`choose_threshold`'s rule on a curve already made (:func:`pr_curve`, or
    :func:`off_map_curve` of one)."""
    enough = math.ceil(1.0 / (1.0 - target)) if target < 1.0 else 1

    def value(c: dict[str, Any]) -> float:
        return curve_value(c, key)

    def precise(c: dict[str, Any]) -> bool:
        return c["n_verified"] > 0 and value(c) >= target * 100.0

    holds = [precise(c) or c["n_verified"] < enough for c in curve]
    for k, c in enumerate(curve):
        if precise(c) and c["coverage"] >= MIN_COVERAGE and all(holds[k + 1 :]):
            return float(c["threshold"])
    # Unreachable with enough coverage: the most precise threshold that still verifies at
    # least MIN_COVERAGE % of the queries.
    usable = [c for c in curve if c["coverage"] >= MIN_COVERAGE and not math.isnan(value(c))]
    best = max(usable, key=lambda c: (value(c), c["threshold"]), default=None)
    if best is None or value(best) <= 0.0:
        return 1.0
    return float(best["threshold"])


def _metric(outcomes: list[QueryOutcome]) -> dict[str, Any]:
    posed = [o for o in outcomes if o.t_err is not None]
    if not posed:
        return {"n": 0}
    t = np.array([o.t_err for o in posed])
    y = np.array([o.yaw_err for o in posed])
    ok = (t < SUCCESS_M) & (y < SUCCESS_DEG)
    return {
        "n": len(posed),
        "success": float(ok.mean() * 100.0),
        "median_translation_m": float(np.median(t)),
        "median_yaw_deg": float(np.median(y)),
        "p90_translation_m": float(np.percentile(t, 90)),
        "p90_yaw_deg": float(np.percentile(y, 90)),
    }


def summarise(outcomes: list[QueryOutcome], threshold: float, candidates: int) -> dict[str, Any]:
    """The report's figures of a set of outcomes (see the module doc)."""
    rev = [o for o in outcomes if o.reversed]
    fwd = [o for o in outcomes if not o.reversed]
    return {
        "n_queries": len(outcomes),
        "candidates": candidates,
        "recall_at_1_before": _pair_mean(outcomes, "r1_before"),
        "recall_at_1_after": _pair_mean(outcomes, "r1_after"),
        "recall_at_k_before": _pair_mean(outcomes, "rk_before"),
        "recall_at_1pct_before": _pair_mean(outcomes, "r1p_before"),
        "recall_at_1pct_after": _pair_mean(outcomes, "r1p_after"),
        "metric": _metric(outcomes),
        "metric_same_heading": _metric(fwd),
        "metric_reversed": _metric(rev),
        "n_reversed": len(rev),
        "recall_at_1_after_reversed": _pair_mean(rev, "r1_after") if rev else float("nan"),
        "recall_at_1_before_reversed": _pair_mean(rev, "r1_before") if rev else float("nan"),
        "verified": verified_figures(outcomes, threshold),
        "registered_mean": float(np.mean([o.registered for o in outcomes])) if outcomes else 0.0,
    }
