"""The limits of a query and the check of its point array: the one home of both.

:class:`Limits` holds every bound a query must respect (the server builds one from its
settings; the library's default is the server's default). :meth:`Limits.check_points` is the
check of one cloud as an array, used by every way a cloud arrives: the server's JSON and
binary bodies and a library or CLI caller. The server's request models and their JSON Schema
(``pnvlad_service.server.contract``) are derived from the same :class:`Limits`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import SUBMAP_BOUND, SUBMAP_POINTS

if TYPE_CHECKING:
    from pnvlad_service.localization.verify.prior import Prior

#: Longest ``run`` (dataset/run of the map) a prior may name.
MAX_RUN_CHARS = 256

#: Fewest points of a raw scan: the filter G's own fewest (``GConfig.min_points``' default),
#: below which it refuses any scan, so that the HTTP contract can say so.
MIN_RAW_POINTS = 16

#: Slack on the submap bound: normalised clouds written by other tools round a little past it.
BOUND_SLACK = 1e-4


@dataclass(frozen=True)
class Limits:
    """What a query may hold. Points per cloud and the coordinate bounds are the format's;
    the counts are configurable (``ServerSettings`` takes its defaults from here)."""

    #: Most points of a raw scan (``preprocess``); the fewest is :data:`MIN_RAW_POINTS` (the
    #: filter G may still refuse a scan that cropping or ground removal leaves too small).
    max_raw_points: int = 500_000
    #: Largest ``top_n`` a query may ask for.
    max_top_n: int = 100
    #: Most clouds in one batch request.
    max_batch_queries: int = 64
    #: ``top_n`` when a query gives none.
    default_top_n: int = 5
    #: Points of a preprocessed cloud (exactly).
    points_per_cloud: int = SUBMAP_POINTS
    #: Largest |coordinate| of a preprocessed cloud (the normalised frame, with its slack).
    bound: float = SUBMAP_BOUND + BOUND_SLACK
    #: Largest |coordinate| of a raw scan, metres (sensor frame): far beyond any LiDAR's
    #: range, and it keeps overflowing values (1e308) away from the filter G's plane fits.
    max_raw_coord: float = 100_000.0
    #: Fewest points of a raw scan.
    min_raw_points: int = MIN_RAW_POINTS
    #: Largest ``scale`` (metres per normalised unit) a preprocessed query may give.
    max_scale: float = 1000.0
    #: Largest radius a prior pose may ask the map to be searched within, metres
    #: (``PNVLAD_MAX_PRIOR_RADIUS``): the entries within it are registered to the scan.
    max_prior_radius_m: float = 100.0
    #: Radius of a prior that gives none, metres (``PNVLAD_PRIOR_RADIUS``; docs/TRACKING.md).
    default_prior_radius_m: float = 20.0
    #: Largest |northing| or |easting| of a prior, metres: beyond any UTM coordinate, and it
    #: keeps overflowing values away from the range search.
    max_prior_coord: float = 1e8

    def to_json(self) -> dict[str, float]:
        """The configurable counts, the cloud size and the prior's radii, as ``GET /info``
        reports them."""
        return {
            "max_raw_points": self.max_raw_points,
            "max_top_n": self.max_top_n,
            "max_batch_queries": self.max_batch_queries,
            "points_per_cloud": self.points_per_cloud,
            "max_prior_radius_m": self.max_prior_radius_m,
            "default_prior_radius_m": self.default_prior_radius_m,
        }

    def check_radius(self, radius: Any, field: str = "prior.radius_m") -> float:
        """A prior's search radius as a float in (0, max_prior_radius_m] (``None``: the
        default); :class:`InputError` naming ``field`` else."""
        if radius is None:
            return self.default_prior_radius_m
        if isinstance(radius, bool) or not isinstance(radius, int | float):
            raise InputError(f"expected a number, got {show_value(radius)}", field)
        if not (math.isfinite(radius) and 0.0 < radius <= self.max_prior_radius_m):
            raise InputError(
                f"must be > 0 and <= {self.max_prior_radius_m:g} metres, got {radius}", field
            )
        return float(radius)

    def check_prior(
        self,
        northing: Any = None,
        easting: Any = None,
        yaw_deg: Any = None,
        height: Any = None,
        radius_m: Any = None,
        run: Any = None,
        field: str = "prior",
        sep: str = ".",
    ) -> Prior:
        """A prior pose (UTM metres, degrees) as a :class:`~.prior.Prior`: each value a finite
        number, |northing| and |easting| at most ``max_prior_coord``, |yaw_deg| at most 360,
        |height| at most ``max_raw_coord``, the radius by :meth:`check_radius`, the ``run`` a
        string (a run the map does not hold is not an error: the nearest entries are taken);
        :class:`InputError` naming ``field.<name>`` else (a missing one is named too; ``sep``
        joins the two: ``_`` for the query parameters of a binary body)."""
        from pnvlad_service.localization.verify.prior import Prior

        bounds = {
            "northing": self.max_prior_coord,
            "easting": self.max_prior_coord,
            "yaw_deg": 360.0,
            "height": self.max_raw_coord,
        }
        values = {"northing": northing, "easting": easting, "yaw_deg": yaw_deg, "height": height}
        out: dict[str, float | None] = {}
        for name, value in values.items():
            where = f"{field}{sep}{name}"
            if value is None:
                if name != "height":
                    raise InputError("field required: a prior is northing, easting and yaw_deg "
                                     "(height optional)", where)  # fmt: skip
                out[name] = None
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InputError(f"expected a number, got {show_value(value)}", where)
            if not (math.isfinite(value) and abs(value) <= bounds[name]):
                raise InputError(f"must be a number within ±{bounds[name]:g}, got {value}", where)
            out[name] = float(value)
        radius = self.check_radius(radius_m, f"{field}{sep}radius_m")
        if run is not None and not (isinstance(run, str) and 0 < len(run) <= MAX_RUN_CHARS):
            raise InputError(
                f"expected the map's dataset/run (1 to {MAX_RUN_CHARS} characters), got "
                f"{show_value(run)}",
                f"{field}{sep}run",
            )
        return Prior(
            northing=out["northing"],  # type: ignore[arg-type]
            easting=out["easting"],  # type: ignore[arg-type]
            yaw_deg=out["yaw_deg"],  # type: ignore[arg-type]
            radius_m=radius,
            height=out["height"],
            run=run,
        )

    def check_scale(self, scale: Any, field: str = "scale") -> float | None:
        """``scale`` (metres per unit of a preprocessed cloud) as a float in (0, max_scale],
        or ``None``; :class:`InputError` naming ``field`` else."""
        if scale is None:
            return None
        if isinstance(scale, bool) or not isinstance(scale, int | float):
            raise InputError(f"expected a number, got {show_value(scale)}", field)
        if not (math.isfinite(scale) and 0.0 < scale <= self.max_scale):
            raise InputError(f"must be > 0 and <= {self.max_scale:g} metres, got {scale}", field)
        return float(scale)

    def check_top_n(self, top_n: Any, field: str = "top_n") -> int:
        """``top_n`` as an int in 1..max_top_n; :class:`InputError` naming ``field`` else."""
        if isinstance(top_n, bool) or not isinstance(top_n, int):
            raise InputError(f"expected an integer, got {show_value(top_n)}", field)
        if not 1 <= top_n <= self.max_top_n:
            raise InputError(f"must be between 1 and {self.max_top_n}, got {top_n}", field)
        return top_n

    def check_count(self, count: int, field: str) -> None:
        """A batch of ``count`` clouds: 1..max_batch_queries."""
        if not 1 <= count <= self.max_batch_queries:
            raise InputError(f"expected 1 to {self.max_batch_queries} clouds, got {count}", field)

    def check_points(self, points: np.ndarray, preprocess: bool, field: str) -> np.ndarray:
        """Validate one cloud; return float32 [4096, 3] (preprocessed) or float64 [N, 3] (raw).

        Preprocessed: exactly :attr:`points_per_cloud` finite points, |coordinate| <=
        :attr:`bound`. Raw (``preprocess``): :attr:`min_raw_points` to :attr:`max_raw_points`
        finite points, |coordinate| <= :attr:`max_raw_coord` metres. The checks run in that
        order; errors name ``field`` or ``field[i]`` of the first bad point. No copy is made
        when ``points`` already has the returned dtype and is contiguous.
        """
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(
                f"expected an array of [x, y, z] points, got shape {points.shape}", field
            )
        n = len(points)
        if not np.isfinite(points).all():
            bad = int(np.argwhere(~np.isfinite(points))[0][0])
            raise InputError(f"point {bad} has a NaN or infinite coordinate", f"{field}[{bad}]")
        if preprocess:
            if not self.min_raw_points <= n <= self.max_raw_points:
                raise InputError(
                    f"a raw scan needs between {self.min_raw_points} and {self.max_raw_points} "
                    f"points, got {n}",
                    field,
                )
            out64 = np.ascontiguousarray(points, dtype=np.float64)
            if _outside(out64, self.max_raw_coord):
                bad = _first_outside(out64, self.max_raw_coord)
                raise InputError(
                    f"point {bad} is more than {self.max_raw_coord:,.0f} m from the sensor: raw "
                    "scans are in the sensor frame, metres",
                    f"{field}[{bad}]",
                )
            return out64
        if n != self.points_per_cloud:
            raise InputError(
                f"expected exactly {self.points_per_cloud} preprocessed points, got {n} "
                "(send a raw scan with preprocess=true)",
                field,
            )
        if _outside(points, self.bound):  # on the values as sent, before the float32 cast
            bad = _first_outside(points, self.bound)
            raise InputError(
                f"point {bad} lies outside [-1, 1]: preprocessed points are in the benchmark's "
                "normalised frame (send a raw scan with preprocess=true)",
                f"{field}[{bad}]",
            )
        return np.ascontiguousarray(points, dtype=np.float32)


def show_value(value: Any) -> str:
    """A value as JSON (as a JSON body would have it), else its repr; at most 40 characters."""
    try:
        return json.dumps(value)[:40]
    except (TypeError, ValueError):
        return repr(value)[:40]


def _outside(points: np.ndarray, bound: float) -> bool:
    """Whether any coordinate of finite ``points`` has |value| > ``bound`` (no temporary)."""
    return bool(points.max() > bound or points.min() < -bound)


def _first_outside(points: np.ndarray, bound: float) -> int:
    return int(np.argmax((np.abs(points) > bound).any(axis=1)))


def query_kind(kind: str | None, preprocess: bool | None) -> tuple[str, bool]:
    """``(kind, preprocess)`` of a query, each told by the other when absent: a ``submap`` is
    4096 preprocessed points; a ``scan`` (one raw scan, sensor frame) and a ``window`` (raw scans
    accumulated over the last stretch of a drive, its newest scan's frame) are metres that the
    filter G runs on. Without either, a cloud is a preprocessed submap. :class:`InputError`
    naming ``kind`` or ``preprocess`` when they disagree or the kind is unknown."""
    from pnvlad_service.index.manifest import QUERY_KINDS

    if kind is None:
        return ("scan" if preprocess else "submap"), bool(preprocess)
    if kind not in QUERY_KINDS:
        raise InputError(f"must be one of {list(QUERY_KINDS)}, got {kind!r}", "kind")
    if kind == "submap":
        if preprocess:
            raise InputError(
                "a submap query is 4096 preprocessed points: send preprocess=false (or none), "
                "or kind scan / window for metres",
                "preprocess",
            )
        return kind, False
    if preprocess is False:
        raise InputError(
            f"a {kind} query is sent raw, in metres, for the filter G: send preprocess=true (or "
            "none)",
            "preprocess",
        )
    return kind, True
