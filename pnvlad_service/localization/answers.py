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
from pnvlad_service.localization.verify import Verification


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
    ``submap`` or a ``keyframe``).
    """

    matches: tuple[Match, ...]
    batch_size: int
    timings: Timings
    verification: Verification | None = None
    retrieval_ranks: tuple[int, ...] = ()
    query_kind: str = "submap"
    map_kind: str = "submap"

    @property
    def verified(self) -> bool | None:
        """Whether the best match is verified; ``None`` when verification did not run."""
        return None if self.verification is None else self.verification.verified

    def to_json(self) -> dict[str, Any]:
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
            "verified": self.verified,
            "pose": None if v is None or v.pose is None else v.pose.to_json(),
            "verification": None if v is None else verification_json(v),
            "batch_size": self.batch_size,
            "timings_ms": self.timings.to_json(),
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
