"""Query and map kinds against a real `pnvlad serve` on 127.0.0.1: a map of keyframes (single
scans) answers raw scans and says so in every match, refuses accumulated windows naming
``kind``; a kind that disagrees with ``preprocess`` is refused naming the field that is wrong."""

from __future__ import annotations

from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.index.helpers import free_port
from tests.server.helpers import held_scan
from tests.server.test_app import start_server, stop_server

PROBLEM = "application/problem+json"


def test_a_keyframe_map_answers_a_raw_scan(keys_server: str, tiny_maps: dict) -> None:
    body = held_scan(tiny_maps).tobytes()
    ctype = {"content-type": "application/octet-stream"}
    for params in ({"kind": "scan"}, {"preprocess": "true"}):  # kind alone implies raw
        r = httpx.post(f"{keys_server}/localize", params=params, content=body, headers=ctype)
        assert r.status_code == 200, r.text
        doc = r.json()
        assert doc["query_kind"] == "scan" and doc["map_kind"] == "keyframe"
        assert doc["matches"] and all(m["kind"] == "keyframe" for m in doc["matches"])
        tree = tiny_maps["tree"]
        for m in doc["matches"]:  # each one a keyframe of its run
            stamps = tree.locations("business", m["run"], "keyframe").timestamp.tolist()
            assert m["timestamp"] in stamps
    info = httpx.get(f"{keys_server}/info").json()
    assert info["manifest"]["map"] == {"kind": "keyframe", "layout": "keyframe", "turns": 1}
    assert info["manifest"]["preprocess"]["max_range"] == 50.0


@pytest.mark.parametrize(
    ("params", "json_body", "field"),
    [
        ({"kind": "window"}, None, "kind"),  # a window against single scans
        ({"kind": "scan", "preprocess": "false"}, None, "preprocess"),
        ({"kind": "submap", "preprocess": "true"}, None, "preprocess"),
        ({"kind": "everything"}, None, "kind"),
        ({}, {"kind": "scan"}, "preprocess"),  # JSON: raw points say preprocess: true
        ({}, {"kind": "window", "preprocess": True}, "kind"),
        ({}, {"kind": 3, "preprocess": True}, "kind"),
    ],
)
def test_kinds_the_map_cannot_take_are_refused(
    keys_server: str, tiny_maps: dict, params: dict, json_body: dict | None, field: str
) -> None:
    pts = held_scan(tiny_maps)
    if json_body is None:
        r = httpx.post(
            f"{keys_server}/localize",
            params=params,
            content=pts.tobytes(),
            headers={"content-type": "application/octet-stream"},
        )
    else:
        doc = {"points": pts[:5000].astype(float).tolist(), **json_body}
        r = httpx.post(f"{keys_server}/localize", json=doc)
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith(PROBLEM)
    assert r.json()["field"] == field, r.text


def test_a_submap_map_takes_a_window(tiny_maps: dict, tmp_path: Path) -> None:
    """An accumulated window (raw metres) goes to a map of 20 m submaps, and the answer says
    what met."""
    from pnvlad_service.localization.query.localizer import Localizer

    with Localizer.load(tiny_maps["map"], tiny_maps["ckpt"]) as loc:
        answer = loc.localize(held_scan(tiny_maps), kind="window", top_n=3).to_json()
        assert answer["query_kind"] == "window" and answer["map_kind"] == "submap"
        assert [m["kind"] for m in answer["matches"]] == ["submap"] * 3
    with Localizer.load(tiny_maps["keys"], tiny_maps["ckpt"]) as loc:
        from pnvlad_service.errors import InputError

        with pytest.raises(InputError) as err:
            loc.localize(held_scan(tiny_maps), kind="window")
        assert err.value.source == "kind" and "keyframe" in err.value.detail


@pytest.mark.parametrize(
    ("name", "cloud", "field", "message"),
    [
        # Fewer than G's 16 points: refused before G, as the document's minimum says.
        ("too few points", np.random.default_rng(0).normal(0, 5, (12, 3)), "body",
         "between 16 and"),
        ("a plane and nothing else",
         np.c_[np.random.default_rng(1).uniform(-30, 30, (6000, 2)), np.zeros(6000)],
         "points", "ground removal"),
        ("NaN", np.r_[np.random.default_rng(2).normal(0, 5, (5000, 3)), [[np.nan, 0, 0]]],
         "body[5000]", "NaN or infinite"),
    ],
)  # fmt: skip
def test_a_scan_g_cannot_reduce_is_refused_naming_the_field(
    keys_server: str, name: str, cloud: np.ndarray, field: str, message: str
) -> None:
    r = httpx.post(
        f"{keys_server}/localize",
        params={"kind": "scan"},
        content=np.ascontiguousarray(cloud, dtype="<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 422, (name, r.text)
    problem = r.json()
    assert problem["field"] == field and message in problem["detail"], (name, problem)
    # The server is unharmed: the next good scan is answered.
    assert httpx.get(f"{keys_server}/readyz").status_code == 200


def test_a_window_is_laid_as_the_served_maps_windows_were(tiny_maps: dict) -> None:
    """The client's accumulator keeps the map's points a scan, as the serving bundle's manifest
    says from the tree's prepare record (windows of whole scans missed their place: #34)."""
    import json

    from pnvlad_service.client import LocalizeClient

    tree = tiny_maps["tree"].root
    run = next(p for p in (tree / "business").iterdir() if p.is_dir())
    record = json.loads((run / ".prepare-pointcloud_20m.json").read_text())
    port = free_port()
    proc = start_server(tiny_maps["map"], port)
    try:
        with LocalizeClient(f"http://127.0.0.1:{port}") as client:
            acc = client.window_accumulator(20.0)
            assert acc.max_points_per_scan == record["max_points_per_scan"] == 3000
            assert acc.min_spacing_m == record["min_scan_spacing_m"]
            assert acc.window_m == 20.0 and acc.frame == "sensor"
            scan = held_scan(tiny_maps)
            acc.add(scan, np.eye(4))
            assert len(acc.cloud()) == 3000 < len(scan)
            answer = client.localize_window(acc, top_n=2)
            assert answer["query_kind"] == "window" and len(answer["matches"]) == 2
    finally:
        stop_server(proc)
