"""What the localiser answers, as typed records: an :class:`Answer` (the matches, best first,
their verification and the pose, the :class:`Timings` of each stage) and :class:`LocalizerInfo`
(the model and the bundle loaded). Each writes the JSON the server returns (``to_json``), and
``server/schemas.py`` builds its response models from these dataclasses' fields, so the answer
and its schema have one list of fields."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from pnvlad_service.index.bundle import Match
from pnvlad_service.localization.verify.prior import PriorFit
from pnvlad_service.localization.verify.verify import Verification


@dataclass(frozen=True)
class Timings:
    """Seconds one query spent in each stage (``queue``: waiting for the batcher)."""

    parse: float = 0.0
    preprocess: float = 0.0
    queue: float = 0.0
    embed: float = 0.0
    search: float = 0.0
    verify: float = 0.0
    total: float = 0.0

    def seconds(self) -> dict[str, float]:
        """Stage name -> seconds, in the order of the fields."""
        return asdict(self)

    def to_json(self) -> dict[str, float]:
        """Milliseconds, rounded to the microsecond (:func:`milliseconds`)."""
        return {k: milliseconds(v) for k, v in self.seconds().items()}


def milliseconds(seconds: float) -> float:
    """``seconds`` in milliseconds, rounded to the microsecond, as the answers report times."""
    return round(seconds * 1000.0, 3)


def match_json(
    m: Match, score: float | None = None, retrieval_rank: int | None = None
) -> dict[str, Any]:
    """One match as the HTTP answer has it: no zone and a non-finite distance are ``null``;
    ``score``: its verification score (``null`` when it was not verified); ``retrieval_rank``:
    its rank by descriptor distance (``rank`` is its place in the answer)."""
    return {
        "rank": m.rank,
        "retrieval_rank": m.rank if retrieval_rank is None else retrieval_rank,
        "submap_id": m.submap_id,
        "dataset": m.dataset,
        "run": m.run,
        "timestamp": m.timestamp,
        "northing": m.northing,
        "easting": m.easting,
        "utm_zone": m.utm_zone or None,
        "distance": m.distance if math.isfinite(m.distance) else None,
        "score": score,
    }


@dataclass(frozen=True)
class Answer:
    """The map places of one cloud, best first (``rank`` 1), and how long it took.

    Without ``verification`` the order is the descriptor distance's. With it the verified
    candidates come first, best score first, then the rest in distance order;
    ``retrieval_ranks[i]`` is match ``i``'s rank by distance. ``batch_size``: clouds embedded
    together with this one. ``query_kind``: what was asked with (a preprocessed ``submap``, a
    raw ``scan`` or an accumulated ``window``); ``map_kind``: what every match is (a
    ``submap`` or a ``keyframe``). ``no_returns``: the missing returns (points at the sensor)
    dropped from a raw query (:meth:`~.query.Query.make`).

    With ``prior`` (a query that said where it is: :meth:`Localizer.localize` with ``prior``)
    nothing was embedded: the matches are the map entries near the prior that the scan was
    registered to, nearest first (the anchor of the pose first), and ``prior`` is that
    registration (:class:`~.prior.PriorFit`).
    """

    matches: tuple[Match, ...]
    batch_size: int
    timings: Timings
    verification: Verification | None = None
    retrieval_ranks: tuple[int, ...] = ()
    query_kind: str = "submap"
    map_kind: str = "submap"
    prior: PriorFit | None = None
    no_returns: int = 0

    @property
    def verified(self) -> bool | None:
        """Whether the best match is verified; ``None`` when verification did not run."""
        if self.prior is not None:
            return self.prior.verified
        return None if self.verification is None else self.verification.verified

    @property
    def mode(self) -> str:
        """``search`` (retrieval, then verification) or ``prior`` (registration near a prior)."""
        return "search" if self.prior is None else "prior"

    def to_json(self) -> dict[str, Any]:
        if self.prior is not None:
            return self._prior_json(self.prior)
        v = self.verification
        scores = {} if v is None else {c.rank: c.score for c in v.checks}
        ranks = self.retrieval_ranks or tuple(m.rank for m in self.matches)
        return {
            "matches": [
                {**match_json(m, scores.get(r), r), "kind": self.map_kind}
                for m, r in zip(self.matches, ranks, strict=True)
            ],
            "query_kind": self.query_kind,
            "map_kind": self.map_kind,
            "mode": self.mode,
            "verified": self.verified,
            "pose": None if v is None or v.pose is None else pose_json(v.pose),
            "verification": None if v is None else verification_json(v),
            "prior": None,
            "batch_size": self.batch_size,
            "no_returns": self.no_returns,
            "timings_ms": self.timings.to_json(),
        }

    def _prior_json(self, fit: PriorFit) -> dict[str, Any]:
        def score(m: Match) -> float | None:  # the fit is the anchor's (rank 1)
            return fit.fitness if m.rank == 1 and fit.pose is not None else None

        return {
            "matches": [{**match_json(m, score(m)), "kind": self.map_kind} for m in self.matches],
            "query_kind": self.query_kind,
            "map_kind": self.map_kind,
            "mode": self.mode,
            "verified": fit.verified,
            "pose": pose_json(fit.pose, fit) if fit.verified and fit.pose is not None else None,
            "verification": {
                "candidates": len(fit.rows),
                "registered": len(fit.rows) if fit.pose is not None else 0,
                "threshold": fit.threshold,
                "best_score": fit.fitness,
                "confidence": fit.fitness if fit.verified else 0.0,
                "reason": fit.reason,
            },
            "prior": prior_json(fit),
            "batch_size": self.batch_size,
            "no_returns": self.no_returns,
            "timings_ms": self.timings.to_json(),
        }


def pose_json(pose: Any, fit: PriorFit | None = None) -> dict[str, Any]:
    """A verified pose as the answer has it; a pose registered near a prior adds its
    ``covariance`` (6 x 6: x, y, z, then rotations about them; metres and radians, UTM axes)
    and ``sigma_m`` (its largest horizontal standard deviation)."""
    cov = None if fit is None or fit.covariance is None else fit.covariance
    return {
        **pose.to_json(),
        "covariance": None if cov is None else [[float(v) for v in row] for row in cov],
        "sigma_m": None if fit is None else fit.sigma_m,
    }


def prior_json(fit: PriorFit) -> dict[str, Any]:
    """What a prior answer says of its registration besides ``verified`` and ``pose``."""
    return {
        **fit.prior.to_json(),
        "submaps": len(fit.rows),
        "fitness": fit.fitness,
        "uncertain": fit.uncertain,
        "constraint": fit.constraint,
        "sigma_m": fit.sigma_m,
        "correction_m": fit.correction_m,
        "correction_yaw_deg": fit.correction_yaw_deg,
        "registered": pose_json(fit.pose, fit)
        if not fit.verified and fit.pose is not None
        else None,
    }


def verification_json(v: Verification) -> dict[str, Any]:
    """What the answer says of its verification besides ``verified`` and ``pose``."""
    return {
        "candidates": v.candidates,
        "registered": v.registered,
        "threshold": v.threshold,
        "best_score": v.best_score,
        "confidence": v.confidence,
        "reason": v.reason,
    }


@dataclass(frozen=True)
class ModelInfo:
    """The loaded model: sha256 of its weights and of its configuration, arch, output dim."""

    weights_sha256: str
    config_sha256: str
    arch: str | None
    dim: int


@dataclass(frozen=True)
class IndexInfo:
    """The loaded bundle: its id (16 hex digits of the index file's sha256), key, vectors."""

    id: str
    key: str
    count: int


@dataclass(frozen=True)
class LocalizerInfo:
    model: ModelInfo
    index: IndexInfo

    def to_json(self) -> dict[str, Any]:
        return {"model": asdict(self.model), "index": asdict(self.index)}
