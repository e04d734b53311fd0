"""A query without a scale (a submap as the benchmark publishes it): its scale found by
registration (localization/verify/scale.py), on a built street scene whose true scale is
known, and end to end on the tiny city's bundle, where the frame sidecars hold each query's
scale and true pose; and a query with its scale answered as the rigid registration alone
answers it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pnvlad_service.io.submap import read_submap
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.localization.verify.scale import (
    ScaleConfig,
    common_factor,
    refine_scale,
    register_scaled,
    similarity,
)
from pnvlad_service.localization.verify.verify import (
    Candidate,
    Check,
    QueryCloud,
    VerifyConfig,
    estimated_scale,
    verify,
)
from tests.localization import submap_pairs as sp
from tests.localization.test_registration import moved, street

pytest.importorskip("small_gicp")


def test_similarity_recovers_a_known_one() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(0, 10, (200, 3))
    rot = Rotation.from_euler("zyx", [70.0, 2.0, -1.0], degrees=True).as_matrix()
    t = np.array([4.0, -2.0, 0.5])
    s, r, tt = similarity(src, 1.23 * src @ rot.T + t)
    assert s == pytest.approx(1.23, rel=1e-9)
    assert np.allclose(r, rot, atol=1e-9) and np.allclose(tt, t, atol=1e-9)
    # a reflection in the data is not taken: the answer stays a rotation
    _, r2, _ = similarity(src, src * [1.0, 1.0, -1.0])
    assert np.linalg.det(r2) == pytest.approx(1.0)


def test_estimated_scale_is_the_median_size_with_the_majority_sign() -> None:
    assert estimated_scale([50.0, 70.0, 60.0]) == 60.0
    assert estimated_scale([-50.0, -70.0, 60.0]) == -60.0
    assert estimated_scale([-50.0, 70.0, 60.0]) == 60.0
    assert estimated_scale([]) == 1.0


def _normalised_query(seed: int) -> tuple[np.ndarray, float, np.ndarray]:
    """A query of street(1) as G leaves it: (cloud in units, its true metres per unit, the
    true transform from its centroid frame in metres to the street's frame)."""
    rng = np.random.default_rng(seed)
    truth = sp.yaw_matrix(np.radians(35.0), np.array([3.0, -1.0, 0.0]))
    query_m = moved(street(1), truth, rng)
    centroid = query_m.mean(axis=0)
    mpu = float(np.linalg.norm(query_m - centroid, axis=1).mean() / 0.5)
    from_centroid = truth.copy()
    from_centroid[:3, 3] += truth[:3, :3] @ centroid
    return (query_m - centroid) / mpu, mpu, from_centroid


@pytest.mark.parametrize("start", [0.85, 0.92, 1.08, 1.2])
def test_a_wrong_starting_scale_is_registered_back_to_the_true_one(start: float) -> None:
    """Started 8-20 % off (the spread of the candidates' scales on the demo city), the
    registration finds the true scale within 1 % and the true pose within 0.3 m; the rigid
    registration at the start scores clearly less."""
    cloud, mpu, truth = _normalised_query(5)
    target = reg.prepare(street(1), reg.DEFAULT, "target")
    query_m = cloud * mpu * start
    source = reg.prepare(query_m, reg.DEFAULT, "source")
    result, k = register_scaled(query_m, source, target)
    assert start * k == pytest.approx(1.0, abs=0.01)
    assert np.linalg.norm(result.transform[:3, 3] - truth[:3, 3]) < 0.3
    rigid = reg.register(source, target)
    assert result.fitness > rigid.fitness + 0.1, (result.fitness, rigid.fitness)


def test_refine_scale_stays_within_its_bounds() -> None:
    cloud, mpu, _ = _normalised_query(6)
    target = reg.prepare(street(1), reg.DEFAULT, "target")
    query_m = cloud * mpu * 1.3
    first = reg.register(reg.prepare(query_m, reg.DEFAULT, "source"), target)
    points = reg.prepare(query_m, reg.DEFAULT, "source").points
    k, _ = refine_scale(points, target, first.transform, ScaleConfig(bounds=(0.9, 1.1)))
    assert 0.9 <= k <= 1.1
    assert k == pytest.approx(0.9)  # the truth (1 / 1.3) lies beyond: held at the bound


def test_common_factor_keeps_the_factor_that_fits_most() -> None:
    """A query 25 % too large: from a check at the true pose but its factor 1, the sweep's
    factor nearest the truth is kept (its steps are 12-14 % apart). One 20 % too large, with
    also the check :func:`register_scaled` gives (its factor within 1 % of the truth): that
    check's factor."""
    cloud, mpu, truth = _normalised_query(5)
    target = reg.prepare(street(1), reg.DEFAULT, "target")
    query_m = cloud * mpu * 1.25
    posed = Check(1, 0.2, 1.0, truth, 0.1, 1.0)
    k = common_factor(query_m, [(target, posed)])
    assert k in ScaleConfig().sweep()
    assert abs(1.25 * k - 1.0) < 0.07, k
    query_m = cloud * mpu * 1.2
    scaled, own = register_scaled(query_m, reg.prepare(query_m, reg.DEFAULT, "source"), target)
    assert abs(1.2 * own - 1.0) < 0.01
    refined = Check(1, scaled.fitness, scaled.rmse_m, scaled.transform, scaled.constraint, own)
    assert common_factor(query_m, [(target, posed), (target, refined)]) == own


def test_without_a_scale_every_candidate_is_registered_rigidly_at_one_factor() -> None:
    """The second pass: each check is the rigid registration of the query rescaled by one
    factor, computed here apart, and the pose's metres per unit are the start times it."""
    cloud, mpu, truth = _normalised_query(7)
    query = QueryCloud.from_normalised(cloud, candidate_scales=[1.1 * mpu])
    scenes = {1: street(1), 2: street(2)}
    cands = [Candidate(k, c, np.eye(4), key=f"c{k}") for k, c in scenes.items()]
    v = verify(query, cands, VerifyConfig(stop_score=None, threshold=0.2))
    assert v.verified and v.checks[0].rank == 1 and v.registered == 4
    k = v.checks[0].scale
    assert {c.scale for c in v.checks} == {k} and abs(1.1 * k - 1.0) < 0.01
    source = reg.prepare(query.points_m * k, reg.DEFAULT, "source")
    for check in v.checks:
        alone = reg.register(source, reg.prepare(scenes[check.rank], reg.DEFAULT, "target"))
        assert check.score == pytest.approx(alone.fitness, abs=1e-9)
        assert np.allclose(check.transform, alone.transform, atol=1e-6)
    assert v.pose.metres_per_unit == pytest.approx(1.1 * mpu * k)
    assert np.linalg.norm(v.pose.transform[:3, 3] - truth[:3, 3]) < 0.3
    # without the second pass each candidate keeps a factor of its own
    alone = verify(
        query,
        cands,
        VerifyConfig(stop_score=None, threshold=0.2, scale=ScaleConfig(sweep_candidates=0)),
    )
    assert alone.registered == 2


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"sweep_candidates": -1}, "sweep_candidates"),
        ({"sweep_bounds": (1.2, 1.1)}, "sweep_bounds"),
        ({"sweep_steps": 0}, "sweep_steps"),
        ({"bounds": (1.1, 1.4)}, "bounds"),
        ({"starts": (1.5,)}, "starts"),
        ({"starts": ()}, "starts"),
        ({"rounds": 0}, "rounds"),
        ({"distances": (3.0, 0.0)}, "distances"),
    ],
)
def test_a_bad_scale_config_names_its_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        ScaleConfig(**kwargs)


