"""The start of a query without a scale from the map's drives (localization/verify/scale.py):
each entry's direction of travel, the metres per unit a cloud's extent along it gives, the
map-wide check that submaps span alike along their drives, and the Localizer taking that
start (and its narrower bounds) on a push-broom-like map and the candidates' median on the
tiny spinning city."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from pnvlad_service.io.submap import read_submap
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.scale import (
    ScaleConfig,
    along_drive_spread,
    along_track_scale,
    map_tracks,
    track_directions,
    track_scales,
)
from pnvlad_service.localization.verify.verify import VerifyConfig


def _unit(deg: float) -> np.ndarray:
    return np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg))])


def test_track_directions_follow_each_drive_and_skip_gaps() -> None:
    # drive a: east, 10 m a step, its times shuffled in the table; drive b: north-east, with
    # a 100 m gap after its third entry; drive c: one entry
    a = [(t, 10.0 * t, 0.0) for t in (2, 0, 3, 1)]
    b = [(t, 7.0 * t, 7.0 * t) for t in range(3)] + [(3, 14 + 80.0, 14 + 60.0), (4, 99.0, 64.0)]
    rows = [("a", *r) for r in a] + [("b", *r) for r in b] + [("c", 0, 5.0, 5.0)]
    groups = np.array([r[0] for r in rows])
    t = np.array([r[1] for r in rows])
    east = np.array([r[2] for r in rows])
    north = np.array([r[3] for r in rows])
    d = track_directions(groups, t, east, north, max_gap_m=60.0)
    assert np.allclose(d[:4], [1.0, 0.0])
    assert np.allclose(d[4:7], _unit(45.0))  # the gap's side ignored at b's third entry
    last = np.array([99.0 - 94.0, 64.0 - 74.0])
    assert np.allclose(d[7], last / np.linalg.norm(last))  # after the gap: its one neighbour
    assert np.allclose(d[8], last / np.linalg.norm(last))
    assert np.isnan(d[9]).all()


def _swept(rng: np.random.Generator, heading_deg: float, far: bool) -> np.ndarray:
    """What a push-broom records along 20 m of a street heading ``heading_deg`` (metres,
    centred on the stretch): facades 6 m either side up to 12 m, the road's edge, and with
    ``far`` crowns 20-30 m off to one side (what one drive reached and another did not)."""
    s = rng.uniform(-10.0, 10.0, 3000)
    side = np.where(rng.random(3000) < 0.5, -6.0, 6.0) + rng.normal(0, 0.1, 3000)
    z = rng.uniform(0.0, 12.0, 3000)
    parts = [np.c_[s, side, z]]
    if far:
        n = 1500
        parts.append(np.c_[rng.uniform(-10, 10, n), rng.uniform(20, 30, n), rng.uniform(4, 9, n)])
    pts = np.vstack(parts)
    c, si = np.cos(np.radians(heading_deg)), np.sin(np.radians(heading_deg))
    rot = np.array([[c, -si, 0.0], [si, c, 0.0], [0.0, 0.0, 1.0]])
    return pts @ rot.T


def _g_units(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """G's normalisation: centred, mean distance 0.5; (cloud, metres per unit)."""
    c = pts - pts.mean(axis=0)
    mpu = float(np.linalg.norm(c, axis=1).mean() / 0.5)
    return c / mpu, mpu


@pytest.mark.parametrize("heading", [0.0, 33.0, 118.0])
def test_the_extent_along_the_drive_gives_the_scale_that_g_loses(heading: float) -> None:
    rng = np.random.default_rng(int(heading))
    query, mpu = _g_units(_swept(rng, heading, far=True))
    candidate = _swept(rng, heading + 180.0, far=False)  # the other sense of travel
    _, cand_mpu = _g_units(candidate)
    assert abs(cand_mpu / mpu - 1.0) > 0.25  # G's scales of one place disagree
    d = _unit(heading)
    assert along_track_scale(query, candidate, d) == pytest.approx(mpu, rel=0.03)
    assert along_track_scale(-query, candidate, -d) == pytest.approx(mpu, rel=0.03)
    assert along_track_scale(query, candidate, np.array([np.nan, np.nan])) is None
    assert along_track_scale(np.zeros((50, 3)), candidate, d) is None


def test_track_scales_keep_each_candidates_sign_and_fall_back_without_directions() -> None:
    rng = np.random.default_rng(4)
    query, mpu = _g_units(_swept(rng, 20.0, far=False))
    cand = _swept(rng, 20.0, far=True)
    dirs = np.array([_unit(20.0), [np.nan, np.nan], _unit(20.0)])
    got = track_scales(query, [-30.0, 41.0, 25.0], [lambda: cand] * 3, dirs)
    assert got is not None and got[1] == 41.0
    assert got[0] < 0 < got[2]
    assert -got[0] == pytest.approx(mpu, rel=0.03) and got[2] == pytest.approx(mpu, rel=0.03)
    assert track_scales(query, [30.0], [lambda: cand], np.full((1, 2), np.nan)) is None


