"""localization.verify: the confidence worked by hand, the cascade's early stop, the bounded
cache of prepared clouds. Registrations are real (small_gicp) on the street scenes of
test_registration; what a test expects is known from how the scene was built."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pnvlad_service.localization.verify import registration as reg
from pnvlad_service.localization.verify.verify import (
    Candidate,
    Check,
    PreparedCache,
    QueryCloud,
    VerifyConfig,
    confidence,
    verify,
)
from tests.localization import submap_pairs as sp
from tests.localization.test_registration import moved, street

pytest.importorskip("small_gicp")


def _at(x: float, y: float) -> np.ndarray:
    t = np.eye(4)
    t[:2, 3] = [x, y]
    return t


def test_confidence_by_hand() -> None:
    cfg = VerifyConfig(constraint_ref=0.1, rival_m=10.0)
    poses = {1: _at(100.0, 0.0), 2: _at(103.0, 0.0), 3: _at(0.0, 0.0)}
    best = Check(1, 0.6, 0.1, np.eye(4), constraint=0.05)  # puts the query at (100, 0)
    agree = Check(2, 0.5, 0.1, _at(-2.0, 0.0), constraint=0.5)  # (101, 0): 1 m away, no rival
    rival = Check(3, 0.4, 0.1, _at(40.0, 0.0), constraint=0.5)  # (40, 0): 60 m away
    # 0.6 scaled by min(1, 0.05 / 0.1) = 0.5
    assert confidence([best, agree], poses, cfg) == pytest.approx(0.3)
    # less the rival's 0.4, then scaled: (0.6 - 0.4) * 0.5
    assert confidence([best, agree, rival], poses, cfg) == pytest.approx(0.1)
    pinned = Check(1, 0.6, 0.1, np.eye(4), constraint=0.3)
    assert confidence([pinned, rival], poses, cfg) == pytest.approx(0.2)
    # A rival that scores more than the best (ranked after it for being too far) floors at 0.
    assert confidence([pinned, Check(3, 0.9, 0.1, _at(40.0, 0.0))], poses, cfg) == 0.0
    assert confidence([], poses, cfg) == 0.0


@pytest.fixture(scope="module")
def scene() -> dict:
    """A query seeing street(1) from 3 m and 4 degrees off, a true candidate (street(1)) and
    unrelated ones (other streets), all at the map origin."""
    rng = np.random.default_rng(11)
    truth = sp.yaw_matrix(np.radians(4.0), np.array([3.0, -1.0, 0.0]))
    return {
        "query": QueryCloud(moved(street(1), truth, rng), "centroid", "measured"),
        "true": street(1),
        "others": [street(s) for s in (2, 3, 4, 5)],
        "truth": truth,
    }


def _cands(clouds: list[np.ndarray]) -> list[Candidate]:
    return [Candidate(k, c, np.eye(4), key=f"c{k}") for k, c in enumerate(clouds, 1)]


def test_the_cascade_stops_after_the_wave_that_holds_a_sure_match(scene: dict) -> None:
    cands = _cands([scene["true"], *scene["others"]])
    cfg = VerifyConfig(candidates=5, workers=2, stop_score=0.5, threshold=0.2)
    v = verify(scene["query"], cands, cfg)
    assert v.registered == 2 and v.candidates == 5  # wave 1 (ranks 1 and 2) was sure
    assert v.checks[0].rank == 1 and v.checks[0].score > 0.5 and v.verified
    t_err = np.linalg.norm(v.checks[0].transform[:3, 3] - scene["truth"][:3, 3])
    assert t_err < 0.3
    # Without an early stop every candidate is registered, and the answer is the same.
    full = verify(scene["query"], cands, VerifyConfig(candidates=5, workers=2, stop_score=None))
    assert full.registered == 5 and full.checks[0].rank == 1
    assert np.allclose(full.checks[0].transform, v.checks[0].transform)


def test_one_at_a_time_the_cascade_still_registers_a_second_candidate(scene: dict) -> None:
    """The second registered candidate is the rival the confidence is measured against, so
    the cascade stops after two even when the first is sure, unless the first stands alone:
    it scores ``alone_score`` and pins the translation; asked to, it stops after one."""
    cands = _cands([scene["true"], *scene["others"]])
    base = VerifyConfig(candidates=5, workers=1, stop_score=0.5, alone_score=None)
    v = verify(scene["query"], cands, base)
    assert v.registered == 2 and v.checks[0].rank == 1 and v.verified
    first = v.checks[0]
    assert first.score > 0.5 and first.constraint > 0.0  # the scene's fit: sure and pinned
    # Alone: the first's score and constraint both reach the bars, so nothing else is needed.
    alone = replace(base, alone_score=first.score - 0.01, constraint_ref=first.constraint / 2)
    lone = verify(scene["query"], cands, alone)
    assert lone.registered == 1 and lone.verified and lone.checks[0].rank == 1
    assert lone.confidence == pytest.approx(first.score, abs=2e-3)  # no rival, fully pinned
    # With no early stop (stop_score None) every candidate is registered, alone or not.
    assert verify(scene["query"], cands, replace(alone, stop_score=None)).registered == 5
    # Either bar unmet: the second is registered as before.
    for unmet in (
        replace(alone, alone_score=first.score + 0.01),
        replace(alone, constraint_ref=first.constraint * 2),
    ):
        assert verify(scene["query"], cands, unmet).registered == 2
    single = replace(base, min_registered=1)
    assert verify(scene["query"], cands, single).registered == 1
    with pytest.raises(ValueError, match="min_registered"):
        VerifyConfig(min_registered=0)
    with pytest.raises(ValueError, match="alone_score"):
        VerifyConfig(alone_score=1.5)


def test_the_cascade_goes_on_while_nothing_is_sure(scene: dict) -> None:
    # The true place is retrieved 4th: waves (1, 2) and (3, 4) are needed, then it stops.
    clouds = [*scene["others"][:3], scene["true"], scene["others"][3]]
    cfg = VerifyConfig(candidates=5, workers=2, stop_score=0.5)
    v = verify(scene["query"], _cands(clouds), cfg)
    assert v.registered == 4 and v.checks[0].rank == 4
    assert sorted(c.rank for c in v.checks) == [1, 2, 3, 4]
    # Handed over in any order, candidates are registered in retrieval order.
    shuffled = list(reversed(_cands(clouds)))
    again = verify(scene["query"], shuffled, cfg)
    assert sorted(c.rank for c in again.checks) == [1, 2, 3, 4]
    # One worker: waves of one, so it stops right after rank 4.
    one = verify(scene["query"], _cands(clouds), VerifyConfig(workers=1, stop_score=0.5))
    assert one.registered == 4


def test_the_crowded_config_gives_the_same_answer_on_one_thread(scene: dict) -> None:
    """Under load the Localizer registers on ``crowded_threads`` (1) instead of
    ``registration.threads`` (2): only the speed may change, not the answer."""
    cfg = VerifyConfig(candidates=5, stop_score=None)
    crowded = cfg.crowded()
    assert crowded.registration.threads == 1 and cfg.registration.threads == 2
    assert crowded.candidates == cfg.candidates and crowded.threshold == cfg.threshold
    assert VerifyConfig(crowded_threads=None).crowded().registration.threads == 2
    cands = _cands([*scene["others"][:2], scene["true"], *scene["others"][2:]])
    a, b = verify(scene["query"], cands, cfg), verify(scene["query"], cands, crowded)
    assert [c.rank for c in a.checks] == [c.rank for c in b.checks] and a.checks[0].rank == 3
    for x, y in zip(a.checks, b.checks, strict=True):
        assert x.score == pytest.approx(y.score, abs=2e-3)
        assert np.allclose(x.transform, y.transform, atol=1e-3)
    assert a.verified == b.verified and a.confidence == pytest.approx(b.confidence, abs=2e-3)
    with pytest.raises(ValueError, match="crowded_threads"):
        VerifyConfig(crowded_threads=0)


def test_prepared_cache_is_lru_and_bounded() -> None:
    cache = PreparedCache(2)
    cache["a"] = 1
    cache["b"] = 2
    assert cache.get("a") == 1  # a is now the most recent
    cache["c"] = 3  # evicts b
    assert cache.get("b") is None and cache.get("a") == 1 and cache.get("c") == 3
    assert len(cache) == 2 and cache.hits == 3 and cache.misses == 1
    none = PreparedCache(0)
    none["a"] = 1
    assert none.get("a") is None and len(none) == 0
    with pytest.raises(ValueError, match="max_entries"):
        PreparedCache(-1)


def test_verify_reuses_prepared_candidates_from_the_cache(scene: dict, monkeypatch) -> None:
    cands = _cands([scene["true"], *scene["others"]])
    cfg = VerifyConfig(candidates=5, workers=1, stop_score=None)
    cache = PreparedCache(16)
    first = verify(scene["query"], cands, cfg, cache=cache)
    assert len(cache) == 5  # the five targets (the query has no key)
    made = []
    real = reg.prepare

    def counting(points, config=reg.DEFAULT, role="both"):
        made.append(role)
        return real(points, config, role)

    monkeypatch.setattr(reg, "prepare", counting)
    second = verify(scene["query"], cands, cfg, cache=cache)
    assert made == ["source"]  # only the query was prepared again
    assert [c.rank for c in second.checks] == [c.rank for c in first.checks]
    assert [c.score for c in second.checks] == pytest.approx([c.score for c in first.checks])