def test_verify_without_a_scale_poses_the_query_and_says_its_scale() -> None:
    cloud, mpu, truth = _normalised_query(7)
    # the candidates' scales say 10 % too much; the true candidate is ranked second
    query = QueryCloud.from_normalised(cloud, candidate_scales=[1.1 * mpu] * 3)
    assert query.scale == "estimated" and query.metres_per_unit == pytest.approx(1.1 * mpu)
    cands = [
        Candidate(k, c, np.eye(4), key=f"c{k}")
        for k, c in enumerate([street(2), street(1), street(3)], 1)
    ]
    v = verify(query, cands, VerifyConfig(stop_score=None, threshold=0.2))
    assert v.verified and v.checks[0].rank == 2
    assert v.pose.scale == "estimated"
    assert v.pose.metres_per_unit == pytest.approx(mpu, rel=0.01)
    assert np.linalg.norm(v.pose.transform[:3, 3] - truth[:3, 3]) < 0.3


# --- the tiny city ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def city(tiny_maps: dict) -> dict:
    tree, run = tiny_maps["tree"], tiny_maps["query_run"]
    subs = tree.submaps("business", run, "test")
    frames = tree.frames("business", run, "test")
    queries = [(read_submap(tree.root / s.path), s, f) for s, f in zip(subs, frames, strict=True)]
    return {**tiny_maps, "queries": queries}


