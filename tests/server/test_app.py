"""The HTTP service against a real `pnvlad serve` process on 127.0.0.1 (started once per module)
and, where handier, in-process with `with TestClient(app)`: answers equal a local search,
every bad input is a problem+json naming the field, bounded bodies, a client that disconnects
mid-body, concurrency, metrics, authentication, a restart and the weights check at start-up.
"""

from __future__ import annotations

import io
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from pnvlad_service.index import build as ix
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.models.runtimes import load_encoder
from tests.index.helpers import PER_RUN, free_port, make_checkpoint, make_world, read_cloud

MAX_BODY = 4 * 1024 * 1024
PROBLEM = "application/problem+json"


def start_server(
    bundle: Path, port: int, env: dict[str, str] | None = None, args: tuple[str, ...] = ()
) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-m",
        "pnvlad_cli.main",
        "-q",
        "serve",
        "--index",
        str(bundle),
        "--port",
        str(port),
        "--log-level",
        "warning",
        *args,
    ]
    full_env = {**os.environ, "PNVLAD_MAX_BODY_BYTES": str(MAX_BODY), **(env or {})}
    proc = subprocess.Popen(cmd, env=full_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited: {proc.stdout.read().decode()[-3000:]}")  # type: ignore[union-attr]
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    proc.kill()
    raise RuntimeError("server did not become ready in 90 s")


def stop_server(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_world(tmp_path_factory.mktemp("server"))


@pytest.fixture(scope="module")
def server(world: dict[str, Path]) -> Iterator[str]:
    port = free_port()
    proc = start_server(world["bundle"], port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


@pytest.fixture(scope="module")
def client(server: str) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server, timeout=60) as c:
        yield c


@pytest.fixture(scope="module")
def local(world: dict[str, Path]):
    """(encoder, bundle) in this process, for expected answers."""
    return load_encoder(world["ckpt"]), IndexBundle.load(world["bundle"])


def cloud(world: dict[str, Path], i: int) -> np.ndarray:
    records = ix.list_database_submaps(world["tree"])
    return read_cloud(world["tree"], records[i].path)


def expected_ids(local, points: np.ndarray, k: int) -> tuple[list[int], np.ndarray]:
    enc, bundle = local
    d, ids = bundle.search(enc.embed(points.astype(np.float32)[None]), k)
    return ids[0].tolist(), d[0]


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


# -- answers -------------------------------------------------------------------------------


def test_json_query_matches_a_local_search(world, client, local) -> None:
    pts = cloud(world, PER_RUN + 3)  # run 2's fourth submap
    r = client.post("/localize", json={"points": pts.tolist(), "top_n": 5})
    assert r.status_code == 200, r.text
    body = r.json()
    ids, dists = expected_ids(local, pts, 5)
    meta = local[1].metadata
    assert [m["submap_id"] for m in body["matches"]] == [str(meta.submap_id[i]) for i in ids]
    assert [m["rank"] for m in body["matches"]] == [1, 2, 3, 4, 5]
    np.testing.assert_allclose([m["distance"] for m in body["matches"]], dists, atol=1e-5)
    first = body["matches"][0]
    assert first["submap_id"].endswith(str(meta.timestamp[PER_RUN + 3]))
    assert first["northing"] == meta.northing[PER_RUN + 3]
    assert first["easting"] == meta.easting[PER_RUN + 3]
    assert first["distance"] == pytest.approx(0.0, abs=1e-5)
    manifest = local[1].manifest
    assert body["model"]["weights_sha256"] == manifest.model.weights_sha256
    assert body["index"] == {"id": local[1].bundle_id, "key": "Flat", "count": 2 * PER_RUN}
    t = body["timings_ms"]
    assert set(t) >= {"parse", "preprocess", "queue", "embed", "search", "total"}
    assert t["total"] >= t["embed"] > 0


def test_binary_bodies_agree_with_json(world, client) -> None:
    pts = cloud(world, 7)
    ref = client.post("/localize", json={"points": pts.tolist(), "top_n": 3}).json()["matches"]
    f32 = client.post(
        "/localize?top_n=3",
        content=pts.astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    f64 = client.post(
        "/localize?top_n=3",
        content=pts.astype("<f8").tobytes(),
        headers={"content-type": "application/octet-stream", "x-points-dtype": "float64"},
    )
    npy = client.post(
        "/localize?top_n=3", content=npy_bytes(pts), headers={"content-type": "application/x-npy"}
    )
    for r in (f32, f64, npy):
        assert r.status_code == 200, r.text
        assert [m["submap_id"] for m in r.json()["matches"]] == [m["submap_id"] for m in ref]


def test_batch_equals_single_queries(world, client) -> None:
    clouds = [cloud(world, i) for i in (0, 9, PER_RUN + 1)]
    singles = [
        [
            m["submap_id"]
            for m in client.post("/localize", json={"points": c.tolist()}).json()["matches"]
        ]
        for c in clouds
    ]
    r = client.post(
        "/localize/batch", json={"queries": [{"points": c.tolist()} for c in clouds], "top_n": 5}
    )
    assert r.status_code == 200, r.text
    assert [[m["submap_id"] for m in res["matches"]] for res in r.json()["results"]] == singles
    assert all(res["batch_size"] >= 3 for res in r.json()["results"])  # embedded together
    r = client.post(
        "/localize/batch?top_n=5",
        content=npy_bytes(np.stack(clouds)),
        headers={"content-type": "application/x-npy"},
    )
    assert r.status_code == 200, r.text
    assert [[m["submap_id"] for m in res["matches"]] for res in r.json()["results"]] == singles


# -- bad input -----------------------------------------------------------------------------

GOOD = np.zeros((4096, 3)).tolist()


def _with(**kw) -> bytes:
    return json.dumps({"points": GOOD, **kw}).encode()


def _nan_body() -> bytes:
    pts = [list(p) for p in GOOD]
    pts[17][1] = float("nan")
    return json.dumps({"points": pts}).encode()  # Python writes NaN, as many clients do


def _inf_body() -> bytes:
    return json.dumps({"points": GOOD}).encode().replace(b"0.0]", b"Infinity]", 1)


BAD = [
    # (name, path, content type, body, status, field)
    ("not json", "/localize", "application/json", b'{"points": [[1, 2', 400, "body"),
    ("not an object", "/localize", "application/json", b"[1, 2, 3]", 422, "body"),
    ("no points", "/localize", "application/json", b'{"top_n": 3}', 422, "points"),
    ("unknown field", "/localize", "application/json", _with(topn=3), 422, "body"),
    ("2-d points", "/localize", "application/json", b'{"points": [[1, 2]]}', 422, "points[0]"),
    ("strings", "/localize", "application/json", b'{"points": [[1, 2, "a"]]}', 422, "points[0]"),
    ("points not list", "/localize", "application/json", b'{"points": 3}', 422, "points"),
    ("empty points", "/localize", "application/json", b'{"points": []}', 422, "points"),
    ("wrong count", "/localize", "application/json", b'{"points": [[0, 0, 0]]}', 422, "points"),
    ("NaN", "/localize", "application/json", _nan_body(), 422, "points[17]"),
    ("Infinity", "/localize", "application/json", _inf_body(), 422, "points[0]"),
    (
        "outside [-1, 1]",
        "/localize",
        "application/json",
        json.dumps({"points": [[5.0, 0, 0]] * 4096}).encode(),
        422,
        "points[0]",
    ),
    (
        "huge number",
        "/localize",
        "application/json",
        b'{"points": [[1e999, 0, 0]]}',
        422,
        "points[0]",
    ),
    (
        "raw too far",
        "/localize",
        "application/json",
        json.dumps({"points": [[0, 0, 0]] * 20 + [[1e308, 0, 0]], "preprocess": True}).encode(),
        422,
        "points[20]",
    ),
    ("top_n 0", "/localize", "application/json", _with(top_n=0), 422, "top_n"),
    ("top_n too big", "/localize", "application/json", _with(top_n=101), 422, "top_n"),
    ("top_n float", "/localize", "application/json", _with(top_n=2.5), 422, "top_n"),
    ("top_n bool", "/localize", "application/json", _with(top_n=True), 422, "top_n"),
    ("preprocess str", "/localize", "application/json", _with(preprocess="yes"), 422, "preprocess"),
    ("text/plain", "/localize", "text/plain", b"hello", 415, "Content-Type"),
    ("no content type", "/localize", "", b"hello", 415, "Content-Type"),
    ("odd byte count", "/localize", "application/octet-stream", b"\0" * 13, 422, "body"),
    ("empty binary", "/localize", "application/octet-stream", b"", 422, "body"),
    ("binary count", "/localize", "application/octet-stream", b"\0" * 12 * 10, 422, "body"),
    ("npy garbage", "/localize", "application/x-npy", b"\x93NUMPYgarbage", 422, "body"),
    (
        "npy pickle",
        "/localize",
        "application/x-npy",
        b"\x93NUMPY\x01\x00v\x00{'descr': '|O', 'fortran_order': False, 'shape': (1,), }"
        + b" " * 47
        + b"\n"
        + b"\x80\x04N.",
        422,
        "body",
    ),
    (
        "npy ints",
        "/localize",
        "application/x-npy",
        npy_bytes(np.zeros((4096, 3), int)),
        422,
        "body",
    ),
    ("npy shape", "/localize", "application/x-npy", npy_bytes(np.zeros((4096, 4))), 422, "body"),
    ("batch empty", "/localize/batch", "application/json", b'{"queries": []}', 422, "queries"),
    (
        "batch bad item",
        "/localize/batch",
        "application/json",
        json.dumps({"queries": [{"points": GOOD}, {"points": [[0, 0]]}]}).encode(),
        422,
        "queries[1].points[0]",
    ),
    (
        "batch too many",
        "/localize/batch",
        "application/json",
        json.dumps({"queries": [{"points": [[0, 0, 0]]}] * 65}).encode(),
        422,
        "queries",
    ),
    ("batch octet", "/localize/batch", "application/octet-stream", b"\0" * 12, 415, "Content-Type"),
]


@pytest.mark.parametrize(
    ("name", "path", "ctype", "body", "status", "field"), BAD, ids=[b[0] for b in BAD]
)
def test_bad_input_is_a_problem_naming_the_field(client, name, path, ctype, body, status, field):
    headers = {"content-type": ctype} if ctype else {}
    r = client.post(path, content=body, headers=headers)
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM
    p = r.json()
    assert p["status"] == status and p["type"].startswith("urn:pnvlad:problem:")
    assert p["field"] == field and p["detail"] and p["title"]


def test_bad_query_parameters(client) -> None:
    body = np.zeros((4096, 3), "<f4").tobytes()
    for query, field in (("top_n=0", "top_n"), ("top_n=x", "top_n"), ("dtype=int8", "dtype")):
        r = client.post(
            f"/localize?{query}", content=body, headers={"content-type": "application/octet-stream"}
        )
        assert r.status_code == 422 and r.json()["field"] == field, r.text
    r = client.post(
        "/localize",
        content=body,
        headers={"content-type": "application/octet-stream", "x-points-dtype": "i2"},
    )
    assert r.status_code == 422 and r.json()["field"] == "dtype"


def test_unknown_route_and_method_are_problems(client) -> None:
    assert client.get("/nope").headers["content-type"] == PROBLEM
    r = client.get("/localize")
    assert r.status_code == 405 and r.headers["content-type"] == PROBLEM


# -- body limit and disconnects ------------------------------------------------------------


def _raw_request(server: str, head: bytes, body_chunks: list[bytes], read: bool = True) -> bytes:
    host, port = server.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as s:
        s.sendall(head)
        for chunk in body_chunks:
            try:
                s.sendall(chunk)
            except (BrokenPipeError, ConnectionResetError):
                break
        if not read:
            return b""
        data = b""
        try:
            while chunk := s.recv(65536):
                data += chunk
        except ConnectionResetError:
            pass
        return data


def test_declared_length_over_the_limit_is_413(client) -> None:
    r = client.post(
        "/localize",
        content=b"\0" * (MAX_BODY + 12),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 413 and r.headers["content-type"] == PROBLEM
    assert r.json()["field"] == "body"


def test_chunked_body_over_the_limit_is_413_without_content_length(server) -> None:
    chunk = b"\0" * (256 * 1024)
    enc = f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n"
    n = MAX_BODY // len(chunk) + 4
    head = (
        b"POST /localize HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
        b"Transfer-Encoding: chunked\r\n\r\n"
    )
    reply = _raw_request(server, head, [enc] * n + [b"0\r\n\r\n"])
    assert reply.startswith(b"HTTP/1.1 413"), reply[:200]
    assert b"over the limit" in reply


def test_a_lying_content_length_cannot_pass_the_limit(server) -> None:
    # Declares 120 bytes, sends more than the limit: the server reads only what was declared
    # (422: not a whole cloud) or h11 refuses the extra bytes (400); never a 2xx, never a crash.
    head = (
        b"POST /localize HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\n"
        b"Content-Length: 120\r\nConnection: close\r\n\r\n"
    )
    reply = _raw_request(server, head, [b"\0" * 120, b"\0" * (MAX_BODY + 1000)])
    assert reply.startswith((b"HTTP/1.1 422", b"HTTP/1.1 400")), reply[:200]
    assert httpx.get(f"{server}/healthz").status_code == 200


def test_client_disconnecting_mid_body_leaves_the_server_healthy(world, server, client) -> None:
    before = client.get("/metrics").text
    head = (
        b"POST /localize HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
        b"Content-Length: 200000\r\n\r\n"
    )
    for _ in range(3):
        _raw_request(server, head, [b'{"points": [[0.1, 0.2, 0.3], '], read=False)
    time.sleep(0.3)
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.post("/localize", json={"points": cloud(world, 2).tolist(), "top_n": 1})
    assert r.status_code == 200
    assert r.json()["matches"][0]["submap_id"].endswith(str(1_400_000_000_000_000 + 2_000_000))

    def disconnects(text: str) -> float:
        for line in text.splitlines():
            if line.startswith("pnvlad_client_disconnects_total"):
                return float(line.split()[-1])
        return 0.0

    deadline = time.monotonic() + 5
    while disconnects(client.get("/metrics").text) < disconnects(before) + 3:
        assert time.monotonic() < deadline, "disconnects were not counted"
        time.sleep(0.1)


# -- concurrency, metrics --------------------------------------------------------------------


def test_concurrent_good_and_bad_requests(world, server, local) -> None:
    clouds = {i: cloud(world, i) for i in range(0, 2 * PER_RUN, 5)}
    expected = {i: expected_ids(local, c, 3)[0] for i, c in clouds.items()}
    results: dict[str, object] = {}

    def good(i: int) -> None:
        with httpx.Client(base_url=server, timeout=60) as c:
            r = c.post("/localize", json={"points": clouds[i].tolist(), "top_n": 3})
            results[f"good{i}"] = (
                r.status_code,
                [m["rank"] for m in r.json()["matches"]],
                r.json()["matches"][0]["submap_id"],
                r.json()["batch_size"],
            )

    def bad(i: int) -> None:
        with httpx.Client(base_url=server, timeout=60) as c:
            r = c.post(
                "/localize",
                content=b'{"points": [[NaN, 0, 0]]}',
                headers={"content-type": "application/json"},
            )
            results[f"bad{i}"] = r.status_code

    threads = [threading.Thread(target=good, args=(i,)) for i in clouds]
    threads += [threading.Thread(target=bad, args=(i,)) for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    meta = local[1].metadata
    for i in clouds:
        status, ranks, first, _ = results[f"good{i}"]  # type: ignore[misc]
        assert status == 200 and ranks == [1, 2, 3]
        assert first == str(meta.submap_id[expected[i][0]])
    assert all(results[f"bad{i}"] == 422 for i in range(6))


def test_metrics_count_requests_errors_and_stages(client) -> None:
    client.post("/localize", content=b"{", headers={"content-type": "application/json"})
    text = client.get("/metrics").text
    assert 'pnvlad_requests_total{method="POST",route="/localize",status="200"}' in text
    assert 'pnvlad_errors_total{kind="malformed-json"}' in text
    assert 'pnvlad_errors_total{kind="invalid-input"}' in text
    for stage in ("parse", "queue", "embed", "search", "total"):
        assert f'pnvlad_stage_seconds_count{{stage="{stage}"}}' in text
    assert "pnvlad_index_vectors 32.0" in text
    # Random paths share one label value: the metric's cardinality stays bounded.
    client.get("/random/path/123")
    assert "/random/path/123" not in client.get("/metrics").text


def test_ops_endpoints(client, local) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    assert ready["status"] == "ready" and ready["runtime"].startswith("torch ")
    assert ready["index"] == {"id": local[1].bundle_id, "key": "Flat", "count": 2 * PER_RUN}
    info = client.get("/info").json()
    assert info["runtime"] == ready["runtime"]
    assert info["manifest"]["files"] == local[1].manifest.files
    assert info["limits"]["max_body_bytes"] == MAX_BODY
    doc = client.get("/openapi.json").json()
    assert {"/localize", "/localize/batch", "/healthz", "/readyz", "/info", "/metrics"} <= set(
        doc["paths"]
    )
    assert client.get("/docs").status_code == 200


# -- preprocessing of raw scans ------------------------------------------------------------


def test_raw_scan_with_preprocess_equals_local_filter_g(client, local, real_scans) -> None:
    preprocess = pytest.importorskip("pnvlad_service.preprocess.filter_g")
    from pnvlad_service.io.readers import read_points

    # A real KITTI scan of unknown frame (any real scan does: the check is the server's G).
    raw = read_points(real_scans / "kitti00_000000.bin", "kitti")
    r = client.post(
        "/localize?top_n=4&preprocess=true",
        content=raw.astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 200, r.text
    cfg = preprocess.GConfig.model_validate(local[1].manifest.preprocess)
    pts = preprocess.filter_g(raw.astype("<f4").astype(np.float64), cfg, seed=0)
    ids, _ = expected_ids(local, pts, 4)
    assert [m["submap_id"] for m in r.json()["matches"]] == [
        str(local[1].metadata.submap_id[i]) for i in ids
    ]
    assert r.json()["timings_ms"]["preprocess"] > 0
    # Without preprocess the same scan is refused with a hint.
    r = client.post(
        "/localize",
        content=raw.astype("<f4").tobytes(),
        headers={"content-type": "application/octet-stream"},
    )
    assert r.status_code == 422 and "preprocess" in r.json()["detail"]


# -- the CLI client ------------------------------------------------------------------------


def test_pnvlad_localize_against_the_server(world, server, local) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    rel = ix.list_database_submaps(world["tree"])[5].path
    res = CliRunner().invoke(
        app,
        ["localize", str(world["tree"] / rel), "--reader", "benchmark", "--url", server, "-n", "3"],
    )
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    header = ["rank", "submap", "run", "northing", "easting", "distance", "score"]
    assert lines[0].split() == header
    first = lines[1].split()
    assert first[0] == "1" and first[1] == str(local[1].metadata.timestamp[5])
    assert float(first[3]) == pytest.approx(local[1].metadata.northing[5], abs=0.01)
    res = CliRunner().invoke(
        app,
        ["localize", str(world["tree"] / rel), "--reader", "benchmark", "--url", server, "-n", "0"],
    )
    assert res.exit_code == 2 and "top_n" in res.output


# -- start-up, restart, authentication ------------------------------------------------------


def test_refuses_to_start_with_other_weights(world, tmp_path: Path) -> None:
    other = make_checkpoint(tmp_path / "other", seed=3)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pnvlad_cli.main",
            "serve",
            "--index",
            str(world["bundle"]),
            "--checkpoint",
            str(other),
            "--port",
            str(free_port()),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2
    assert "manifest.json" in proc.stderr and str(other / "model.safetensors") in proc.stderr
    assert "other weights" in proc.stderr


@pytest.mark.slow
def test_restart_with_the_same_bundle_gives_the_same_answers(world) -> None:
    queries = [cloud(world, i).tolist() for i in (1, PER_RUN + 6)]

    def ask(base: str) -> list:
        with httpx.Client(base_url=base, timeout=60) as c:
            return [
                c.post("/localize", json={"points": q, "top_n": 6}).json()["matches"]
                for q in queries
            ]

    answers = []
    for _ in range(2):
        port = free_port()
        proc = start_server(world["bundle"], port)
        try:
            answers.append(ask(f"http://127.0.0.1:{port}"))
        finally:
            stop_server(proc)
    assert answers[0] == answers[1]


def test_bearer_token(world) -> None:
    from fastapi.testclient import TestClient

    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    settings = ServerSettings(index=world["bundle"], api_key="s3cret")
    body = {"points": cloud(world, 0).tolist(), "top_n": 1}
    with TestClient(create_app(settings)) as c:
        r = c.post("/localize", json=body)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
        assert r.headers["content-type"] == PROBLEM
        assert (
            c.post("/localize", json=body, headers={"Authorization": "Bearer nope"}).status_code
            == 401
        )
        assert c.get("/info").status_code == 401
        r = c.post("/localize", json=body, headers={"Authorization": "Bearer s3cret"})
        assert r.status_code == 200 and r.json()["matches"][0]["rank"] == 1
        assert c.get("/healthz").status_code == 200  # probes stay open


def test_settings_come_from_the_environment(monkeypatch, world) -> None:
    from pnvlad_service.server.settings import ServerSettings

    monkeypatch.setenv("PNVLAD_INDEX", str(world["bundle"]))
    monkeypatch.setenv("PNVLAD_MAX_TOP_N", "7")
    s = ServerSettings()
    assert s.index == world["bundle"] and s.max_top_n == 7 and s.host == "127.0.0.1"


def test_the_verification_settings_reach_the_cascade(monkeypatch) -> None:
    """PNVLAD_VERIFY_* become the VerifyConfig the localizer registers with; an alone score of
    1 means the cascade always registers a second candidate."""
    from pnvlad_service.localization.verify.verify import VerifyConfig
    from pnvlad_service.server.settings import ServerSettings

    assert ServerSettings().verify_config().alone_score == VerifyConfig().alone_score
    monkeypatch.setenv("PNVLAD_VERIFY_STOP_SCORE", "0.4")
    monkeypatch.setenv("PNVLAD_VERIFY_ALONE_SCORE", "0.5")
    cfg = ServerSettings().verify_config()
    assert (cfg.stop_score, cfg.alone_score) == (0.4, 0.5)
    monkeypatch.setenv("PNVLAD_VERIFY_ALONE_SCORE", "1")
    assert ServerSettings().verify_config().alone_score is None


def test_the_settings_are_the_localizer_configs_sections(monkeypatch) -> None:
    """Each localiser setting is its section's field (same default, bounds, description)
    under the name the server reads, and the environment reaches the config it loads with."""
    import pydantic

    from pnvlad_service.localization.query.config import (
        BatchSection,
        EncoderSection,
        LocalizerConfig,
        PriorSection,
        VerifySection,
    )
    from pnvlad_service.server.settings import ServerSettings

    names = {
        "rerank": (VerifySection, "candidates"),
        "verify_threshold": (VerifySection, "threshold"),
        "verify_cache": (VerifySection, "cache"),
        "verify_crowded_threads": (VerifySection, "crowded_threads"),
        "prior_min_fitness": (PriorSection, "min_fitness"),
        "prior_max_sigma": (PriorSection, "max_sigma"),
        "batch_wait_ms": (BatchSection, "wait_ms"),
        "runtime": (EncoderSection, "runtime"),
        "verify_bundle": (LocalizerConfig, "check_bundle"),
    }
    for setting, (section, field) in names.items():
        mine, theirs = ServerSettings.model_fields[setting], section.model_fields[field]
        assert (mine.default, mine.metadata, mine.description) == (
            theirs.default,
            theirs.metadata,
            theirs.description,
        ), setting
    # The server verifies in a child by default; the library does not.
    assert ServerSettings().localizer_config().verify.process is True
    assert LocalizerConfig().verify.process is False
    monkeypatch.setenv("PNVLAD_RERANK", "7")
    monkeypatch.setenv("PNVLAD_VERIFY_THRESHOLD", "0.3")
    monkeypatch.setenv("PNVLAD_PRIOR_MAX_SUBMAPS", "2")
    monkeypatch.setenv("PNVLAD_BATCH_LANES", "3")
    cfg = ServerSettings().localizer_config()
    assert (cfg.verify.candidates, cfg.verify.threshold) == (7, 0.3)
    assert cfg.prior.config().max_submaps == 2 and cfg.batching.config().lanes == 3
    monkeypatch.setenv("PNVLAD_RERANK", "101")  # the section's bound, read from the environment
    with pytest.raises(pydantic.ValidationError):
        ServerSettings()
