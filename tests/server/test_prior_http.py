"""A prior pose over HTTP against a real `pnvlad serve` on 127.0.0.1 (the tiny city's keyframe
map): JSON, binary and the client give one answer; the OpenAPI document states the fields and
their bounds; a prior off the map is a 200 that says so; every bad prior is a 422 problem+json
naming its field, never a 5xx; a drive followed through the server survives scans out of time
order and odometry that jumps."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator

import httpx
import numpy as np
import pytest

from pnvlad_service.client import LocalizeClient, ServerRefused
from pnvlad_service.localization.drive.service import http_ask
from pnvlad_service.localization.drive.tracking import SEARCHING, DriveLocalizer, DriveScan
from pnvlad_service.localization.verify.prior import Prior
from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server

PROBLEM = "application/problem+json"
OCTET = {"content-type": "application/octet-stream"}


@pytest.fixture(scope="module")
def drive():
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    return simulated_drive(get_preset("tiny"), 0, 0, 3)  # tiny_maps' held-out run


@pytest.fixture(scope="module")
def server(tiny_maps: dict) -> Iterator[str]:
    port = free_port()
    proc = start_server(tiny_maps["keys"], port, {"PNVLAD_MAX_PRIOR_RADIUS": "60"})
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


def prior_of(pose: np.ndarray, **kw) -> dict:
    doc = {
        "northing": float(pose[1, 3]) + 0.7,
        "easting": float(pose[0, 3]) - 0.5,
        "yaw_deg": math.degrees(math.atan2(pose[1, 0], pose[0, 0])) + 1.5,
    }
    return {**doc, **kw}


def test_json_binary_and_the_client_give_one_answer(server: str, drive) -> None:
    scan = drive.scan(8).astype("<f4")
    prior = prior_of(drive.true_poses[8])
    body = {"points": scan.tolist(), "preprocess": True, "prior": prior, "top_n": 3}
    r = httpx.post(f"{server}/localize", json=body, timeout=60)
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["mode"] == "prior" and doc["query_kind"] == "scan" and doc["map_kind"] == "keyframe"
    assert len(doc["matches"]) <= 3 and all(m["kind"] == "keyframe" for m in doc["matches"])
    assert doc["prior"]["radius_m"] == 20.0 and doc["prior"]["northing"] == prior["northing"]
    assert doc["timings_ms"]["embed"] == 0.0 and doc["batch_size"] == 1
    if doc["verified"]:
        assert len(doc["pose"]["covariance"]) == 6 and doc["pose"]["sigma_m"] <= 1.0
    params = {f"prior_{k}": v for k, v in prior.items()} | {"kind": "scan", "top_n": 3}
    b = httpx.post(f"{server}/localize", params=params, content=scan.tobytes(), headers=OCTET)
    assert b.status_code == 200, b.text
    with LocalizeClient(server) as client:
        c = client.localize(scan, 3, prior=Prior(**prior))
    for other in (b.json(), c):  # the same, but for rounding in the last bits
        assert other["matches"] == doc["matches"] and other["verified"] == doc["verified"]
        for key, value in doc["prior"].items():
            assert other["prior"][key] == (value if value is None or isinstance(value, str)
                                           else pytest.approx(value, rel=1e-9))  # fmt: skip
        if doc["pose"]:
            t = np.array(doc["pose"]["transform"])
            np.testing.assert_allclose(np.array(other["pose"]["transform"]), t, atol=1e-9)
    # The run of the map asked for is the one registered to (each has entries there).
    info = httpx.get(f"{server}/info").json()
    for run in next(e["runs"] for e in info["manifest"]["indexed"]):
        asked = {**body, "prior": {**prior, "run": f"business/{run}"}}
        d = httpx.post(f"{server}/localize", json=asked, timeout=60).json()
        assert {m["run"] for m in d["matches"]} == {run}
    assert info["limits"]["max_prior_radius_m"] == 60.0
    assert info["limits"]["default_prior_radius_m"] == 20.0


def test_the_openapi_document_states_the_prior(server: str) -> None:
    spec = httpx.get(f"{server}/openapi.json").json()
    op = spec["paths"]["/localize"]["post"]
    pre, raw = op["requestBody"]["content"]["application/json"]["schema"]["oneOf"]
    assert pre["properties"]["prior"]["type"] == "null" and "prior" in raw["properties"]
    prior = raw["properties"]["prior"]["anyOf"][0]
    assert prior["required"] == ["northing", "easting", "yaw_deg"]
    radius = prior["properties"]["radius_m"]["anyOf"][0]
    assert radius["exclusiveMinimum"] == 0.0 and radius["maximum"] == 60.0
    params = {p["name"]: p for p in op["parameters"]}
    for name in ("prior_northing", "prior_easting", "prior_yaw_deg", "prior_height",
                 "prior_radius_m", "prior_run"):  # fmt: skip
        assert name in params and params[name]["in"] == "query"
    assert params["prior_radius_m"]["schema"]["anyOf"][0]["maximum"] == 60.0
    answer = spec["components"]["schemas"]["LocalizeResponse"]["properties"]
    assert {"mode", "prior"} <= set(answer)
    assert "covariance" in spec["components"]["schemas"]["PoseOut"]["properties"]


def test_a_prior_off_the_map_is_answered_not_refused(server: str, drive) -> None:
    far = prior_of(drive.true_poses[8], northing=float(drive.true_poses[8][1, 3]) + 5000.0)
    r = httpx.post(f"{server}/localize", json={"points": drive.scan(8).tolist(),
                   "preprocess": True, "prior": far}, timeout=60)  # fmt: skip
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["verified"] is False and doc["pose"] is None and doc["matches"] == []
    assert doc["verification"]["reason"].startswith("no map within 20 m of the prior")


BAD_JSON = [
    ({"radius_m": 0}, "prior.radius_m"),
    ({"radius_m": 61}, "prior.radius_m"),
    ({"radius_m": "5"}, "prior.radius_m"),
    ({"northing": None}, "prior.northing"),
    ({"yaw_deg": 720.0}, "prior.yaw_deg"),
    ({"height": 1e9}, "prior.height"),
    ({"run": ""}, "prior.run"),
    ({"run": "x" * 300}, "prior.run"),
    ({"heading": 3.0}, "prior.heading"),
]


@pytest.mark.parametrize(("change", "field"), BAD_JSON, ids=[f for _, f in BAD_JSON])
def test_a_bad_json_prior_is_a_422_naming_its_field(server: str, drive, change, field) -> None:
    prior = {k: v for k, v in {**prior_of(drive.true_poses[3]), **change}.items() if v is not None}
    body = {"points": drive.scan(3)[:500].tolist(), "preprocess": True, "prior": prior}
    r = httpx.post(f"{server}/localize", json=body, timeout=60)
    assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
    assert r.json()["field"] == field, r.json()


def test_bad_priors_in_query_parameters_and_combinations(server: str, tiny_maps, drive) -> None:
    scan = drive.scan(3).astype("<f4")
    good = {f"prior_{k}": v for k, v in prior_of(drive.true_poses[3]).items()} | {"kind": "scan"}
    cases = [
        ({**good, "prior_radius_m": "0"}, "prior_radius_m"),
        ({**good, "prior_radius_m": "nan"}, "prior_radius_m"),
        ({**good, "prior_radius_m": "1e3"}, "prior_radius_m"),
        ({**good, "prior_northing": "north"}, "prior_northing"),
        ({k: v for k, v in good.items() if k != "prior_easting"}, "prior_easting"),
        ({**good, "kind": "submap"}, "prior_northing"),  # a prior with a preprocessed submap
        ({**good, "verify": "false"}, "verify"),
    ]
    for params, field in cases:
        r = httpx.post(f"{server}/localize", params=params, content=scan.tobytes(), headers=OCTET)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, (params, r.text)
        assert r.json()["field"] == field, (params, r.json())
    body = {"points": np.zeros((4096, 3)).tolist(), "prior": prior_of(drive.true_poses[3])}
    r = httpx.post(f"{server}/localize", json=body)
    assert r.status_code == 422 and r.json()["field"] == "prior"
    body = {"points": scan[:800].tolist(), "preprocess": True, "verify": False,
            "prior": prior_of(drive.true_poses[3])}  # fmt: skip
    r = httpx.post(f"{server}/localize", json=body)
    assert r.status_code == 422 and r.json()["field"] == "verify"
    with LocalizeClient(server) as client, pytest.raises(ServerRefused) as err:
        client.localize(scan, prior={**prior_of(drive.true_poses[3]), "radius_m": 500.0})
    assert err.value.status == 422 and "prior_radius_m" in str(err.value)


def test_a_bundle_without_geometry_refuses_a_prior(tiny_maps, drive) -> None:
    port = free_port()
    proc = start_server(tiny_maps["plain"], port)
    try:
        body = {"points": drive.scan(3)[:800].tolist(), "preprocess": True,
                "prior": prior_of(drive.true_poses[3])}  # fmt: skip
        r = httpx.post(f"http://127.0.0.1:{port}/localize", content=json.dumps(body),
                       headers={"content-type": "application/json"}, timeout=60)  # fmt: skip
    finally:
        stop_server(proc)
    assert r.status_code == 422 and r.json()["field"] == "prior"
    assert "no geometry" in r.json()["detail"]


def test_a_drive_followed_through_the_server_survives_bad_input(server: str, drive) -> None:
    """From the first scan's true pose: tracked; then a scan out of time order, then odometry
    that jumps 500 m: each sends it back to searching with a line, and nothing raises."""
    stamps, odo = drive.timestamps, drive.poses
    with LocalizeClient(server) as client:
        loc = DriveLocalizer(http_ask(client), initial_pose=drive.true_poses[0])
        steps = [loc.step(DriveScan(i, int(stamps[i]), drive.scan(i), odo[i])) for i in range(6)]
        assert sum(s.verified for s in steps) >= 3, [s.reason for s in steps]
        back = loc.step(DriveScan(6, int(stamps[2]), drive.scan(6), odo[6]))
        assert back.state == SEARCHING and "out of time order" in back.reason
        jump = np.eye(4)
        jump[0, 3] = 500.0
        late = loc.step(DriveScan(7, int(stamps[7]), drive.scan(7), jump @ odo[7]))
        assert late.event == "reset" and late.reason.startswith("odometry jumped")
        assert late.reply is not None and late.reply.mode == "search"
