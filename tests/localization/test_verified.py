"""Verified localisation end to end on the tiny synthetic city: a bundle of two runs with
geometry, queried with a third run's submaps. The model is random, so retrieval alone is a
lottery; registering every database submap (K = all) must still find the true place and pose
it within the issue's 2 m and 5 degrees of the simulator's truth."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.evaluation.rerank_figures import pose_error
from pnvlad_service.io.submap import read_submap
from pnvlad_service.localization.query.config import LocalizerConfig, VerifySection
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.localization.verify.verifier import InChild
from pnvlad_service.localization.verify.verify import VerifyConfig, bundle_candidates


@pytest.fixture(scope="module")
def city(tiny_maps: dict) -> dict:
    return {**tiny_maps, "bundle": tiny_maps["map"]}


def _queries(city: dict) -> list[tuple[np.ndarray, object, object]]:
    tree, run = city["tree"], city["query_run"]
    subs = tree.submaps("business", run, "test")
    frames = tree.frames("business", run, "test")
    return [(read_submap(tree.root / s.path), s, f) for s, f in zip(subs, frames, strict=True)]


def test_every_query_verifies_at_its_true_place_and_pose(city: dict) -> None:
    """K = all, no early stop: the re-ranked top-1 is the true place, posed within 2 m and 5
    degrees, for at least 80 % of the queries, and every verified answer is one of those."""
    frames = city["tree"].frames_by_path()
    with Localizer.load(city["bundle"]) as loc:
        assert loc.can_verify
        loc.verify_config = VerifyConfig(
            candidates=min(100, loc.bundle.count), threshold=0.1, stop_score=None
        )
        ok = verified = 0
        queries = _queries(city)
        for cloud, sub, qf in queries:
            ans = loc.localize(cloud, top_n=3, scale=qf.scale)
            best = ans.matches[0]
            assert ans.verified is not None and ans.verification is not None
            assert ans.verification.registered == loc.bundle.count
            assert [m.rank for m in ans.matches] == [1, 2, 3]
            near = np.hypot(best.northing - sub.northing, best.easting - sub.easting)
            path = str((city["tree"].root / best.path).resolve())
            dbf = frames[path]
            # The query frame is its centroid frame: local = centre + that frame.
            q_frame = qf.true_pose.copy()
            q_frame[:3, 3] += q_frame[:3, :3] @ qf.centre
            truth = np.linalg.inv(dbf.true_pose) @ q_frame
            est = ans.verification.checks[0].transform
            t, y = pose_error(est, truth)
            right = near < 25 and t < 2.0 and y < 5.0
            ok += right
            if ans.verified:
                verified += 1
                assert right, (near, t, y, ans.verification.confidence)
                assert ans.verification.pose.scale == "measured"
                posed = np.linalg.inv(dbf.map_pose) @ ans.verification.pose.transform
                assert np.allclose(posed, est)
        assert ok >= 0.8 * len(queries), (ok, len(queries))
        assert verified >= 3, verified


def test_a_degenerate_query_is_not_verified_and_does_not_raise(city: dict) -> None:
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (4096, 2)), np.zeros(4096)].astype(np.float32)
    line = np.c_[np.linspace(-1, 1, 4096), np.zeros((4096, 2))].astype(np.float32)
    with Localizer.load(city["bundle"]) as loc:
        for cloud in (plane, line):
            ans = loc.localize(cloud, top_n=2)
            assert ans.verified is False and ans.verification.pose is None
            assert ans.verification.registered == 0 and ans.verification.confidence == 0.0
            assert "plane" in ans.verification.reason or "line" in ans.verification.reason
            assert ans.to_json()["verified"] is False
        # A raw scan that G leaves nearly empty: 80 points in a 1 m box, refilled to 4096.
        blob = rng.uniform([4.0, -0.5, 1.0], [5.0, 0.5, 2.0], (80, 3))
        ans = loc.localize(blob, preprocess=True, top_n=2)
        assert ans.verified is False and "distinct points" in ans.verification.reason


def test_verification_asked_of_a_bundle_without_geometry_names_the_field(city: dict) -> None:
    cloud = _queries(city)[0][0]
    with Localizer.load(city["plain"]) as loc:
        assert not loc.can_verify
        ans = loc.localize(cloud, top_n=2)  # default: off, silently
        assert ans.verified is None and ans.to_json()["pose"] is None
        with pytest.raises(InputError, match="no geometry") as exc:
            loc.localize(cloud, top_n=2, verify=True)
        assert exc.value.source == "verify"
    with Localizer.load(city["bundle"]) as loc:
        ans = loc.localize(cloud, top_n=2, verify=False)
        assert ans.verified is None
        with pytest.raises(InputError, match="scale"):
            loc.localize(cloud, top_n=2, scale=-1.0)


def test_candidates_are_read_only_when_registered_and_not_cached(city: dict) -> None:
    """``bundle_candidates`` reads a submap's points when the cascade registers it and its
    prepared cloud is not cached: once per registered candidate on a cold cache, never on a
    warm one; and the answers are those of candidates read up front."""
    from pnvlad_service.localization.verify.verify import Candidate, PreparedCache, verify

    cloud, _, qf = _queries(city)[0]
    with Localizer.load(city["bundle"]) as loc:
        geometry = loc.bundle.geometry
        ids = [int(i) for i in loc.submit(loc.prepare(cloud, False, qf.scale), 10).result().ids]
        query = loc.prepare(cloud, False, qf.scale).query([])
        read: list[int] = []
        real = geometry.metres

        def counted(i: int) -> np.ndarray:
            read.append(i)
            return real(i)

        geometry.metres = counted  # the real reader, counted
        try:
            cache = PreparedCache(32)
            cold = verify(query, bundle_candidates(geometry, ids), loc.verify_config, cache=cache)
            assert 2 <= cold.registered < len(ids)  # the cascade stopped early
            assert sorted(read) == sorted(ids[: cold.registered])
            read.clear()
            warm = verify(query, bundle_candidates(geometry, ids), loc.verify_config, cache=cache)
            assert read == []
        finally:
            geometry.metres = real
        eager = [Candidate(k, real(i), geometry.map_pose(i), key=i) for k, i in enumerate(ids, 1)]
        plain = verify(query, eager, loc.verify_config)
        for got in (cold, warm):
            assert got.order == plain.order and got.verified == plain.verified
            assert [c.score for c in got.checks] == pytest.approx([c.score for c in plain.checks])


def test_the_encoder_is_crowded_while_a_verification_is_in_flight(city: dict) -> None:
    """A Localizer with geometry tells its encoder that the cores are taken (``crowded_by``)
    exactly while a verification runs: asked from inside one (as a candidate's points are
    read), it says so; before and after, not."""
    cloud, _, qf = _queries(city)[0]
    with Localizer.load(city["bundle"]) as loc:
        crowded = loc.encoder.crowded_by
        assert crowded is not None and crowded() is False
        geometry = loc.bundle.geometry
        real = geometry.metres
        seen: list[bool] = []

        def metres(i: int) -> np.ndarray:
            seen.append(crowded())
            return real(i)

        geometry.metres = metres
        try:
            answer = loc.localize(cloud, top_n=3, scale=qf.scale)
        finally:
            geometry.metres = real
        assert answer.verification is not None and seen and all(seen)
        assert crowded() is False


def test_the_child_process_verifies_as_the_server_process_does(
    city: dict, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``verify_process``: the same checks (order, scores, transforms) and poses as in the
    caller's process; when the child is killed, the query that finds it dead is still
    answered (in the caller's process) and the next one starts a new child."""
    import os
    import signal

    config = VerifyConfig(candidates=6, threshold=0.1, stop_score=None)
    queries = _queries(city)[:4]
    with Localizer.load(city["bundle"], config=_config(config)) as here:
        expected = [here.localize(c, top_n=3, scale=qf.scale) for c, _, qf in queries]
    from pnvlad_service.localization.verify.verify_process import SPINCOUNT_MARK

    # As `pnvlad serve` leaves the environment: its spin count, which the child drops.
    monkeypatch.setenv("GOMP_SPINCOUNT", "20000")
    monkeypatch.setenv(SPINCOUNT_MARK, "1")
    with Localizer.load(city["bundle"], config=_config(config, process=True)) as loc:
        assert isinstance(loc.verifier, InChild)
        child = loc.verifier.process
        for (cloud, _, qf), want in zip(queries, expected, strict=True):
            got = loc.localize(cloud, top_n=3, scale=qf.scale)
            assert got.verification.order == want.verification.order
            assert got.verified == want.verified
            for g, w in zip(got.verification.checks, want.verification.checks, strict=True):
                assert g.score == pytest.approx(w.score, abs=1e-9)
                assert np.allclose(g.transform, w.transform, atol=1e-6)
            if want.verified:
                assert np.allclose(
                    got.verification.pose.transform, want.verification.pose.transform
                )
        # The child's OpenMP threads sleep at barriers, set before libgomp loaded there.
        from pnvlad_service.localization.verify.verify_process import _runtime

        runtime = child._started().submit(_runtime).result()
        policy = os.environ.get("OMP_WAIT_POLICY", "PASSIVE")  # a value set outside is kept
        assert runtime == {
            "OMP_WAIT_POLICY": policy,
            "GOMP_SPINCOUNT": None,
            "gomp_before": False,
        }
        (pid,) = [p.pid for p in child._pool._processes.values()]
        os.kill(pid, signal.SIGKILL)
        cloud, _, qf = queries[0]
        again = loc.localize(cloud, top_n=3, scale=qf.scale)  # answered here
        assert again.verification.order == expected[0].verification.order
        after = loc.localize(cloud, top_n=3, scale=qf.scale)  # a new child
        assert after.verification.order == expected[0].verification.order
        (new_pid,) = [p.pid for p in child._pool._processes.values()]
        assert new_pid != pid


