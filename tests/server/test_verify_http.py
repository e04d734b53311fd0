"""Verification over HTTP against a real ``pnvlad serve``: a bundle with geometry answers
verified with a pose; asking it of a bundle without geometry is a 422 naming ``verify``; a
degenerate cloud answers ``verified: false``, never a 5xx."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_service.io.submap import read_submap
from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server


@pytest.fixture(scope="module")
def bundles(tiny_maps: dict) -> dict:
    tree, run = tiny_maps["tree"], tiny_maps["query_run"]
    sub = tree.submaps("business", run, "test")[2]
    frame = tree.frames("business", run, "test")[2]
    return {"base": tiny_maps["base"], "query": read_submap(tree.root / sub.path), "frame": frame}


def _serve(bundle: Path, env: dict[str, str] | None = None) -> Iterator[str]:
    port = free_port()
    proc = start_server(bundle, port, env)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


@pytest.fixture(scope="module")
def geo(bundles: dict) -> Iterator[str]:
    # Every database submap a candidate (the model is random): the true one is among them.
    env = {"PNVLAD_RERANK": "26", "PNVLAD_VERIFY_THRESHOLD": "0.25"}
    yield from _serve(bundles["base"] / "map.index", env)


@pytest.fixture(scope="module")
def plain(bundles: dict) -> Iterator[str]:
    yield from _serve(bundles["base"] / "plain.index")


def _json(points: np.ndarray, **kw: object) -> bytes:
    return json.dumps({"points": points.tolist(), **kw}).encode()


def test_a_verified_answer_with_scores_and_a_pose(geo: str, bundles: dict) -> None:
    body = _json(bundles["query"], top_n=3, scale=bundles["frame"].scale)
    r = httpx.post(f"{geo}/localize", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["verified"] is True, doc["verification"]
    v = doc["verification"]
    assert v["candidates"] == 26 and 1 <= v["registered"] <= 26
    assert v["threshold"] == 0.25 <= v["confidence"] <= v["best_score"]
    ms = doc["matches"]
    # The cascade's unregistered candidates have no score; the registered ones come first.
    assert [m["score"] is not None for m in ms] == sorted(
        [m["score"] is not None for m in ms], reverse=True
    )
    assert [m["rank"] for m in ms] == [1, 2, 3]
    assert ms[0]["score"] == doc["verification"]["best_score"] >= ms[1]["score"]
    pose = doc["pose"]
    assert pose["scale"] == "measured" and pose["frame"] == "centroid"
    assert 0.0 < pose["constraint"] <= 1.0
    t = np.array(pose["transform"])
    assert t.shape == (4, 4) and np.allclose(t[3], [0, 0, 0, 1])
    assert pose["northing"] == t[1, 3] and pose["easting"] == t[0, 3]
    # The query's centroid sits in the map where the query run's own map says, within the
    # two runs' GNSS/INS errors (1.5 m std each in the simulator).
    f = bundles["frame"]
    there = f.origin + f.centre
    assert np.hypot(pose["easting"] - there[0], pose["northing"] - there[1]) < 8.0
    assert doc["timings_ms"]["verify"] > 0
    # Binary body, scale as a query parameter: the same answer.
    q = {"top_n": 3, "scale": f.scale}
    r2 = httpx.post(
        f"{geo}/localize",
        params=q,
        content=bundles["query"].astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r2.status_code == 200 and r2.json()["matches"] == ms
    # verify=false: the descriptor order, no scores.
    r3 = httpx.post(
        f"{geo}/localize",
        content=_json(bundles["query"], top_n=3, verify=False),
        headers={"content-type": "application/json"},
    )
    assert r3.json()["verified"] is None and all(m["score"] is None for m in r3.json()["matches"])
    d = [m["distance"] for m in r3.json()["matches"]]
    assert d == sorted(d)


def test_batch_verifies_each_query(geo: str, bundles: dict) -> None:
    rng = np.random.default_rng(1)
    plane = np.c_[rng.uniform(-1, 1, (4096, 2)), np.zeros(4096)]
    body = json.dumps(
        {
            "queries": [
                {"points": bundles["query"].tolist(), "scale": bundles["frame"].scale},
                {"points": plane.tolist()},
            ],
            "top_n": 2,
        }
    ).encode()
    r = httpx.post(
        f"{geo}/localize/batch",
        content=body,
        headers={"content-type": "application/json"},
        timeout=60,
    )
    assert r.status_code == 200, r.text
    first, second = r.json()["results"]
    assert first["verified"] is True and first["pose"] is not None
    assert second["verified"] is False and "plane" in second["verification"]["reason"]


def test_degenerate_clouds_answer_not_verified(geo: str) -> None:
    rng = np.random.default_rng(0)
    line = np.c_[np.linspace(-1, 1, 4096), np.zeros((4096, 2))]
    blob = rng.uniform([4.0, -0.5, 1.0], [5.0, 0.5, 2.0], (80, 3))  # nearly empty after G
    for body in (_json(line), _json(blob, preprocess=True)):
        r = httpx.post(
            f"{geo}/localize", content=body, headers={"content-type": "application/json"}
        )
        assert r.status_code == 200, r.text
        assert r.json()["verified"] is False and r.json()["pose"] is None
        assert r.json()["verification"]["reason"]


def test_verify_asked_of_a_bundle_without_geometry_is_a_422(plain: str, bundles: dict) -> None:
    h = {"content-type": "application/json"}
    r = httpx.post(f"{plain}/localize", content=_json(bundles["query"], verify=True), headers=h)
    assert r.status_code == 422 and r.json()["field"] == "verify", r.text
    assert "no geometry" in r.json()["detail"]
    r = httpx.post(
        f"{plain}/localize",
        params={"verify": "true"},
        headers={"content-type": "application/octet-stream"},
        content=bundles["query"].astype("<f4").tobytes(),
    )
    assert r.status_code == 422 and r.json()["field"] == "verify"
    body = json.dumps({"queries": [{"points": bundles["query"].tolist()}], "verify": True})
    r = httpx.post(f"{plain}/localize/batch", content=body.encode(), headers=h)
    assert r.status_code == 422 and r.json()["field"] == "verify"
    # The default is off there: a plain answer.
    r = httpx.post(f"{plain}/localize", content=_json(bundles["query"]), headers=h)
    assert r.status_code == 200 and r.json()["verified"] is None
    # The CLI: exit 2 naming the field.
    from pnvlad_cli.main import app

    path = bundles["base"] / "q.npy"
    np.save(path, bundles["query"])
    res = CliRunner().invoke(app, ["localize", str(path), "--url", plain, "--verify"])
    assert res.exit_code == 2 and "verify" in res.output, res.output


@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ({"scale": -1.0}, "scale"),
        ({"scale": "big"}, "scale"),
        ({"verify": "yes"}, "verify"),
        ({"preprocess": True, "scale": 10.0}, "scale"),
    ],
)
def test_bad_verify_fields_name_themselves(
    geo: str, bundles: dict, extra: dict, field: str
) -> None:
    pts = bundles["query"] * (30.0 if extra.get("preprocess") else 1.0)
    r = httpx.post(
        f"{geo}/localize", content=_json(pts, **extra), headers={"content-type": "application/json"}
    )
    assert r.status_code == 422 and r.json()["field"] == field, r.text


def test_the_server_takes_the_models_calibrated_threshold(bundles: dict, tmp_path) -> None:
    """A model directory with verification.json for its weights sets the server's threshold
    (no PNVLAD_VERIFY_THRESHOLD); a malformed record stops the start, naming the file."""
    import shutil

    from pnvlad_service.localization.query.calibration import Calibration, write_calibration
    from pnvlad_service.models.store import weights_sha256

    model = tmp_path / "model"
    shutil.copytree(bundles["base"] / "ckpt", model)
    record = Calibration(0.33, weights_sha256(model), 26, 99.5, 40, {"precision": 99.7})
    path = write_calibration(model, record)
    env = {"PNVLAD_RERANK": "26", "PNVLAD_CHECKPOINT": str(model)}
    served = _serve(bundles["base"] / "map.index", env)
    url = next(served)
    try:
        body = _json(bundles["query"], top_n=1, scale=bundles["frame"].scale)
        r = httpx.post(
            f"{url}/localize", content=body, headers={"content-type": "application/json"}
        )
        assert r.status_code == 200, r.text
        assert r.json()["verification"]["threshold"] == 0.33
    finally:
        served.close()
    path.write_text('{"format": "pnvlad-verification", "version": 1}')
    with pytest.raises(RuntimeError, match=r"verification\.json"):
        next(_serve(bundles["base"] / "map.index", env))
