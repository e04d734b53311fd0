"""UTM zones: the zone a map's coordinates are in, parsed and checked, and UTM (easting,
northing) turned into WGS 84 latitude and longitude.

A zone is written as its number, 1 to 60, then either

- a **latitude band** letter, C to X without I and O (the MGRS bands of 8 degrees, X 12):
  ``"30U"`` (Oxford), ``"32N"``, ``"17S"`` (North Carolina: band S is 32 to 40 degrees
  *north*). C to M are south of the equator, N to X north of it; or
- a **hemisphere** word: ``"17 south"``, ``"32 north"`` (``north``/``south``, any case, the
  space optional): the only way to name a southern zone without its band, since the letter
  ``S`` is a band.

Case and surrounding spaces do not matter; a leading zero is kept out (``"05Q"`` is ``"5Q"``).
A zone with a band also checks the coordinates it converts: their latitude must fall in the
band (a degree of slack either side, for maps that cross its edge), which catches a southern
hemisphere written as ``S``.

The conversion is pyproj's (PROJ's exact transverse Mercator, EPSG 326xx / 327xx), the
``geo`` extra, imported on first use.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.extras import require

#: The latitude bands, south to north: C starts at 80 degrees south, each 8 degrees, X 12.
BANDS = "CDEFGHJKLMNPQRSTUVWX"
#: Degrees either side of a band that a converted latitude may still lie in.
BAND_SLACK_DEG = 1.0

_ZONE = re.compile(r"^\s*0*(\d{1,2})\s*([A-Za-z]+)\s*$")
_EXAMPLES = "e.g. '30U', '32N', '17 south'"


@dataclass(frozen=True)
class UtmZone:
    """A parsed zone: ``number`` 1 to 60, ``band`` its latitude band letter or ``None``,
    ``south`` whether it lies south of the equator (false northing 10,000 km)."""

    number: int
    band: str | None
    south: bool

    def __str__(self) -> str:
        if self.band is not None:
            return f"{self.number}{self.band}"
        return f"{self.number} {'south' if self.south else 'north'}"

    @property
    def epsg(self) -> int:
        """The EPSG code of the zone on WGS 84: 326xx north, 327xx south."""
        return (32700 if self.south else 32600) + self.number

    def band_bounds(self) -> tuple[float, float] | None:
        """Latitudes (degrees) the band spans, or ``None`` without a band."""
        if self.band is None:
            return None
        low = -80.0 + 8.0 * BANDS.index(self.band)
        return low, (84.0 if self.band == "X" else low + 8.0)


def parse_zone(text: str, field: str = "utm_zone") -> UtmZone:
    """The zone written in ``text`` (module docstring). Raises ``InputError`` naming ``field``
    for anything else: an empty text, a number outside 1 to 60, an unknown letter."""
    m = _ZONE.match(str(text))
    if m is None:
        raise InputError(
            f"{text!r} is not a UTM zone: a number 1-60 and a latitude band or hemisphere "
            f"({_EXAMPLES})",
            field,
        )
    number, tail = int(m.group(1)), m.group(2).upper()
    if not 1 <= number <= 60:
        raise InputError(f"{text!r}: UTM zone number {number} is not in 1-60 ({_EXAMPLES})", field)
    if tail in ("NORTH", "SOUTH"):
        return UtmZone(number, None, tail == "SOUTH")
    if len(tail) != 1 or tail not in BANDS:
        raise InputError(
            f"{text!r}: {tail!r} is neither a latitude band (C-X without I and O) nor "
            f"'north'/'south' ({_EXAMPLES})",
            field,
        )
    return UtmZone(number, tail, BANDS.index(tail) < BANDS.index("N"))


def normalize_zone(text: str | None, field: str = "utm_zone") -> str:
    """``text`` as the canonical zone string (``" 30u"`` -> ``"30U"``, ``"17South"`` ->
    ``"17 south"``), ``""`` for ``None`` or an empty text (zone unknown). Raises
    ``InputError`` naming ``field`` for a malformed zone."""
    if text is None or not str(text).strip():
        return ""
    return str(parse_zone(text, field))


@lru_cache(maxsize=8)
def _transformer(epsg: int) -> Any:
    pyproj = require("pyproj", "pyproj", "geo", "UTM to latitude/longitude")
    return pyproj.Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)


def to_latlon(
    zone: UtmZone | str, easting: Any, northing: Any, field: str = "utm_zone"
) -> tuple[np.ndarray, np.ndarray]:
    """WGS 84 ``(latitude, longitude)`` in degrees (float64, the shape of ``easting``) of UTM
    ``easting``, ``northing`` (metres, scalars or arrays) in ``zone``.

    Raises ``InputError`` naming ``field`` for a malformed zone, coordinates that are not
    finite or lie outside any UTM zone (easting 0 to 1,000 km, northing 0 to 10,000 km), or a
    latitude outside the zone's band (module docstring)."""
    z = parse_zone(zone, field) if isinstance(zone, str) else zone
    e = np.asarray(easting, dtype=np.float64)
    n = np.asarray(northing, dtype=np.float64)
    if e.shape != n.shape:
        raise ValueError(f"easting {e.shape} and northing {n.shape} differ in shape")
    if not (np.isfinite(e).all() and np.isfinite(n).all()):
        raise InputError("easting/northing must be finite", field)
    if e.size and (e.min() <= 0 or e.max() >= 1e6 or n.min() < 0 or n.max() > 1e7):
        raise InputError(
            f"easting {e.min():.0f}..{e.max():.0f} m / northing {n.min():.0f}..{n.max():.0f} m "
            f"are not UTM coordinates of zone {z} (easting 0-1000 km, northing 0-10000 km)",
            field,
        )
    lon, lat = _transformer(z.epsg).transform(e, n)
    lat, lon = np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)
    bounds = z.band_bounds()
    if bounds is not None and lat.size:
        low, high = bounds
        if lat.min() < low - BAND_SLACK_DEG or lat.max() > high + BAND_SLACK_DEG:
            raise InputError(
                f"zone {z}: these coordinates lie at latitude {lat.min():.2f}..{lat.max():.2f}, "
                f"outside band {z.band} ({low:g} to {high:g} degrees); for the southern "
                f"hemisphere write '{z.number} south'",
                field,
            )
    return lat, lon


