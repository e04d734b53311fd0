"""A real ``pnvlad serve`` of a bundle that records its map as aligned registers a prior to the
nearest entries of any of the map's drives by default, and says so on /info; the settings
override it, and a bundle of the recorded tree keeps one drive at a time."""

from __future__ import annotations

import math

import httpx
import pytest

from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server


def _runs_near(url: str, drive, scans: range) -> list[int]:
    """How many of the map's drives each scan's prior registration used."""
    out = []
    for i in scans:
        true = drive.true_poses[i]
        prior = {"northing": float(true[1, 3]), "easting": float(true[0, 3]),
                 "yaw_deg": math.degrees(math.atan2(true[1, 0], true[0, 0]))}  # fmt: skip
        body = {"points": drive.scan(i).astype("<f4").tolist(), "preprocess": True,
                "prior": prior, "top_n": 30}  # fmt: skip
        r = httpx.post(f"{url}/localize", json=body, timeout=60)
        assert r.status_code == 200, r.text
        out.append(len({m["run"] for m in r.json()["matches"]}))
    return out


@pytest.fixture(scope="module")
def drive():
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    return simulated_drive(get_preset("tiny"), 0, 0, 3)  # the run the bundles leave out


@pytest.mark.parametrize("same_run", [None, "true"])
def test_the_server_follows_its_bundle_unless_told(
    tiny_aligned: dict, drive, same_run: str | None
) -> None:
    port = free_port()
    env = {} if same_run is None else {"PNVLAD_PRIOR_SAME_RUN": same_run}
    proc = start_server(tiny_aligned["keys"], port, env)
    try:
        url = f"http://127.0.0.1:{port}"
        info = httpx.get(f"{url}/info", timeout=30).json()
        runs = _runs_near(url, drive, range(4, 40, 8))
    finally:
        stop_server(proc)
    assert info["prior"]["aligned_map"] is True
    assert len(info["manifest"]["map"]["alignment"]) == 64
    if same_run is None:
        assert (info["prior"]["same_run"], info["prior"]["max_submaps"]) == (False, 8)
        assert info["prior"]["retry_submaps"] == 24
        assert max(runs) >= 2, runs
    else:
        assert info["prior"]["same_run"] is True and info["prior"]["max_submaps"] == 8
        assert set(runs) == {1}, runs


def test_a_recorded_maps_server_keeps_one_drive(keys_server: str, drive) -> None:
    info = httpx.get(f"{keys_server}/info", timeout=30).json()
    want = {"aligned_map": False, "same_run": True, "max_submaps": 4, "retry_submaps": 0,
            "min_fitness": 0.4, "max_sigma_m": 1.0}  # fmt: skip
    assert info["prior"] == want
    assert set(_runs_near(keys_server, drive, range(4, 40, 8))) == {1}
