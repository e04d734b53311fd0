"""The map's UTM zone through a real `pnvlad serve` on 127.0.0.1: ``GET /info`` says it (null
for a map built without one), every match carries the same, and the OpenAPI schema documents
the field."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from pnvlad_service.index.build import build_bundle
from pnvlad_service.index.bundle import IndexBundle
from tests.index.helpers import free_port, make_checkpoint, read_cloud
from tests.index.test_utm_zone import _prepare
from tests.server.test_app import start_server, stop_server


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("zone_http")
    ckpt = make_checkpoint(base / "ckpt")
    out = {}
    for name, zone in (("zoned", " 17 South"), ("plain", "")):
        tree = base / name
        _prepare(tree, "a", zone)
        out[name] = build_bundle(base / f"{name}.index", ckpt, tree, progress=False).path
        out[f"{name}_tree"] = tree
    return out


@pytest.mark.parametrize(("name", "zone"), [("zoned", "17 south"), ("plain", None)])
def test_info_and_answers_carry_the_zone(maps: dict[str, Path], name: str, zone: str | None):
    port = free_port()
    proc = start_server(maps[name], port)
    try:
        url = f"http://127.0.0.1:{port}"
        info = httpx.get(f"{url}/info").json()
        assert info["utm_zone"] == zone
        bundle = IndexBundle.load(maps[name])
        points = read_cloud(maps[f"{name}_tree"], str(bundle.metadata.path[0]))
        r = httpx.post(f"{url}/localize", json={"points": points.tolist(), "top_n": 3})
        assert r.status_code == 200, r.text
        zones = [m["utm_zone"] for m in r.json()["matches"]]
        assert zones and zones == [zone] * len(zones)
        schema = httpx.get(f"{url}/openapi.json").json()["components"]["schemas"]["Info"]
        assert "UTM zone" in schema["properties"]["utm_zone"]["description"]
    finally:
        stop_server(proc)
