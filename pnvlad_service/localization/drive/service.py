"""What a drive asks and what it reads back: :class:`Reply`, the typed answer of one scan as a
drive needs it, and :data:`Ask`, the service a drive asks (:func:`local_ask`: a bundle in this
process; :func:`http_ask`: a server).

A local service hands over the localiser's typed :class:`~..answers.Answer`
(:meth:`Reply.of_answer` reads its attributes); a server's answer is JSON on the wire, read
once into the same record (:meth:`Reply.of_json`). The drive runner, the tracker and the rows
read :class:`Reply` only, whichever service answered.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from pnvlad_service.localization.query.answers import Answer
    from pnvlad_service.localization.verify.prior import Prior


@dataclass(frozen=True)
class Place:
    """The answer's best match: the map entry ``submap_id`` (``dataset/run/timestamp``), its
    ``timestamp`` and ``run``, what it is (``kind``: ``submap`` or ``keyframe``), its UTM
    position (metres) and descriptor ``distance`` (``None`` when not finite or not searched)."""

    submap_id: str | None
    timestamp: int
    run: str
    kind: str | None
    northing: float
    easting: float
    distance: float | None


@dataclass(frozen=True)
class Reply:
    """What the service made of one scan, as a drive reads it.

    ``mode``: ``search`` (retrieval and verification) or ``prior`` (a registration near a
    prior pose); ``verified``: the answer's verdict (``None``: the service does not verify);
    ``pose``: float64 [4, 4] sensor -> UTM of a verified answer, else ``None``; ``top``: the
    best match (``None``: no match); ``confidence`` and ``reason``: the verification's
    (``None`` without one); ``fitness``, ``sigma_m`` (metres), ``correction_m`` (how far the
    registration moved the prior) and ``uncertain``: a prior answer's registration;
    ``timings_ms``: the service's stages, milliseconds; ``covariance``: float64 [6, 6] of a
    verified prior answer's pose (the registration's point-to-plane covariance: x, y, z, then
    rotations about them; metres and radians, UTM axes), else ``None``; ``fit_pose`` and
    ``fit_covariance``: a prior answer's registration whether verified or not (too loose along
    a direction, or fitting under the threshold), what a tracker weighs against its odometry.
    ``==`` compares every field but the arrays."""

    mode: str = "search"
    verified: bool | None = None
    pose: np.ndarray | None = field(default=None, compare=False)
    top: Place | None = None
    confidence: float | None = None
    reason: str | None = None
    fitness: float | None = None
    sigma_m: float | None = None
    correction_m: float | None = None
    uncertain: bool = False
    timings_ms: Mapping[str, float] = field(default_factory=dict)
    covariance: np.ndarray | None = field(default=None, compare=False)
    fit_pose: np.ndarray | None = field(default=None, compare=False)
    fit_covariance: np.ndarray | None = field(default=None, compare=False)

    @property
    def verified_pose(self) -> np.ndarray | None:
        """The pose when the answer is verified, else ``None``."""
        return self.pose if self.verified else None

    @classmethod
    def of_answer(cls, answer: Answer) -> Reply:
        """The reply of the localiser's typed answer (the values its JSON would carry)."""
        top = None
        if answer.matches:
            m = answer.matches[0]
            distance = float(m.distance) if math.isfinite(m.distance) else None
            top = Place(m.submap_id, int(m.timestamp), str(m.run), answer.map_kind,
                        float(m.northing), float(m.easting), distance)  # fmt: skip
        fit = answer.prior
        if fit is not None:
            pose = fit.pose.transform if fit.verified and fit.pose is not None else None
            fit_cov = None if fit.covariance is None else np.asarray(fit.covariance, np.float64)
            return cls(
                mode="prior",
                verified=bool(fit.verified),
                pose=None if pose is None else np.asarray(pose, dtype=np.float64),
                top=top,
                confidence=float(fit.fitness) if fit.verified else 0.0,
                reason=fit.reason,
                fitness=float(fit.fitness),
                sigma_m=_number(fit.sigma_m),
                correction_m=_number(fit.correction_m),
                uncertain=bool(fit.uncertain),
                timings_ms=answer.timings.to_json(),
                covariance=None if pose is None else fit_cov,
                fit_pose=None
                if fit.pose is None
                else np.asarray(fit.pose.transform, dtype=np.float64),
                fit_covariance=fit_cov,
            )
        v = answer.verification
        pose = None if v is None or v.pose is None else v.pose.transform
        return cls(
            mode="search",
            verified=None if v is None else bool(v.verified),
            pose=None if pose is None else np.asarray(pose, dtype=np.float64),
            top=top,
            confidence=None if v is None else float(v.confidence),
            reason=None if v is None else v.reason,
            timings_ms=answer.timings.to_json(),
        )

    @classmethod
    def of_json(cls, doc: Mapping[str, Any]) -> Reply:
        """The reply of a server's JSON answer (``POST /localize``)."""
        matches = doc.get("matches") or []
        top = None
        if matches:
            m = matches[0]
            top = Place(m.get("submap_id"), int(m["timestamp"]), str(m.get("run", "")),
                        m.get("kind"), float(m["northing"]), float(m["easting"]),
                        _number(m.get("distance")))  # fmt: skip
        pose = doc.get("pose")
        v = doc.get("verification") or {}
        fit = doc.get("prior") or {}
        fitted = pose if fit and doc.get("verified") else fit.get("registered")
        return cls(
            mode=doc.get("mode", "search"),
            verified=doc.get("verified"),
            pose=np.asarray(pose["transform"], dtype=np.float64) if pose else None,
            top=top,
            confidence=_number(v.get("confidence")),
            reason=v.get("reason"),
            fitness=_number(fit.get("fitness")),
            sigma_m=_number(fit.get("sigma_m")),
            correction_m=_number(fit.get("correction_m")),
            uncertain=bool(fit.get("uncertain")),
            timings_ms=dict(doc.get("timings_ms") or {}),
            covariance=_matrix(pose.get("covariance")) if pose else None,
            fit_pose=np.asarray(fitted["transform"], dtype=np.float64) if fitted else None,
            fit_covariance=_matrix(fitted.get("covariance")) if fitted else None,
        )


