"""Fixtures shared by the server's tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.index.helpers import free_port
from tests.server.test_app import start_server, stop_server


@pytest.fixture(scope="module")
def keys_server(tiny_maps: dict) -> Iterator[str]:
    """A real ``pnvlad serve`` of the tiny city's keyframe map on 127.0.0.1, one per module."""
    port = free_port()
    proc = start_server(tiny_maps["keys"], port)
    yield f"http://127.0.0.1:{port}"
    stop_server(proc)
