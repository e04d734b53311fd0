"""A bundle's geometry at a real server's start-up: a bundle with geometry serves; one whose
geometry.f16 is truncated or fails its hash is refused, by `pnvlad serve` before it starts
(exit 2, one line naming the file) and by the app's lifespan under plain uvicorn."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from pnvlad_service.index.geometry import POINTS_FILE, ROW_BYTES
from tests.index.helpers import PER_RUN, free_port, make_world
from tests.server.test_app import start_server, stop_server


@pytest.fixture(scope="module")
def geo(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return make_world(tmp_path_factory.mktemp("server_geo"), "geo.index", frames=True)


def _serve(bundle: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pnvlad_cli.main", "serve", "--index", str(bundle),
           "--port", str(free_port())]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=90)


def _uvicorn(bundle: Path) -> subprocess.CompletedProcess:
    """The app without the CLI's check: the lifespan's IndexBundle.load must refuse it."""
    cmd = [sys.executable, "-m", "uvicorn", "pnvlad_service.server.app:create_app_from_env",
           "--factory", "--port", str(free_port()), "--log-level", "warning"]  # fmt: skip
    env = {**os.environ, "PNVLAD_INDEX": str(bundle)}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=90, env=env)


def test_a_bundle_with_geometry_serves(geo) -> None:
    port = free_port()
    proc = start_server(geo["bundle"], port)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=30) as c:
            manifest = c.get("/info").json()["manifest"]
            assert manifest["count"] == 2 * PER_RUN and manifest["geometry"]["count"] == 2 * PER_RUN
    finally:
        stop_server(proc)


def test_a_truncated_geometry_file_is_refused_at_start_up(geo, tmp_path) -> None:
    bad = tmp_path / "truncated.index"
    shutil.copytree(geo["bundle"], bad)
    os.truncate(bad / POINTS_FILE, 3 * ROW_BYTES + 10)
    res = _serve(bad)
    assert res.returncode == 2, res.stderr[-2000:]
    assert f"{bad / POINTS_FILE}: geometry.f16 is truncated" in res.stderr
    assert "Traceback" not in res.stderr


def test_a_geometry_file_failing_its_hash_is_refused_at_start_up(geo, tmp_path) -> None:
    bad = tmp_path / "flipped.index"
    shutil.copytree(geo["bundle"], bad)
    data = bytearray((bad / POINTS_FILE).read_bytes())
    data[7 * ROW_BYTES + 5] ^= 0x01
    (bad / POINTS_FILE).write_bytes(bytes(data))
    res = _serve(bad)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "geometry.f16 does not match the manifest's sha256 (row 7" in res.stderr
    assert str(bad / POINTS_FILE) in res.stderr
    # Without the CLI in front, the app itself refuses to start.
    res = _uvicorn(bad)
    out = res.stdout + res.stderr
    assert res.returncode != 0 and "geometry.f16 does not match" in out, out[-2000:]
