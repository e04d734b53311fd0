"""What a drive reads of an answer (localization/drive/service.py): the localiser's typed
answer and the server's JSON of the same query become the same :class:`Reply`, searched for
and registered near a prior, with and without verification; a bundle in this process and a
real `pnvlad serve` on 127.0.0.1 give a drive the same replies."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterator

import numpy as np
import pytest

from pnvlad_service.client import LocalizeClient
from pnvlad_service.localization.drive.service import Reply, http_ask, local_ask
from pnvlad_service.localization.query.config import LocalizerConfig, PriorSection
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.prior import Prior
from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server

SCAN = 21  # the held-out drive's scan that the keyframe map verifies (test_cli_follow.py)


@pytest.fixture(scope="module")
def drive():
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    return simulated_drive(get_preset("tiny"), 0, 0, 3)  # tiny_maps' held-out run


def assert_same(a: Reply, b: Reply) -> None:
    """Field by field; floats to 1e-9 (a registration's last digits vary between runs)."""
    for f in dataclasses.fields(Reply):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name in ("pose", "covariance", "fit_pose", "fit_covariance"):
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-9)
        elif isinstance(x, float):
            assert y == pytest.approx(x, rel=1e-9), f.name
        else:
            assert x == y, f.name


def wire(answer) -> Reply:
    """The answer's JSON as a client reads it off the wire."""
    return Reply.of_json(json.loads(json.dumps(answer.to_json())))


def test_the_typed_answer_and_its_json_are_one_reply(tiny_maps: dict, drive) -> None:
    points = drive.scan(SCAN)
    limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
    with Localizer.load(tiny_maps["keys"]) as loc:
        searched = loc.localize(points, kind="scan", limits=limits)
        true = drive.true_poses[SCAN]
        near = loc.localize(points, kind="scan", limits=limits, prior=Prior.of_matrix(true))
    with Localizer.load(tiny_maps["plain"]) as loc:
        plain = loc.localize(points, kind="scan", limits=limits)
    for answer in (searched, near, plain):
        reply = Reply.of_answer(answer)
        assert_same(reply, wire(answer))
        top = answer.matches[0]
        assert (reply.top.submap_id, reply.top.northing) == (top.submap_id, top.northing)
        assert reply.timings_ms["total"] == pytest.approx(answer.timings.total * 1e3, abs=1e-3)
    s, n, p = (Reply.of_answer(a) for a in (searched, near, plain))
    assert s.mode == "search" and s.verified is searched.verification.verified
    assert s.confidence == searched.verification.confidence and s.fitness is None
    # Near the truth: registered, verified, the pose within a metre of the truth.
    assert n.mode == "prior" and n.verified and n.fitness == near.prior.fitness
    assert n.correction_m == near.prior.correction_m and n.sigma_m == near.prior.sigma_m
    assert math.dist(n.pose[:2, 3], true[:2, 3]) < 1.0
    np.testing.assert_array_equal(n.verified_pose, near.prior.pose.transform)
    np.testing.assert_array_equal(n.fit_pose, n.pose)
    np.testing.assert_array_equal(n.fit_covariance, n.covariance)
    # A bundle without geometry does not verify: no verdict, no confidence, no pose.
    assert (p.verified, p.confidence, p.pose, p.verified_pose) == (None, None, None, None)
    assert (s.fit_pose, p.fit_pose) == (None, None)


def test_an_uncertain_registration_carries_its_pose_on_both_paths(tiny_maps: dict, drive) -> None:
    """A registration that fits but is too loose to verify (here: any standard deviation over
    1 mm) is not the answer's pose, but its pose and covariance reach the drive (a tracker
    weighs them against its odometry), through the typed answer and its JSON alike."""
    points = drive.scan(SCAN)
    limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
    prior = Prior.of_matrix(drive.true_poses[SCAN])
    strict = LocalizerConfig(prior=PriorSection(max_sigma=1e-3))
    with Localizer.load(tiny_maps["keys"]) as loc:
        firm = Reply.of_answer(loc.localize(points, kind="scan", limits=limits, prior=prior))
    with Localizer.load(tiny_maps["keys"], config=strict) as loc:
        answer = loc.localize(points, kind="scan", limits=limits, prior=prior)
    loose = Reply.of_answer(answer)
    assert_same(loose, wire(answer))
    assert (loose.verified, loose.uncertain, loose.pose, loose.covariance) == (
        False, True, None, None,
    )  # fmt: skip
    assert loose.reason.startswith("position uncertain along a direction")
    # The same registration as the verified one of the default rules.
    np.testing.assert_allclose(loose.fit_pose, firm.pose, atol=1e-6)
    np.testing.assert_allclose(loose.fit_covariance, firm.covariance, rtol=1e-6)


@pytest.fixture(scope="module")
def url(tiny_maps: dict) -> Iterator[str]:
    port = free_port()
    proc = start_server(tiny_maps["keys"], port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


def test_a_server_and_a_local_bundle_reply_alike(tiny_maps: dict, drive, url: str) -> None:
    points = drive.scan(SCAN)
    prior = Prior.of_matrix(drive.true_poses[SCAN])
    with Localizer.load(tiny_maps["keys"]) as loc, LocalizeClient(url) as client:
        here, there = local_ask(loc), http_ask(client)
        for args in ((points,), (points, prior)):
            a, b = here(*args), there(*args)
            assert set(a.timings_ms) == set(b.timings_ms)
            untimed = [dataclasses.replace(r, timings_ms={}) for r in (a, b)]
            assert_same(*untimed)
        assert here(points, prior).mode == "prior" and there(points).mode == "search"


def test_a_server_gives_an_uncertain_registration_as_a_bundle_does(tiny_maps: dict, drive) -> None:
    """The same strict rule (PNVLAD_PRIOR_MAX_SIGMA 1 mm) on a real server and in this
    process: the unverified registration's pose and covariance reach the drive alike."""
    points = drive.scan(SCAN)
    prior = Prior.of_matrix(drive.true_poses[SCAN])
    port = free_port()
    proc = start_server(tiny_maps["keys"], port, env={"PNVLAD_PRIOR_MAX_SIGMA": "0.001"})
    strict = LocalizerConfig(prior=PriorSection(max_sigma=1e-3))
    try:
        with (
            Localizer.load(tiny_maps["keys"], config=strict) as loc,
            LocalizeClient(f"http://127.0.0.1:{port}") as client,
        ):
            a, b = local_ask(loc)(points, prior), http_ask(client)(points, prior)
    finally:
        stop_server(proc)
    assert a.uncertain and b.uncertain and a.pose is None and b.pose is None
    assert a.fit_pose is not None and a.fit_covariance is not None
    assert_same(*(dataclasses.replace(r, timings_ms={}) for r in (a, b)))