def _number(value: Any) -> float | None:
    return None if value is None else float(value)


def _matrix(value: Any) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=np.float64)


class Ask(Protocol):
    """The service a drive asks: ``ask(points, prior, kind)`` -> :class:`Reply` of a raw scan
    float [N, 3] (sensor frame, metres) or of a ``window`` (the last stretch of the drive laid
    together), searched for (``prior`` None) or registered near ``prior``. Raises
    :class:`~pnvlad_service.errors.InputError` when the service refuses the scan."""

    def __call__(
        self, points: np.ndarray, prior: Prior | None = None, kind: str = "scan"
    ) -> Reply: ...


def local_ask(localizer: Any, top_n: int = 5) -> Ask:
    """:data:`Ask` of a :class:`~..localizer.Localizer` in this process (a raw scan is bounded
    by the bundle, not by a server's request limits)."""
    from pnvlad_service.localization.query.limits import Limits

    def ask(points: np.ndarray, prior: Prior | None = None, kind: str = "scan") -> Reply:
        limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
        if prior is not None:
            limits = replace(limits, max_prior_radius_m=max(limits.max_prior_radius_m,
                                                            prior.radius_m))  # fmt: skip
        answer = localizer.localize(points, top_n=top_n, limits=limits, kind=kind, prior=prior)
        return Reply.of_answer(answer)

    return ask


def http_ask(client: Any, top_n: int = 5) -> Ask:
    """:data:`Ask` of a :class:`~pnvlad_service.client.LocalizeClient` (a server)."""

    def ask(points: np.ndarray, prior: Prior | None = None, kind: str = "scan") -> Reply:
        return Reply.of_json(client.localize(points, top_n, kind=kind, prior=prior))

    return ask


@dataclass(frozen=True)
class Service:
    """A service a drive asks: its :class:`Ask` and ``map_record()``, the serving map's
    ``map`` entry (how its windows laid each scan; ``None`` where it does not say)."""

    ask: Ask
    map_record: Any


def local_service(localizer: Any, bundle: Any, top_n: int = 5) -> Service:
    """The :class:`Service` of a localiser in this process serving the bundle at ``bundle``."""

    def map_record() -> Any:
        from pnvlad_service.index.manifest import Manifest

        return Manifest.read(bundle).map_record.to_json()

    return Service(local_ask(localizer, top_n), map_record)


def http_service(client: Any, top_n: int = 5) -> Service:
    """The :class:`Service` of a server (a :class:`~pnvlad_service.client.LocalizeClient`)."""
    return Service(http_ask(client, top_n), lambda: client.info()["manifest"].get("map"))
