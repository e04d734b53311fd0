"""`pnvlad serve --checkpoint pretrained:NAME`: a real server on 127.0.0.1 started with a
shipped model by its name (the README's main job does this) serves a map built with it and
answers with the shipped weights (the name was once taken for a relative path and made absolute
before it was resolved, and the server refused to start)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.models import pretrained
from pnvlad_service.models.store import model_identity
from tests.index.helpers import free_port, read_cloud
from tests.server.test_app import start_server, stop_server

NAME = "bev-benchmark"


@pytest.mark.skipif(
    NAME not in {e.name for e in pretrained.Catalogue.read(pretrained.PACKAGE_CATALOGUE).entries},
    reason=f"pretrained:{NAME} does not ship",
)
def test_serve_takes_a_shipped_model_by_name(
    tiny: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pnvlad_service.client import LocalizeClient
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.build import build_bundle, list_database_submaps

    monkeypatch.delenv(pretrained.CATALOGUE_ENV, raising=False)
    runs = BenchmarkTree(tiny).runs("business")
    bundle = tmp_path / "map.index"
    build_bundle(bundle, f"pretrained:{NAME}", tiny, runs=runs[1:], progress=False)
    held = list_database_submaps(tiny, runs=runs[:1])
    port = free_port()
    proc = start_server(bundle, port, args=("--checkpoint", f"pretrained:{NAME}"))
    try:
        with LocalizeClient(f"http://127.0.0.1:{port}") as client:
            info = client.info()
            shipped = model_identity(
                pretrained.resolve(f"pretrained:{NAME}", pretrained.PACKAGE_CATALOGUE)
            )
            assert info["model"]["weights_sha256"] == shipped.weights_sha256
            near = 0
            for item in held[:8]:
                cloud = read_cloud(tiny, item.path)
                answer = client.localize(cloud, top_n=1, verify=False)
                top = answer["matches"][0]
                off = np.hypot(top["northing"] - item.northing, top["easting"] - item.easting)
                near += off < 25
            assert near >= 5, near  # the shipped model finds 74 % of this city's places
    finally:
        stop_server(proc)