@lru_cache(maxsize=8)
def _to_utm(epsg: int) -> Any:
    pyproj = require("pyproj", "pyproj", "geo", "latitude/longitude to UTM")
    return pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)


def from_latlon(
    zone: UtmZone | str, latitude: Any, longitude: Any, field: str = "utm_zone"
) -> tuple[np.ndarray, np.ndarray]:
    """UTM ``(easting, northing)`` in metres (float64, the shape of ``latitude``) of WGS 84
    ``latitude``, ``longitude`` (degrees) in ``zone``: the inverse of :func:`to_latlon`.
    ``InputError`` naming ``field`` for a malformed zone or coordinates that are not finite or
    not latitudes and longitudes; the result is checked by :func:`to_latlon`'s bounds (a zone
    far from the coordinates gives eastings outside it)."""
    z = parse_zone(zone, field) if isinstance(zone, str) else zone
    lat = np.asarray(latitude, dtype=np.float64)
    lon = np.asarray(longitude, dtype=np.float64)
    if not (np.isfinite(lat).all() and np.isfinite(lon).all()):
        raise InputError("latitude/longitude must be finite", field)
    if lat.size and (np.abs(lat).max() > 90 or np.abs(lon).max() > 180):
        raise InputError("latitude must lie in -90..90 and longitude in -180..180", field)
    east, north = _to_utm(z.epsg).transform(lon, lat)
    east, north = np.asarray(east, dtype=np.float64), np.asarray(north, dtype=np.float64)
    to_latlon(z, east, north, field)  # the zone's checks: eastings in range, the band
    return east, north
