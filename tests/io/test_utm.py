"""UTM zones: what is accepted and refused, and UTM -> latitude/longitude against places whose
coordinates are published in both systems."""

from __future__ import annotations

import importlib.util
import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.io.utm import BANDS, UtmZone, normalize_zone, parse_zone, to_latlon

needs_pyproj = pytest.mark.skipif(
    importlib.util.find_spec("pyproj") is None, reason="needs the geo extra (pyproj)"
)

# (zone, easting, northing) -> (latitude, longitude), to the metre, as published with the
# `utm` package's tests (cities of both hemispheres, both sides of Greenwich).
KNOWN = [
    ("32U", 294409, 5628898, 50.77535, 6.08389),  # Aachen
    ("18T", 583960, 4507523, 40.71435, -74.00597),  # New York
    ("60G", 313784, 5427057, -41.28646, 174.77624),  # Wellington
    ("34H", 261878, 6243186, -33.92487, 18.42406),  # Cape Town
    ("6W", 466013, 7190568, 64.83778, -147.71639),  # Fairbanks
    ("30V", 377486, 6296562, 56.79680, -5.00601),  # Ben Nevis
]


@needs_pyproj
@pytest.mark.parametrize(("zone", "e", "n", "lat", "lon"), KNOWN)
def test_known_places(zone: str, e: float, n: float, lat: float, lon: float) -> None:
    got_lat, got_lon = to_latlon(zone, e, n)
    # One metre of rounding in the published coordinates is about 1e-5 degrees.
    assert got_lat == pytest.approx(lat, abs=1e-5)
    assert got_lon == pytest.approx(lon, abs=1e-5)


@needs_pyproj
def test_a_southern_zone_by_hemisphere_matches_its_band() -> None:
    # Cape Town written with the hemisphere instead of band H: the same place.
    assert np.allclose(to_latlon("34 south", 261878, 6243186), to_latlon("34H", 261878, 6243186))


@needs_pyproj
@given(st.integers(1, 60))
def test_central_meridian_at_the_equator(number: int) -> None:
    # Easting 500 km is the zone's central meridian, 6 * number - 183 degrees; northing 0 in
    # a northern zone (10,000 km in a southern one) is the equator.
    for zone, northing in ((f"{number} north", 0.0), (f"{number} south", 1e7)):
        lat, lon = to_latlon(zone, 500000.0, northing)
        assert lat == pytest.approx(0.0, abs=1e-9)
        assert lon == pytest.approx(6 * number - 183, abs=1e-9)


@needs_pyproj
def test_arrays_keep_their_shape() -> None:
    e = np.array([[294409.0, 294509.0], [294409.0, 294409.0]])
    n = np.array([[5628898.0, 5628898.0], [5628998.0, 5628898.0]])
    lat, lon = to_latlon("32U", e, n)
    assert lat.shape == lon.shape == (2, 2)
    assert lon[0, 1] > lon[0, 0] and lat[1, 0] > lat[0, 0]  # east is east, north is north


@pytest.mark.parametrize(
    ("text", "canonical", "south"),
    [
        ("30U", "30U", False),
        (" 30u ", "30U", False),
        ("32N", "32N", False),
        ("17S", "17S", False),  # band S: 32 to 40 degrees north
        ("05Q", "5Q", False),
        ("60G", "60G", True),
        ("17 south", "17 south", True),
        ("17South", "17 south", True),
        ("1 NORTH", "1 north", False),
    ],
)
def test_accepted_zones(text: str, canonical: str, south: bool) -> None:
    zone = parse_zone(text)
    assert str(zone) == canonical and zone.south is south
    assert normalize_zone(text) == canonical
    assert parse_zone(canonical) == zone  # the canonical text reads back the same


@pytest.mark.parametrize(
    "text",
    [
        "0U",
        "61U",
        "30",
        "U30",
        "30I",
        "30O",
        "30B",
        "30Y",
        "30UU",
        "thirty",
        "30 east",
        "3.5U",
        "-3U",
        "30 U 1",
    ],
)
def test_malformed_zones_name_the_field(text: str) -> None:
    with pytest.raises(InputError) as err:
        parse_zone(text, field="--utm-zone")
    assert str(err.value).startswith("--utm-zone: ")
    assert "\n" not in str(err.value)


def test_unknown_zone_is_empty() -> None:
    assert normalize_zone(None) == "" and normalize_zone("  ") == ""


def test_bands_span_the_earth() -> None:
    bounds = [UtmZone(1, b, False).band_bounds() for b in BANDS]
    assert bounds[0][0] == -80 and bounds[-1][1] == 84
    assert all(a[1] == b[0] for a, b in itertools.pairwise(bounds))


@needs_pyproj
def test_a_southern_place_written_with_band_s_is_refused() -> None:
    # Cape Town's northing read as band S (north of the equator) lands near 56 degrees north.
    with pytest.raises(InputError, match=r"outside band S.*'34 south'"):
        to_latlon("34S", 261878, 6243186)


@needs_pyproj
@pytest.mark.parametrize(
    ("e", "n"), [(0.0, 5e6), (1e6, 5e6), (5e5, -1.0), (5e5, 1.1e7), (float("nan"), 5e6)]
)
def test_coordinates_outside_any_zone_are_refused(e: float, n: float) -> None:
    with pytest.raises(InputError, match=r"^utm_zone: "):
        to_latlon("31 north", e, n)
