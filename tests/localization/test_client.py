"""LocalizeClient against a real `pnvlad serve` on 127.0.0.1 with an API key: its answers are
the library's, its errors carry the problem's status and detail, it keeps one connection and
reopens it when the server closed it, and an unreachable server is one clear error."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.client import LocalizeClient, ServerError, ServerRefused
from pnvlad_service.errors import InputError, PnvladError
from pnvlad_service.index import build as ix
from pnvlad_service.index.manifest import Manifest
from pnvlad_service.localization.query.localizer import Localizer
from tests.index.helpers import PER_RUN, free_port, read_cloud
from tests.server.test_app import start_server, stop_server

KEY = "k3y-for-tests"


@pytest.fixture(scope="module")
def url(world: dict[str, Path]) -> Iterator[str]:
    port = free_port()
    proc = start_server(world["bundle"], port, env={"PNVLAD_API_KEY": KEY})
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


@pytest.fixture(scope="module")
def client(url: str) -> Iterator[LocalizeClient]:
    with LocalizeClient(url, api_key=KEY, timeout=60) as c:
        yield c


def cloud(world: dict[str, Path], i: int) -> np.ndarray:
    return read_cloud(world["tree"], ix.list_database_submaps(world["tree"])[i].path)


def test_answers_equal_the_librarys(world, client) -> None:
    with Localizer.load(world["bundle"]) as loc:
        for i, dtype in ((2, np.float64), (PER_RUN + 5, np.float32)):
            pts = cloud(world, i).astype(dtype)
            got = client.localize(pts, top_n=4)
            want = loc.localize(pts, top_n=4)
            assert [m["submap_id"] for m in got["matches"]] == [m.submap_id for m in want.matches]
            np.testing.assert_allclose(
                [m["distance"] for m in got["matches"]],
                [m.distance for m in want.matches],
                atol=1e-5,
            )
            assert got["model"] == loc.info.to_json()["model"]
            assert got["index"] == loc.info.to_json()["index"]


def test_ready_and_info(world, url, client) -> None:
    assert client.ready()
    info = client.info()
    assert info["limits"]["points_per_cloud"] == 4096
    assert info["manifest"] == Manifest.read(world["bundle"]).to_json()
    # /readyz is open to all; /info needs the key.
    with LocalizeClient(url) as anonymous:
        assert anonymous.ready()
        with pytest.raises(ServerRefused) as err:
            anonymous.info()
    assert err.value.status == 401 and "Bearer" in str(err.value)


def test_refused_requests_carry_the_problem(world, client) -> None:
    with pytest.raises(ServerRefused) as err:
        client.localize(cloud(world, 0), top_n=0)
    e = err.value
    assert isinstance(e, InputError) and e.status == 422 and e.source == client.url
    assert e.problem["field"] == "top_n" and e.problem["detail"] in str(e)
    assert str(e).startswith(f"{client.url}: server answered 422: top_n")
    with pytest.raises(ServerRefused, match="preprocess") as err:
        client.localize(np.random.default_rng(0).uniform(-30, 30, (1000, 3)))  # raw, no flag
    assert err.value.problem["field"] == "body"


def test_a_connection_closed_by_the_server_is_reopened(world, client) -> None:
    pts = cloud(world, 3)
    first = client.localize(pts, top_n=1)["matches"]
    kept = client._conn
    assert client.localize(pts, top_n=1)["matches"] == first and client._conn is kept
    time.sleep(5.5)  # past uvicorn's keep-alive (5 s): the server closes the idle connection
    assert client.localize(pts, top_n=1)["matches"] == first
    assert client._conn is not kept  # reopened once, transparently


def test_an_unreachable_server_is_one_clear_error() -> None:
    with LocalizeClient(f"http://127.0.0.1:{free_port()}", timeout=5) as c:
        assert not c.ready()
        with pytest.raises(ServerError, match="cannot reach the server") as err:
            c.localize(np.zeros((4096, 3), np.float32))
    assert isinstance(err.value, PnvladError) and err.value.status is None
    with pytest.raises(InputError, match="http"):
        LocalizeClient("127.0.0.1:8000")
