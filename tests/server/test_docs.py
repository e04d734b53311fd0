"""API docs with no internet: /docs and /redoc load only assets the server itself serves, and
headless Chromium renders the operations from them (a real server on 127.0.0.1)."""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from pnvlad_service.index import build as ix
from pnvlad_service.server import docs
from tests.index.helpers import free_port, make_checkpoint, make_tree
from tests.server.test_app import start_server, stop_server

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Flags that keep Chromium off every network but loopback (no updates, sync, QUIC, ...).
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    base = tmp_path_factory.mktemp("docs")
    tree = make_tree(base / "tree")
    ix.build_bundle(base / "map.index", make_checkpoint(base / "ckpt"), tree, progress=False)
    port = free_port()
    proc = start_server(base / "map.index", port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        stop_server(proc)


def _links(html: str) -> list[str]:
    return re.findall(r"""(?:src|href|url)\s*[=:]\s*['"]([^'"]+)['"]""", html)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_pages_load_only_assets_the_server_serves(server: str, page: str) -> None:
    r = httpx.get(server + page, timeout=10)
    assert r.status_code == 200 and "text/html" in r.headers["content-type"]
    links = _links(r.text)
    assert links, "the page names no assets"
    for link in links:
        assert link.startswith("/"), f"{page} loads {link} from elsewhere"
        got = httpx.get(server + link, timeout=10)
        assert got.status_code == 200 and len(got.content) > 100, link
    assert f"{docs.ASSETS_URL}/" in r.text


def _dump_dom(url: str) -> str:
    with tempfile.TemporaryDirectory() as profile:
        proc = subprocess.run(
            [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             "--virtual-time-budget=15000", "--dump-dom", url],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium not installed (Debian package chromium)")
def test_swagger_ui_renders_the_operations_in_headless_chromium(server: str) -> None:
    dom = _dump_dom(server + "/docs")
    paths = set(re.findall(r'class="opblock-summary-path" data-path="([^"]+)"', dom))
    assert {"/localize", "/localize/batch", "/healthz", "/info"} <= paths


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium not installed (Debian package chromium)")
def test_redoc_renders_the_operations_in_headless_chromium(server: str) -> None:
    dom = _dump_dom(server + "/redoc")
    assert "Localise one point cloud" in dom and "/localize/batch" in dom


def test_missing_assets_answer_503_naming_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    from fastapi.testclient import TestClient

    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    monkeypatch.setattr(docs, "assets_dir", lambda: None)
    client = TestClient(create_app(ServerSettings()))  # no lifespan: no bundle needed
    for page in ("/docs", "/redoc"):
        r = client.get(page)
        assert r.status_code == 503 and "fastapi-offline" in r.text
    assert client.get("/openapi.json").status_code == 200


def test_assets_dir_is_the_installed_package() -> None:
    folder = docs.assets_dir()
    assert isinstance(folder, Path)
    assert all((folder / name).stat().st_size > 1000 for name in docs.ASSET_FILES)