def test_a_script_without_a_main_guard_gets_an_error_that_says_so(
    city: dict, tmp_path: Path
) -> None:
    """spawn imports the parent's script again in the child: without ``if __name__ ==
    "__main__":`` the child would start another child; the parent's error says what to do."""
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from pnvlad_service.localization.query.localizer import Localizer\n"
        "from pnvlad_service.localization.query.config import LocalizerConfig\n"
        f"Localizer.load({str(city['bundle'])!r},\n"
        "    config=LocalizerConfig(verify={'process': True})).close()\n"
    )
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode != 0
    assert "if __name__ == '__main__':" in out.stderr and "verification process" in out.stderr


def test_the_models_calibrated_threshold_is_taken_unless_one_is_given(city, tmp_path) -> None:
    """A model directory's verification.json sets the threshold for its weights; a given
    threshold wins; a record of other weights is ignored; a malformed one is refused, naming
    the file."""
    import json
    import shutil

    from pnvlad_service.localization.query.calibration import (
        Calibration,
        read_calibration,
        write_calibration,
    )
    from pnvlad_service.models.store import weights_sha256

    model = tmp_path / "model"
    shutil.copytree(city["base"] / "ckpt", model)
    sha = weights_sha256(model)
    record = Calibration(0.37, sha, 10, 99.5, 120, {"precision": 99.6, "coverage": 88.0})
    path = write_calibration(model, record)
    assert read_calibration(model, sha) == record  # round trip
    with Localizer.load(city["bundle"], model) as loc:
        assert loc.verify_config.threshold == 0.37
        assert loc.localize(_queries(city)[0][0], top_n=1).verification.threshold == 0.37
    given = LocalizerConfig(verify=VerifySection(threshold=0.2))
    with Localizer.load(city["bundle"], model, given) as loc:
        assert loc.verify_config.threshold == 0.2
    # Chosen for other weights: not used.
    doc = json.loads(path.read_text())
    path.write_text(json.dumps({**doc, "weights_sha256": "0" * 64}))
    assert read_calibration(model, sha) is None
    with Localizer.load(city["bundle"], model) as loc:
        assert loc.verify_config.threshold == VerifyConfig.threshold
    for bad in ({**doc, "threshold": 1.5}, {**doc, "format": "x"}, {"format": doc["format"]}):
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match="verification"):
            Localizer.load(city["bundle"], model)
        with pytest.raises(InputError) as err:
            read_calibration(model, sha)
        assert str(path) in str(err.value)
    path.write_text("{not json")
    with pytest.raises(InputError, match="unreadable"):
        read_calibration(model, sha)


def _config(verify: VerifyConfig, **rest: object) -> LocalizerConfig:
    """A localiser's config that verifies as ``verify`` says."""
    return LocalizerConfig(verify=VerifySection.of(verify, **rest))
