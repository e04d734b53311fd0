"""Map updates over HTTP, against a real `pnvlad serve` on 127.0.0.1: POST /admin/reload (401
without the key, 422 naming the file for a missing or corrupt bundle with the old map still
answering, 200 and answers naming the new bundle), `pnvlad index add` plus SIGHUP, the admin
route off without a key (403); and a server without torch on model.onnx, which also refuses an
ONNX file exported from other weights at start-up, naming both files."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from pnvlad_service.index.build import add_to_bundle, build_bundle
from tests.index.helpers import PER_RUN, RUNS, free_port, make_checkpoint, make_tree, read_cloud
from tests.server.test_app import start_server, stop_server

KEY = "s3cret-admin"
PROBLEM = "application/problem+json"


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``a``: the first run (geometry: the server verifies in its child process); ``b``: both
    runs; ``serving``: a copy of ``a`` the SIGHUP test grows in place."""
    base = tmp_path_factory.mktemp("reload")
    tree = make_tree(base / "tree", frames=True)
    ckpt = make_checkpoint(base / "ckpt")
    build_bundle(base / "a", ckpt, tree, runs=[RUNS[0]], progress=False)
    shutil.copytree(base / "a", base / "b")
    add_to_bundle(base / "b", ckpt, tree, runs=[RUNS[1]], progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "a": base / "a", "b": base / "b"}


def cloud(maps: dict[str, Path], run: int, i: int) -> list[list[float]]:
    folder = maps["tree"] / "oxford" / RUNS[run] / "pointcloud_20m"
    name = sorted(folder.glob("*.bin"))[i].name
    return read_cloud(folder, name).tolist()


def ask(c: httpx.Client, maps, run: int = 1, i: int = 2) -> dict:
    r = c.post("/localize", json={"points": cloud(maps, run, i), "top_n": 3, "verify": False},
               headers={"Authorization": f"Bearer {KEY}"})  # fmt: skip
    assert r.status_code == 200, r.text
    return r.json()


@pytest.fixture(scope="module")
def server(maps) -> dict:
    bundle = maps["base"] / "served"
    shutil.copytree(maps["a"], bundle)
    port = free_port()
    proc = start_server(bundle, port, env={"PNVLAD_API_KEY": KEY})
    try:
        yield {"url": f"http://127.0.0.1:{port}", "proc": proc, "bundle": bundle}
    finally:
        stop_server(proc)


def test_reload_over_http(maps, server, tmp_path) -> None:
    auth = {"Authorization": f"Bearer {KEY}"}
    with httpx.Client(base_url=server["url"], timeout=60) as c:
        first = c.get("/readyz").json()["index"]
        assert first["count"] == PER_RUN
        # Unauthenticated: 401, nothing loaded.
        r = c.post("/admin/reload", json={"index": str(maps["b"])})
        assert r.status_code == 401 and r.headers["content-type"] == PROBLEM
        r = c.post("/admin/reload", json={"index": str(maps["b"])},
                   headers={"Authorization": "Bearer wrong"})  # fmt: skip
        assert r.status_code == 401
        # A missing bundle and a corrupt one: 422 naming the file; the old map still answers.
        missing = tmp_path / "nowhere.index"
        r = c.post("/admin/reload", json={"index": str(missing)}, headers=auth)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM
        assert str(missing) in r.json()["detail"]
        corrupt = tmp_path / "corrupt.index"
        shutil.copytree(maps["b"], corrupt)
        (corrupt / "index.faiss").write_bytes((corrupt / "index.faiss").read_bytes()[:-7])
        r = c.post("/admin/reload", json={"index": str(corrupt)}, headers=auth)
        assert r.status_code == 422 and "index.faiss" in r.json()["detail"]
        assert str(corrupt) in r.json()["detail"]
        assert ask(c, maps)["index"] == first
        # Unknown fields are refused.
        r = c.post("/admin/reload", json={"bundle": str(maps["b"])}, headers=auth)
        assert r.status_code == 422
        # The real thing: b swapped in, answers name it and find run 2's place.
        r = c.post("/admin/reload", json={"index": str(maps["b"])}, headers=auth)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["previous"]["index"] == first and body["encoder_reused"] is True
        assert body["current"]["index"]["count"] == 2 * PER_RUN
        answer = ask(c, maps)
        assert answer["index"] == body["current"]["index"]
        assert answer["matches"][0]["run"] == RUNS[1]
        assert c.get("/readyz").json()["index"] == answer["index"]
        verified = c.post("/localize", json={"points": cloud(maps, 1, 2), "top_n": 3},
                          headers=auth).json()  # fmt: skip
        assert verified["verified"] is not None  # the new bundle's geometry, in a new child
        text = c.get("/metrics").text
        assert 'pnvlad_reloads_total{result="swapped"} 1.0' in text
        assert 'pnvlad_reloads_total{result="refused"} 2.0' in text
        assert f"pnvlad_index_vectors {2 * PER_RUN}.0" in text
        # Back to the served path (read again), for the SIGHUP test.
        r = c.post("/admin/reload", json={"index": str(server["bundle"])}, headers=auth)
        assert r.status_code == 200 and r.json()["current"]["index"] == first


def test_index_add_then_sighup(maps, server) -> None:
    with httpx.Client(base_url=server["url"], timeout=60) as c:
        before = c.get("/readyz").json()["index"]
        assert before["count"] == PER_RUN
        add_to_bundle(server["bundle"], maps["ckpt"], maps["tree"], runs=[RUNS[1]], progress=False)
        server["proc"].send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 60
        while c.get("/readyz").json()["index"] == before and time.monotonic() < deadline:
            time.sleep(0.1)
        after = c.get("/readyz").json()["index"]
        assert after["count"] == 2 * PER_RUN and after["id"] != before["id"]
        assert ask(c, maps)["index"] == after
    assert server["proc"].poll() is None  # SIGHUP did not end it