def test_only_a_map_whose_submaps_span_alike_along_their_drives_gives_tracks() -> None:
    rng = np.random.default_rng(5)
    n = 40
    meta = SimpleNamespace(
        dataset=np.array(["d"] * n),
        run=np.array(["r"] * n),
        timestamp=np.arange(n),
        easting=10.0 * np.arange(n),
        northing=np.zeros(n),
    )
    swept = [_swept(rng, 0.0, far=bool(i % 2)) for i in range(n)]
    config = ScaleConfig(track_spread=1.3)
    steady = map_tracks(meta, lambda i: swept[i])
    assert config.takes_tracks(steady) and np.allclose(steady.directions, [1.0, 0.0])
    assert not ScaleConfig(track_spread=None).takes_tracks(steady)
    # a spinning sensor's submaps reach as far along the street as it sees: 40-160 m
    reach = rng.uniform(20.0, 80.0, n)
    spun = [s * [r / 10.0, 1.0, 1.0] for s, r in zip(swept, reach, strict=True)]
    assert not config.takes_tracks(map_tracks(meta, lambda i: spun[i]))
    assert along_drive_spread(np.full((n, 2), np.nan), lambda i: swept[i]) == np.inf


def test_tracked_config_narrows_the_bounds_and_the_sweep() -> None:
    base = ScaleConfig()
    t = base.tracked()
    assert t.bounds == t.sweep_bounds == base.track_bounds
    assert t.sweep_steps == base.track_sweep_steps
    assert np.allclose(t.sweep()[[0, -1]], base.track_bounds)
    assert t.starts == (1.0,)
    with pytest.raises(ValueError, match="track_bounds"):
        ScaleConfig(track_bounds=(1.05, 1.2))
    with pytest.raises(ValueError, match="track_spread"):
        ScaleConfig(track_spread=0.9)


# --- through the Localizer -------------------------------------------------------------


def _query(tiny_maps: dict):
    tree, run = tiny_maps["tree"], tiny_maps["query_run"]
    sub = tree.submaps("business", run, "test")[0]
    frame = tree.frames("business", run, "test")[0]
    return read_submap(tree.root / sub.path), frame


def test_a_spinning_map_keeps_the_candidates_median(tiny_maps: dict) -> None:
    """The tiny city's submaps reach along the street as far as its sensor sees: no tracks,
    and a query without a scale starts from its candidates' median scale, as before."""
    cloud, _ = _query(tiny_maps)
    with Localizer.load(tiny_maps["map"]) as loc:
        loc.verify_config = VerifyConfig(candidates=4, threshold=0.0, stop_score=None)
        prepared = loc.prepare(cloud, False, None)
        ids = [int(i) for i in loc.submit(prepared, 4).result().ids]
        v = loc.verify_ids(prepared, ids)
        start = v.pose.metres_per_unit / v.checks[0].scale
        median = float(np.median([abs(loc.bundle.geometry.scale(i)) for i in ids]))
        assert abs(start) == pytest.approx(median, rel=1e-9)


def test_a_map_of_steady_drives_starts_from_them(tiny_maps: dict) -> None:
    """With the spread allowed wide enough to take the tiny city's drives as steady, the
    start is the median of the candidates' along-drive estimates, computed here apart, and
    the factor found stays within the tracked bounds."""
    cloud, _ = _query(tiny_maps)
    with Localizer.load(tiny_maps["map"]) as loc:
        prepared = loc.prepare(cloud, False, None)
        ids = [int(i) for i in loc.submit(prepared, 4).result().ids]
        # the map's drives are made once, on this first query without a scale; each call's
        # own config then decides whether a query starts from them
        loc.verify_config = VerifyConfig(candidates=4, threshold=0.0, stop_score=None)
        median = loc.verify_ids(prepared, ids)
        assert abs(median.pose.metres_per_unit / median.checks[0].scale) == pytest.approx(
            float(np.median([abs(loc.bundle.geometry.scale(i)) for i in ids])), rel=1e-9
        )
        scale = ScaleConfig(track_spread=100.0)
        loc.verify_config = replace(loc.verify_config, scale=scale)
        v = loc.verify_ids(prepared, ids)
        meta, geo = loc.bundle.metadata, loc.bundle.geometry
        expected = []
        for i in ids:  # the direction from the entry's neighbours in its drive, apart
            same = np.flatnonzero((meta.run == meta.run[i]) & (meta.dataset == meta.dataset[i]))
            same = same[np.argsort(meta.timestamp[same])]
            j = int(np.flatnonzero(same == i)[0])
            a, b = same[max(j - 1, 0)], same[min(j + 1, len(same) - 1)]
            d = np.array([meta.easting[b] - meta.easting[a], meta.northing[b] - meta.northing[a]])
            d /= np.linalg.norm(d)
            ext = [np.ptp(np.percentile(p[:, :2] @ d, [0.5, 99.5])) for p in (geo.metres(i), cloud)]
            expected.append(ext[0] / ext[1])
        start = v.pose.metres_per_unit / v.checks[0].scale
        assert abs(start) == pytest.approx(float(np.median(expected)), rel=1e-6)
        lo, hi = scale.track_bounds
        assert lo - 1e-9 <= v.checks[0].scale <= hi + 1e-9