def _true_xy(frame) -> np.ndarray:
    """The query's centroid frame's true position (easting, northing)."""
    return (frame.true_pose[:3, :3] @ frame.centre + frame.true_pose[:3, 3])[:2]


def test_queries_without_scale_verify_at_the_right_place_with_their_scale(city: dict) -> None:
    """Every candidate registered (the model is random): queries without a scale verify about
    as often as with it, every verified one within 25 m of the truth (map poses carry the
    simulated GNSS error), its scale within 3 % of the sidecar's."""
    with Localizer.load(city["map"]) as loc:
        loc.verify_config = VerifyConfig(
            candidates=min(100, loc.bundle.count), threshold=0.1, stop_score=None
        )
        known = free = 0
        for cloud, _, frame in city["queries"]:
            known += bool(loc.localize(cloud, top_n=1, scale=frame.scale).verified)
            ans = loc.localize(cloud, top_n=1)
            if not ans.verified:
                continue
            free += 1
            pose = ans.verification.pose
            assert pose.scale == "estimated"
            assert pose.metres_per_unit == pytest.approx(frame.scale, rel=0.03)
            assert np.linalg.norm([pose.easting, pose.northing] - _true_xy(frame)) < 25.0
    assert known >= 3 and free >= known - 1, (known, free, len(city["queries"]))


def test_a_query_with_its_scale_is_registered_rigidly_as_before(city: dict) -> None:
    """With a scale, each candidate's check is the rigid registration of the query at that
    scale, computed here apart (what verification did before the scale could be free), and the
    scale's settings change nothing."""
    cloud, _, frame = city["queries"][0]
    config = VerifyConfig(candidates=4, threshold=0.1, stop_score=None)
    with Localizer.load(city["map"]) as loc:
        loc.verify_config = config
        ans = loc.localize(cloud, top_n=4, scale=frame.scale)
        loc.verify_config = replace(config, scale=ScaleConfig(bounds=(0.5, 2.0), rounds=1))
        again = loc.localize(cloud, top_n=4, scale=frame.scale)
        ids = loc.submit(loc.prepare(cloud, False, frame.scale), 4).result().ids
        geometry = loc.bundle.geometry
        source = reg.prepare(cloud * frame.scale, reg.DEFAULT, "source")
        checks = ans.verification.checks
        assert len(checks) == 4
        if ans.verified:
            assert ans.verification.pose.scale == "measured"
            assert ans.verification.pose.metres_per_unit == frame.scale
        for check in checks:
            target = reg.prepare(geometry.metres(int(ids[check.rank - 1])), reg.DEFAULT, "target")
            alone = reg.register(source, target)
            assert check.scale == 1.0
            assert check.score == pytest.approx(alone.fitness, abs=1e-9)
            assert np.allclose(check.transform, alone.transform, atol=1e-6)
        assert again.verification.order == ans.verification.order
        for a, b in zip(checks, again.verification.checks, strict=True):
            assert a.score == pytest.approx(b.score, abs=1e-9)
            assert np.allclose(a.transform, b.transform, atol=1e-6)