def test_the_admin_route_is_off_without_a_key(maps) -> None:
    from fastapi.testclient import TestClient

    from pnvlad_service.localization.query.localizer import Localizer
    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    loc = Localizer.load(maps["a"], maps["ckpt"])
    try:
        app = create_app(ServerSettings(index=maps["a"]), localizer=loc)
        with TestClient(app) as c:
            r = c.post("/admin/reload", json={"index": str(maps["b"])})
            assert r.status_code == 403 and "PNVLAD_ADMIN_KEY" in r.json()["detail"]
        app = create_app(ServerSettings(index=maps["a"], admin_key=KEY), localizer=loc)
        with TestClient(app) as c:
            r = c.post("/admin/reload", headers={"Authorization": f"Bearer {KEY}"})
            assert r.status_code == 200  # no body: the serving path read again
            assert c.post("/localize", json={"points": cloud(maps, 0, 1)}).status_code == 200
    finally:
        loc.close()


def test_the_document_says_what_the_admin_route_answers(maps) -> None:
    """Off (no key): 403 whatever the request carries, and the document declares no bearer
    scheme there and lists 403, not 401. With a key: the bearer scheme declared, a missing
    header a 401 with ``WWW-Authenticate``, a wrong one too. Both: a body that is not text is
    the 400 the document lists."""
    from fastapi.testclient import TestClient

    from pnvlad_service.localization.query.localizer import Localizer
    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    loc = Localizer.load(maps["a"], maps["ckpt"])
    try:
        for key in (None, KEY):
            app = create_app(ServerSettings(index=maps["a"], admin_key=key), localizer=loc)
            with TestClient(app) as c:
                op = c.get("/openapi.json").json()["paths"]["/admin/reload"]["post"]
                documented = {int(s) for s in op["responses"]}
                bare = c.post("/admin/reload", json={})
                wrong = c.post("/admin/reload", json={}, headers={"Authorization": "Bearer no"})
                garbled = c.post(
                    "/admin/reload",
                    content=b"\x11\xff\xfe{",
                    headers={"content-type": "application/json", "Authorization": f"Bearer {key}"},
                )
            assert {bare.status_code, wrong.status_code, garbled.status_code} <= documented
            assert garbled.status_code == 400
            if key is None:
                assert "security" not in op and 401 not in documented
                assert bare.status_code == wrong.status_code == 403
            else:
                assert op["security"] == [{"HTTPBearer": []}] and 401 in documented
                assert bare.status_code == wrong.status_code == 401
                assert bare.headers["www-authenticate"] == "Bearer"
    finally:
        loc.close()


# --------------------------------------------------------------------------------------------
# Without torch, on model.onnx
# --------------------------------------------------------------------------------------------

SERVE_WITHOUT_TORCH = (
    "import sys; sys.modules['torch'] = None\n"
    "from pnvlad_cli.main import app\n"
    "sys.argv = ['pnvlad', *sys.argv[1:]]\n"
    "app()\n"
)


def serve_without_torch(bundle: Path, port: int) -> subprocess.Popen:
    cmd = [sys.executable, "-c", SERVE_WITHOUT_TORCH, "serve", "--index", str(bundle),
           "--port", str(port), "--log-level", "info"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_a_server_without_torch_embeds_on_onnx_runtime(maps) -> None:
    pytest.importorskip("onnx")
    from pnvlad_service.index.bundle import IndexBundle
    from pnvlad_service.models.onnx_export import export_onnx
    from pnvlad_service.models.runtimes import load_encoder

    export_onnx(maps["ckpt"])
    port = free_port()
    proc = serve_without_torch(maps["b"], port)
    try:
        deadline = time.monotonic() + 90
        ready = None
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                r = httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1)
                if r.status_code == 200:
                    ready = r.json()
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        assert ready is not None, proc.stdout.read() if proc.poll() is not None else "not ready"
        assert ready["runtime"].startswith("onnxruntime ")
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as c:
            pts = np.asarray(cloud(maps, 1, 5), dtype=np.float32)
            got = c.post("/localize", json={"points": pts.tolist(), "verify": False}).json()
            checked = c.post("/localize", json={"points": pts.tolist()}).json()
        enc, bundle = load_encoder(maps["ckpt"], runtime="torch"), IndexBundle.load(maps["b"])
        _, ids = bundle.search(enc.embed(pts[None]), 5)
        assert got["matches"][0]["submap_id"] == str(bundle.metadata.submap_id[ids[0][0]])
        assert checked["verified"] is not None  # verification works beside it
    finally:
        stop_server(proc)
    log = proc.stdout.read()
    assert "embedding with onnxruntime" in log


def test_an_onnx_file_of_other_weights_is_refused_at_start_up(maps, tmp_path) -> None:
    pytest.importorskip("onnx")
    from pnvlad_service.models.onnx_export import export_onnx

    model = tmp_path / "model"
    shutil.copytree(maps["ckpt"], model)
    other = make_checkpoint(tmp_path / "other", seed=9)
    export_onnx(other)
    shutil.copy(other / "model.onnx", model / "model.onnx")
    bundle = tmp_path / "map.index"
    shutil.copytree(maps["a"], bundle)
    cmd = [sys.executable, "-c", SERVE_WITHOUT_TORCH, "serve", "--index", str(bundle),
           "--checkpoint", str(model), "--port", str(free_port())]  # fmt: skip
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=90, env=os.environ)
    assert res.returncode == 2, res.stderr[-2000:]
    line = res.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert f"{model / 'model.onnx'} was exported from other weights" in line
    assert str(model / "model.safetensors") in line
