"""The localisation library with no HTTP: typed, frozen answers equal to a plain search and to
the server's, raw scans through the bundle's filter G, many threads through the micro-batcher,
and no web framework imported (the compatibility check: test_compatibility.py; the thread
counts: test_threads.py)."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError, NotReadyError
from pnvlad_service.index import build as ix
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.localization.query.answers import Answer
from pnvlad_service.localization.query.config import BatchSection, LocalizerConfig
from pnvlad_service.localization.query.localizer import Localizer, Match
from pnvlad_service.models.runtimes import load_encoder
from tests.index.helpers import PER_RUN, read_cloud


@pytest.fixture(scope="module")
def loc(world: dict[str, Path]):
    with Localizer.load(world["bundle"]) as loc:
        yield loc


@pytest.fixture(scope="module")
def plain(world: dict[str, Path]):
    """(encoder, bundle) loaded directly, for expected answers."""
    return load_encoder(world["ckpt"]), IndexBundle.load(world["bundle"])


def cloud(world: dict[str, Path], i: int) -> np.ndarray:
    return read_cloud(world["tree"], ix.list_database_submaps(world["tree"])[i].path)


def plain_search(plain, points: np.ndarray, k: int) -> tuple[list[int], np.ndarray]:
    enc, bundle = plain
    d, ids = bundle.search(enc.embed(np.asarray(points, np.float32)[None]), k)
    return ids[0].tolist(), d[0]


def raw_scan(seed: int = 0) -> np.ndarray:
    """A synthetic raw scan in metres: ground (z = 0) and a few walls standing on it."""
    rng = np.random.default_rng(seed)
    g = np.arange(-30.0, 30.0, 0.5)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    parts = [np.c_[x, y, rng.normal(0.0, 0.02, x.size)]]
    for cx, cy, along_x in ((5.0, 8.0, True), (-12.0, 3.0, False), (2.0, -15.0, True)):
        s, h = np.meshgrid(np.arange(-4.0, 4.0, 0.1), np.arange(0.5, 3.0, 0.1))
        wx, wy = (cx + s, np.full_like(s, cy)) if along_x else (np.full_like(s, cx), cy + s)
        parts.append(np.c_[wx.ravel(), wy.ravel(), h.ravel()])
    return np.concatenate(parts) + rng.normal(0.0, 0.01, (sum(len(p) for p in parts), 3))


def test_a_typed_answer_equals_a_plain_search(world, loc, plain) -> None:
    pts = cloud(world, PER_RUN + 3)
    answer = loc.localize(pts, top_n=5)
    assert isinstance(answer, Answer) and all(isinstance(m, Match) for m in answer.matches)
    ids, dists = plain_search(plain, pts, 5)
    meta = plain[1].metadata
    assert [m.submap_id for m in answer.matches] == [str(meta.submap_id[i]) for i in ids]
    assert [m.rank for m in answer.matches] == [1, 2, 3, 4, 5]
    np.testing.assert_allclose([m.distance for m in answer.matches], dists, atol=1e-5)
    first = answer.matches[0]
    assert first.northing == meta.northing[PER_RUN + 3]
    assert first.easting == meta.easting[PER_RUN + 3]
    assert answer.batch_size == 1 and answer.timings.queue == 0.0  # no batcher: no queue
    assert answer.timings.total >= answer.timings.embed > 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        answer.batch_size = 2  # type: ignore[misc]
    manifest = plain[1].manifest
    assert loc.info.model.weights_sha256 == manifest.model.weights_sha256
    assert loc.info.model.dim == 16 and loc.info.index.count == 2 * PER_RUN
    assert loc.info.index.id == plain[1].bundle_id and loc.info.index.key == "Flat"
    assert loc.manifest_json() == manifest.to_json()
    assert loc.identity.checkpoint == str(world["ckpt"].resolve())


def test_the_library_answers_as_the_server_does(world, loc) -> None:
    from fastapi.testclient import TestClient

    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    clouds = [cloud(world, i) for i in (0, 9, PER_RUN + 1)]
    with TestClient(create_app(ServerSettings(index=world["bundle"]))) as c:  # its own load
        for pts in clouds:
            served = c.post("/localize", json={"points": pts.tolist(), "top_n": 4}).json()
            mine = {**loc.localize(pts, top_n=4).to_json(), **loc.info.to_json()}
            assert served["matches"] == mine["matches"]
            assert (served["model"], served["index"]) == (mine["model"], mine["index"])
            assert set(served["timings_ms"]) == set(mine["timings_ms"])
        batch = c.post(
            "/localize/batch", json={"queries": [{"points": p.tolist()} for p in clouds]}
        ).json()
    for served, pts in zip(batch["results"], clouds, strict=True):  # embedded as a batch of 3
        mine = loc.localize(pts).matches
        assert [m["submap_id"] for m in served["matches"]] == [m.submap_id for m in mine]
        np.testing.assert_allclose(
            [m["distance"] for m in served["matches"]], [m.distance for m in mine], atol=1e-5
        )


def test_a_raw_scan_goes_through_the_bundles_filter_g(loc, plain) -> None:
    from pnvlad_service.preprocess.filter_g import GConfig, filter_g

    raw = raw_scan()
    answer = loc.localize(raw, preprocess=True, top_n=3)
    cfg = GConfig.model_validate(dict(plain[1].manifest.preprocess))
    ids, dists = plain_search(plain, filter_g(raw, cfg, seed=0), 3)
    assert [m.id for m in answer.matches] == ids
    np.testing.assert_allclose([m.distance for m in answer.matches], dists, atol=1e-5)
    assert answer.timings.preprocess > 0
    prepared = loc.prepare(raw, True)
    cloud = prepared.cloud
    assert cloud.dtype == np.float32 and cloud.shape == (4096, 3)
    assert np.abs(cloud).max() <= 1.0
    # What G did comes along: the cloud in metres is the raw scan's voxel means (sensor frame).
    assert prepared.sensor and prepared.scale is not None and prepared.scale > 0
    metres = prepared.query([]).points_m
    from scipy.spatial import cKDTree

    assert np.median(cKDTree(raw).query(metres)[0]) < 2.0
    # The filter G's own refusal, as the library raises it (the server names its field).
    with pytest.raises(InputError, match="points"):
        loc.localize(np.zeros((3, 3)), preprocess=True)


def test_bad_clouds_raise_the_librarys_errors_naming_the_field(loc) -> None:
    pts = np.zeros((4096, 3))
    pts[17, 2] = np.nan
    with pytest.raises(InputError) as info:
        loc.localize(pts)
    assert info.value.source == "points[17]"
    with pytest.raises(InputError, match="exactly 4096") as info:
        loc.localize(np.zeros((100, 3)))
    assert info.value.source == "points"
    with pytest.raises(InputError) as info:
        loc.localize(np.zeros((4096, 3)), top_n=0)
    assert info.value.source == "top_n"


def test_a_closed_localizer_is_not_ready(world) -> None:
    loc = Localizer.load(world["bundle"], config=LocalizerConfig(batching=BatchSection()))
    pts = cloud(world, 1)
    assert loc.localize(pts).matches[0].rank == 1
    loc.close()
    loc.close()  # idempotent
    with pytest.raises(NotReadyError, match="closed"):
        loc.localize(pts)


def test_many_threads_share_batches_and_get_their_own_answers(world, loc) -> None:
    idx = list(range(0, 2 * PER_RUN, 2))
    clouds = {i: cloud(world, i) for i in idx}
    expected = {i: loc.localize(c, top_n=3).matches for i, c in clouds.items()}
    got: dict[tuple[int, int], Answer] = {}
    with Localizer.load(
        world["bundle"], config=LocalizerConfig(batching=BatchSection(max_size=8, wait_ms=5.0))
    ) as shared:
        start = threading.Barrier(len(idx))

        def ask(i: int) -> None:
            start.wait()
            for r in range(3):
                got[(i, r)] = shared.localize(clouds[i], top_n=3)

        threads = [threading.Thread(target=ask, args=(i,)) for i in idx]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
    assert len(got) == 3 * len(idx)
    for (i, _), answer in got.items():
        assert [m.id for m in answer.matches] == [m.id for m in expected[i]]
    assert max(a.batch_size for a in got.values()) > 1


def test_the_library_imports_no_web_framework() -> None:
    code = (
        "import sys\n"
        "import pnvlad_service.localization.query.localizer, pnvlad_service.client\n"
        "import pnvlad_service.localization.query.limits\n"
        "import pnvlad_service.localization.query.batching\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('fastapi', 'starlette'))\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_warm_up_embeds_each_batch_size_once_and_changes_no_answer(world, loc, plain) -> None:
    """warm_up(n) runs the encoder once at each batch size 1..n on whole submaps (the shapes
    the server embeds), and answers after it are those of a plain search."""
    seen: list[tuple[int, ...]] = []
    real = loc.encoder

    class Recording:
        """The real encoder, its input shapes written down."""

        def __getattr__(self, name: str):
            return getattr(real, name)

        def embed(self, points):
            seen.append(np.shape(points))
            return real.embed(points)

    loc.encoder = Recording()
    try:
        assert loc.warm_up(0) >= 0.0 and seen == []
        loc.warm_up(3)
        assert seen == [(1, 4096, 3), (2, 4096, 3), (3, 4096, 3)]
    finally:
        loc.encoder = real
    pts = cloud(world, 3)
    ids, d = plain_search(plain, pts, 5)
    answer = loc.localize(pts, top_n=5)
    assert [m.id for m in answer.matches] == ids
    assert [m.distance for m in answer.matches] == pytest.approx(d.tolist(), abs=1e-5)
