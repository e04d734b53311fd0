"""The one query type: :class:`Query`, a cloud and what is asked of it, checked once.

Every way a query arrives builds it with :meth:`Query.make`: the server's JSON bodies (the
request models of :mod:`pnvlad_service.server.contract` call it from their validator), its
binary bodies (:mod:`pnvlad_service.server.bodies`) and a library or CLI caller
(:meth:`~.localizer.Localizer.localize`). :meth:`Query.make` is the one home of a query's
rules, in this order:

1. ``kind`` and ``preprocess`` agree (:func:`~.limits.query_kind`: a ``submap`` is 4096
   preprocessed points; a ``scan`` or ``window`` is raw metres the filter G runs on);
2. a prior pose needs a raw scan, refuses ``verify: false``, and its values are in bounds
   (:meth:`~.limits.Limits.check_prior`);
3. the points (:meth:`~.limits.Limits.check_points`: exactly 4096 in [-1, 1], or a raw scan of
   :data:`~.limits.MIN_RAW_POINTS` (the filter G's fewest) to ``max_raw_points`` points);
4. a raw cloud loses its missing returns (points within :data:`~pnvlad_service.io.readers.
   NO_RETURN_M` of the sensor: drivers such as Ouster's write a beam that saw nothing as a
   point at the origin), counted in ``no_returns`` (the answer's); one with fewer than
   :data:`~.limits.MIN_RAW_POINTS` returns left is refused;
5. ``top_n`` and ``scale`` in bounds, and no ``scale`` on a raw scan (it is in metres).

What depends on the map (a kind the bundle does not hold, verification or a prior asked of a
bundle without geometry) is the localiser's to check when the query runs
(:meth:`~.localizer.Localizer.check`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import NO_RETURN_M, drop_no_returns
from pnvlad_service.localization.query.limits import Limits, query_kind
from pnvlad_service.localization.verify.prior import Prior

SCALE_RAW = "scale is for preprocessed clouds; a raw scan (preprocess=true) is in metres already"

PRIOR_RAW = (
    "a prior pose is the sensor's: send the raw scan (preprocess true, kind scan or window), not "
    "a preprocessed submap"
)

PRIOR_VERIFY = "a query with a prior is registered to the map: no verify=false"

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Where:
    """The names a query's refusals give its fields: ``points`` (``body`` for a binary body,
    ``queries[i].points`` in a batch), the ``prior`` and the separator of its values
    (``prior.northing`` in JSON, ``prior_northing`` for a binary body's query parameters)."""

    points: str = "points"
    prior: str = "prior"
    sep: str = "."

    @property
    def prior_itself(self) -> str:
        """The field a prior refused as a whole is named by."""
        return self.prior if self.sep == "." else f"{self.prior}{self.sep}northing"


@dataclass(frozen=True)
class Query:
    """A checked query: ``points`` float32 [4096, 3] (a ``submap``) or float64 [N, 3] metres (a
    raw ``scan`` or ``window``); ``top_n`` matches; ``verify``: ``None`` (when the bundle can),
    true or false; ``scale``: metres per unit of a preprocessed cloud, when the caller knows it;
    ``prior``: where a raw scan's sensor is thought to be (it is then registered to the map
    there, not searched for); ``no_returns``: the missing returns dropped from a raw cloud.
    Build it with :meth:`make`."""

    points: np.ndarray
    kind: str
    top_n: int
    verify: bool | None = None
    scale: float | None = None
    prior: Prior | None = None
    no_returns: int = 0

    @property
    def raw(self) -> bool:
        """Whether the cloud is a raw scan the filter G runs on (``preprocess``)."""
        return self.kind != "submap"

    @classmethod
    def make(
        cls,
        points: Any,
        *,
        limits: Limits | None = None,
        preprocess: bool | None = None,
        kind: str | None = None,
        top_n: int | None = None,
        verify: bool | None = None,
        scale: Any = None,
        prior: Prior | dict[str, Any] | None = None,
        where: Where | None = None,
    ) -> Query:
        """The query these values make, every rule checked (see the module doc); an
        :class:`InputError` naming the field (``where``'s names) for the first one broken.
        ``prior``: a :class:`Prior` or its values by name (``northing``, ``easting``,
        ``yaw_deg``, ``height``, ``radius_m``, ``run``)."""
        limits = limits or Limits()
        where = where or Where()
        if isinstance(prior, Prior):
            prior = {
                "northing": prior.northing,
                "easting": prior.easting,
                "yaw_deg": prior.yaw_deg,
                "height": prior.height,
                "radius_m": prior.radius_m,
                "run": prior.run,
            }
        given = {k: v for k, v in (prior or {}).items() if v is not None}
        kind, raw = query_kind(kind, preprocess)
        pose = None
        if given:
            if not raw:
                raise InputError(PRIOR_RAW, where.prior_itself)
            if verify is False:
                raise InputError(PRIOR_VERIFY, "verify")
            pose = limits.check_prior(**given, field=where.prior, sep=where.sep)
        pts = limits.check_points(np.asarray(points), raw, where.points)
        dropped = 0
        if raw:
            pts, dropped = _returns(pts, limits, where.points)
        n = limits.default_top_n if top_n is None else limits.check_top_n(top_n)
        scale = limits.check_scale(scale)
        if raw and scale is not None:
            raise InputError(SCALE_RAW, "scale")
        return cls(pts, kind, n, verify, scale, pose, dropped)


def _returns(points: np.ndarray, limits: Limits, field: str) -> tuple[np.ndarray, int]:
    """A raw cloud without its missing returns, and how many there were; :class:`InputError`
    naming ``field`` when fewer than ``limits.min_raw_points`` returns are left."""
    kept, dropped = drop_no_returns(points)
    if not dropped:
        return points, 0
    if len(kept) < limits.min_raw_points:
        what = "none is a return" if len(kept) == 0 else f"only {len(kept)} are returns"
        raise InputError(
            f"{len(points):,} points, {what}: {dropped:,} lie within {NO_RETURN_M} m of the sensor "
            f"(missing returns written as zeros); a raw scan needs at least "
            f"{limits.min_raw_points} returns",
            field,
        )
    log.debug("%d missing returns (points within %s m of the sensor) dropped from the %s",
             dropped, NO_RETURN_M, field)  # fmt: skip
    return np.ascontiguousarray(kept), dropped
