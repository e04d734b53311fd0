"""localization.serving: a map swapped while it serves. A query holds its localiser for its
whole life and its answer names that bundle; the old localiser closes only after its last
query; a bundle that fails a check (missing, corrupt, truncated geometry, other weights) is
refused and the old one serves on; reloads run one at a time."""

from __future__ import annotations

import os
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.index.build import add_to_bundle, build_bundle
from pnvlad_service.index.geometry import POINTS_FILE, ROW_BYTES
from pnvlad_service.localization.query.config import BatchSection, LocalizerConfig
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.query.serving import ReloadInProgress, ServingMap
from tests.index.helpers import PER_RUN, RUNS, make_checkpoint, make_tree, read_cloud


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """``a``: the first run (with geometry); ``b``: both runs (``a`` plus an added run, as
    ``pnvlad index add`` makes it); ``other``: the first run with other weights."""
    base = tmp_path_factory.mktemp("serving")
    tree = make_tree(base / "tree", frames=True)
    ckpt = make_checkpoint(base / "ckpt")
    build_bundle(base / "a", ckpt, tree, runs=[RUNS[0]], progress=False)
    shutil.copytree(base / "a", base / "b")
    add_to_bundle(base / "b", ckpt, tree, runs=[RUNS[1]], progress=False)
    other = make_checkpoint(base / "other_ckpt", seed=5)
    build_bundle(base / "other", other, tree, runs=[RUNS[0]], progress=False)
    return {"base": base, "tree": tree, "ckpt": ckpt, "a": base / "a", "b": base / "b",
            "other": base / "other"}  # fmt: skip


def loader(index: Path, model: Path, encoder) -> Localizer:
    return Localizer.load(
        index, model, LocalizerConfig(batching=BatchSection(max_size=8)), encoder=encoder
    )


def query(maps: dict[str, Path], i: int) -> np.ndarray:
    run = RUNS[i // PER_RUN]
    folder = maps["tree"] / "oxford" / run / "pointcloud_20m"
    files = sorted(folder.glob("*.bin"))
    return read_cloud(folder, files[i % PER_RUN].name).astype(np.float32)


@pytest.fixture
def serving(maps):
    sm = ServingMap(loader(maps["a"], maps["ckpt"], None), maps["a"], loader, drain_s=20)
    yield sm
    sm.close()


def test_a_query_finishes_on_the_bundle_it_started_on(maps, serving) -> None:
    old = serving.current
    pts = query(maps, PER_RUN + 2)  # run 2's submap: only bundle b holds its place
    done: dict[str, object] = {}
    with serving.lease() as held:
        t = threading.Thread(target=lambda: done.setdefault("r", serving.reload(maps["b"])))
        t.start()
        deadline = time.monotonic() + 30
        while serving.current is old and time.monotonic() < deadline:
            time.sleep(0.01)
        assert serving.current is not old  # swapped while the lease is held
        t.join(0.3)
        assert t.is_alive()  # the reload waits for this query before closing the old one
        a = held.localize(pts, top_n=3, verify=True)  # still answers, from a
        assert held.info.index.count == PER_RUN and all(m.id < PER_RUN for m in a.matches)
    t.join(30)
    assert not t.is_alive()
    r = done["r"]
    assert r.previous["index"]["count"] == PER_RUN and r.current["index"]["count"] == 2 * PER_RUN
    assert r.encoder_reused and serving.current.encoder is old.encoder
    assert old._closed  # closed once its last query was done
    with serving.lease() as loc:
        assert loc.info.index.count == 2 * PER_RUN
        assert loc.localize(pts, top_n=3, verify=False).matches[0].id == PER_RUN + 2
        assert loc.localize(pts, top_n=3, verify=True).verified is not None  # new geometry


def _refused(serving: ServingMap, path: Path, match: str) -> InputError:
    before = serving.current
    with pytest.raises(InputError, match=match) as exc:
        serving.reload(path)
    assert serving.current is before and not before._closed
    with serving.lease() as loc:  # the old one still answers
        assert loc.localize(np.zeros((4096, 3), np.float32) + 0.1, top_n=1).matches
    return exc.value


def test_broken_bundles_are_refused_and_the_old_one_serves_on(maps, serving, tmp_path) -> None:
    missing = tmp_path / "nowhere.index"
    assert str(missing) in str(_refused(serving, missing, "directory not found"))

    corrupt = tmp_path / "corrupt.index"
    shutil.copytree(maps["b"], corrupt)
    with open(corrupt / "metadata.npz", "r+b") as fh:
        fh.seek(100)
        fh.write(b"\xff\x00\xff")
    err = _refused(serving, corrupt, r"do not match the manifest's sha256: \['metadata.npz'\]")
    assert str(corrupt) in str(err)

    truncated = tmp_path / "truncated.index"
    shutil.copytree(maps["b"], truncated)
    os.truncate(truncated / POINTS_FILE, 3 * ROW_BYTES + 10)
    err = _refused(serving, truncated, "geometry.f16 is truncated")
    assert str(truncated / POINTS_FILE) in str(err)

    err = _refused(serving, maps["other"], "was built with other weights")
    assert "model.safetensors" in str(err)
    assert serving.reloads == 0


def test_one_reload_at_a_time(maps) -> None:
    gate = threading.Event()

    def slow(index, model, encoder):
        gate.wait(20)
        return loader(index, model, encoder)

    sm = ServingMap(loader(maps["a"], maps["ckpt"], None), maps["a"], slow)
    try:
        t = threading.Thread(target=sm.reload, args=(maps["b"],))
        t.start()
        time.sleep(0.2)
        with pytest.raises(ReloadInProgress):
            sm.reload(maps["b"])
        gate.set()
        t.join(30)
        assert sm.current.info.index.count == 2 * PER_RUN
    finally:
        gate.set()
        sm.close()


def test_answers_across_swaps_each_name_one_bundle(maps, serving) -> None:
    """Four threads query while the map swaps a -> b -> a -> b: no error, and every answer's
    matches lie in the bundle its localiser names (ids of run 2 exist only in b)."""
    ids = {"a": None, "b": None}
    for name in ids:
        with Localizer.load(maps[name], maps["ckpt"]) as loc:
            ids[name] = loc.info.index.id
    stop = threading.Event()
    seen: list[tuple[str, int, int]] = []
    errors: list[BaseException] = []

    def client(k: int) -> None:
        i = k
        while not stop.is_set():
            try:
                with serving.lease() as loc:
                    ans = loc.localize(query(maps, PER_RUN + i % PER_RUN), top_n=5, verify=False)
                    seen.append((loc.info.index.id, loc.info.index.count,
                                 max(m.id for m in ans.matches)))  # fmt: skip
            except BaseException as exc:  # the test counts them
                errors.append(exc)
            i += 4

    threads = [threading.Thread(target=client, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for name in ("b", "a", "b"):
        time.sleep(0.3)
        serving.reload(maps[name])
    time.sleep(0.3)
    stop.set()
    for t in threads:
        t.join(30)
    assert errors == []
    assert {s[0] for s in seen} == {ids["a"], ids["b"]}
    for bundle_id, count, top in seen:
        assert top < count
        assert count == (PER_RUN if bundle_id == ids["a"] else 2 * PER_RUN)
