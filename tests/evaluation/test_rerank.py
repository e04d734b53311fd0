"""evaluation.rerank: queries registered and re-ranked, the outcome of one by hand, the
calibration's off-map queries, and pnvlad eval --rerank end to end on the tiny city (the
figures on hand-worked outcomes: test_rerank_figures.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pnvlad_service.evaluation.rerank import _outcome
from pnvlad_service.localization.verify.verify import Check, Verification, rerank


def test_rerank_orders_by_score_then_retrieval_rank() -> None:
    eye = np.eye(4)
    checks = [Check(1, 0.2, 0.1, eye), Check(2, 0.9, 0.1, eye), Check(3, 0.9, 0.1, eye)]
    assert [c.rank for c in rerank(checks)] == [2, 3, 1]
    # A candidate that places the query 30 m from its origin is another place: after those
    # within the radius, whatever its score.
    far = np.eye(4)
    far[:2, 3] = [18.0, 24.0]
    checks = [Check(1, 0.2, 0.1, eye), Check(2, 0.9, 0.1, far), Check(3, 0.5, 0.1, eye)]
    assert [c.rank for c in rerank(checks, 25.0)] == [3, 1, 2]
    assert [c.rank for c in rerank(checks)] == [2, 3, 1]


def test_off_map_verification_offers_only_far_candidates(tiny, tmp_path) -> None:
    """rerank_pairs(off_map_m): every candidate of every query is farther than off_map_m from
    it, so no re-ranked answer is right; an off_map_m beyond the city leaves no query."""
    from pnvlad_service.data.dataset import load_eval_runs
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.evaluation.evaluate import embed_runs
    from pnvlad_service.evaluation.rerank import rerank_pairs
    from pnvlad_service.localization.verify.verify import VerifyConfig
    from pnvlad_service.models.inference import Encoder
    from tests.index.helpers import make_checkpoint

    enc = Encoder.from_checkpoint(make_checkpoint(tmp_path / "ckpt"), device="cpu")
    runs = load_eval_runs(tiny)[:2]
    _, db, q = embed_runs(enc.embed, runs, enc.cfg.num_points, 1, False)
    frames = BenchmarkTree(tiny).frames_by_path()
    config = VerifyConfig(candidates=3, stop_score=None)
    on, _ = rerank_pairs(runs, db, q, frames, config)
    assert any(o.r1_after for o in on)  # on the map, some are right
    off, _ = rerank_pairs(runs, db, q, frames, config, off_map_m=50.0)
    assert off and len(off) <= len(on)
    assert not any(o.r1_after or o.r1p_after or o.rk_before for o in off)
    assert all(o.registered == 3 for o in off)  # stop_score None: all three registered
    far, _ = rerank_pairs(runs, db, q, frames, config, off_map_m=1e9)
    assert far == []


def test_outcome_uses_the_reranked_top1_and_the_true_relative_pose() -> None:
    from pnvlad_service.data.frames import SubmapFrame

    def frame(x: float, yaw: float) -> SubmapFrame:
        return SubmapFrame(0, np.zeros(3), np.zeros(3), 1.0, "enu", np.array([x, 0.0, 0.0]), yaw)

    q = frame(5.0, 180.0)  # the query drove the other way, 5 m east of the origin
    dbf = [frame(100.0, 0.0), frame(0.0, 0.0)]
    rel = np.linalg.inv(dbf[1].true_pose) @ q.true_pose
    est = rel.copy()
    est[0, 3] += 0.3  # 0.3 m off
    v = Verification(True, (Check(2, 0.9, 0.1, est), Check(1, 0.1, 0.9, np.eye(4))), None, 0.5)
    ranked = np.array([7, 3, 9])  # retrieval: row 7 first (wrong), row 3 second (true)
    out = _outcome(0, ranked, np.array([3]), 1, v, q, dbf)
    assert not out.r1_before and out.r1_after and out.rk_before
    assert not out.r1p_before and out.r1p_after  # n1 = 1
    assert out.t_err == pytest.approx(0.3) and out.yaw_err == pytest.approx(0.0, abs=1e-9)
    assert out.pose_ok and not math.isnan(out.best_score)
    # A far-off estimate: the pose is wrong, whatever the place label says.
    est[0, 3] += 3.0
    assert _outcome(0, ranked, np.array([3]), 1, v, q, dbf).pose_ok is False


def test_eval_rerank_on_the_tiny_city(tiny, tmp_path, monkeypatch) -> None:
    """`pnvlad eval --rerank` end to end: the threshold comes from the training layout, the
    report holds every figure the issue names, and the figures are drawn; the registration's
    OpenMP threads sleep at barriers unless the user said otherwise."""
    import json

    from typer.testing import CliRunner

    from pnvlad_cli.main import app
    from tests.index.helpers import make_checkpoint

    monkeypatch.setenv("OMP_WAIT_POLICY", "unset")  # restored after the test, then cleared
    monkeypatch.delenv("OMP_WAIT_POLICY")
    ckpt = make_checkpoint(tmp_path / "ckpt")
    out = tmp_path / "rep.json"
    args = ["eval", "-m", str(ckpt), "-r", str(tiny), "--rerank", "5", "--no-progress"]
    args += ["--calibration-queries", "8", "-o", str(out), "--figures", str(tmp_path / "f")]
    res = CliRunner().invoke(app, [*args, "--save-threshold"])
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())["rerank"]
    # --save-threshold: the chosen threshold beside the weights, for these weights.
    from pnvlad_service.localization.query.calibration import read_calibration
    from pnvlad_service.models.store import weights_sha256

    saved = read_calibration(ckpt, weights_sha256(ckpt))
    assert saved is not None and saved.threshold == rep["calibration"]["threshold"]
    assert saved.candidates == 5 and saved.n_queries == rep["calibration"]["n_queries"]
    assert f"written to {ckpt / 'verification.json'}" in res.output
    assert rep["candidates"] == 5
    assert rep["omp_wait_policy"] == "PASSIVE"
    cal = rep["calibration"]
    assert cal["n_queries"] > 0 and 0.0 <= cal["threshold"] <= 1.0
    assert rep["verified"]["threshold"] == cal["threshold"]
    # Off-map queries weighed in: their share, count and acceptance at the chosen threshold,
    # which a curve row of their own repeats.
    from pnvlad_service.evaluation.rerank_figures import OFF_MAP_SHARE

    off = cal["off_map"]
    assert off["share"] == OFF_MAP_SHARE and off["n_queries"] > 0 and len(off["curve"]) == 101
    row = dict((round(t, 2), a) for t, a in off["curve"])[round(cal["threshold"], 2)]
    assert cal["at_threshold"]["off_map_accept"] == pytest.approx(row)
    assert f"planned as {100 * OFF_MAP_SHARE:g} % of queries" in res.output
    assert saved.at_threshold["off_map_accept"] == pytest.approx(row)
    # The ceiling: re-ranking the top 5 cannot beat recall@5 before it.
    assert rep["recall_at_1_after"] <= rep["recall_at_k_before"] + 1e-9
    assert rep["recall_at_1_before"] <= rep["recall_at_k_before"] + 1e-9
    assert rep["metric"]["n"] >= 0 and len(rep["pr_curve"]) == 101
    assert "re-ranking top 5" in res.output
    assert (tmp_path / "f" / "verified_pr.png").stat().st_size > 1000
    assert (tmp_path / "f" / "pose_errors.png").stat().st_size > 1000
    # The help names the library's calibration default, not a copy that drifts from it.
    from pnvlad_service.evaluation.rerank import CALIBRATION_QUERIES

    helped = CliRunner().invoke(app, ["eval", "--help"], env={"COLUMNS": "200"})
    assert f"(default: {CALIBRATION_QUERIES}," in helped.output
    assert f"(default: {OFF_MAP_SHARE};" in " ".join(helped.output.split())
    # A share outside [0, 1) is refused naming the flag; 0 leaves the off-map queries out.
    res = CliRunner().invoke(app, [*args, "--off-map-share", "1.5"])
    assert res.exit_code == 2 and "--off-map-share" in res.output
    res = CliRunner().invoke(app, [*args, "--off-map-share", "0"])
    assert res.exit_code == 0, res.output
    assert "off_map" not in json.loads(out.read_text())["rerank"]["calibration"]
    # ... and serve's help the library's fallback threshold.
    from pnvlad_service.localization.verify.verify import VerifyConfig

    served = CliRunner().invoke(app, ["serve", "--help"], env={"COLUMNS": "200"})
    assert f"else {VerifyConfig.threshold}," in " ".join(served.output.split())
    # A threshold to save must be chosen here.
    res = CliRunner().invoke(app, [*args, "--save-threshold", "--verify-threshold", "0.2"])
    assert res.exit_code == 2 and "--save-threshold" in res.output
    # Asked of a tree without sidecars, or without --root: exit 2 naming the flag.
    res = CliRunner().invoke(app, ["eval", "-m", str(ckpt), "--rerank", "0", "-r", str(tiny)])
    assert res.exit_code == 2 and "--rerank" in res.output


def test_off_map_descriptors_come_from_the_calibrations_own(tiny, tmp_path) -> None:
    """The off-map queries' descriptors are the calibration runs' rows, equal to embedding
    them afresh; runs with a submap the calibration never embedded are embedded."""
    from pnvlad_service.data.dataset import load_eval_runs
    from pnvlad_service.evaluation.evaluate import embed_runs
    from pnvlad_service.evaluation.rerank import _descriptors_of, subsample_queries
    from pnvlad_service.models.inference import Encoder
    from tests.index.helpers import make_checkpoint

    enc = Encoder.from_checkpoint(make_checkpoint(tmp_path / "ckpt"), device="cpu")
    embedded: list[int] = []

    def embed(rs):
        embedded.append(len(rs))
        _, db, q = embed_runs(enc.embed, rs, enc.cfg.num_points, 1, False)
        return db, q

    runs = load_eval_runs(tiny)[:2]
    db, _ = embed(runs)
    few = subsample_queries(runs, 3, seed=1)
    got_db, got_q = _descriptors_of(few, runs, db, embed)
    assert embedded == [2]  # nothing embedded again
    want_db, want_q = embed(few)
    for a, b in zip([*got_db, *got_q], [*want_db, *want_q], strict=True):
        assert a.shape == b.shape and np.allclose(a, b, atol=1e-5)
    others = load_eval_runs(tiny)[2:3]
    _descriptors_of(others, runs, db, embed)
    assert embedded == [2, 2, 1]
