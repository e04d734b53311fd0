"""A followed scan's filter G taken one scan ahead in a worker (localization/drive/ahead.py):
the worker's G is the localiser's own to the bit, a scan it refuses is left to the localiser
(which says why, as it would), and a follow of a bundle in this process asks the same questions
and gets the same answers with G taken ahead as in turn, without running G itself."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.localization.drive.ahead import ScansAhead, filtered
from pnvlad_service.localization.drive.runner import run_drive
from pnvlad_service.localization.drive.service import local_ask
from pnvlad_service.localization.query.localizer import Localizer
from pnvlad_service.preprocess import filter_g

SCANS = 14


class FirstScans:
    """The first ``n`` scans of a simulated drive, with its poses and true poses."""

    def __init__(self, drive, n: int) -> None:
        self.drive, self.name = drive, drive.name
        self.timestamps = drive.timestamps[:n]
        self.poses = drive.poses[:n]
        self.true_poses = drive.true_poses[:n]

    def scan(self, i: int) -> np.ndarray:
        return self.drive.scan(i)


@pytest.fixture(scope="module")
def drive():
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    return FirstScans(simulated_drive(get_preset("tiny"), 0, 0, 3), SCANS)  # held out


def test_the_workers_g_is_the_localisers_own(tiny_maps: dict, drive) -> None:
    """Bit for bit, on a plain scan, one with missing returns written as zeros (dropped first,
    as a query drops them) and one G refuses (None: the localiser is left to refuse it)."""
    plain = drive.scan(3)
    zeros = np.r_[drive.scan(5), np.zeros((500, 3), dtype=np.float32)]
    too_few = drive.scan(6)[:10]
    with Localizer.load(tiny_maps["keys"]) as loc, ScansAhead(None, loc.g_config) as worker:
        got = [worker.submit(p, None).result(timeout=120) for p in (plain, zeros, too_few)]
        for points, ahead in zip((plain, zeros), got, strict=False):
            assert ahead.step is None  # no steps asked for
            expected = loc.prepare(_returns_only(points), True)
            here = loc.prepare(points, True, filtered=ahead.filtered)
            assert np.array_equal(here.cloud, expected.cloud)
            assert np.array_equal(here.centre, expected.centre) and here.scale == expected.scale
        assert got[2].filtered is None and filtered(too_few, loc.g_config) is None


def _returns_only(points: np.ndarray) -> np.ndarray:
    kept = points[np.linalg.norm(points, axis=1) > 0.01]
    return np.ascontiguousarray(kept, dtype=np.float64)


def test_a_follow_takes_g_ahead_and_answers_as_in_turn(
    tiny_maps: dict, drive, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The held-out drive followed from its true first pose on the recorded poses: the same
    states, registrations and poses with G taken in the worker as in this process, and this
    process runs G for no scan of it (it did for every one in turn)."""
    ran = []
    apply_g = filter_g.apply_g

    def counted(*args, **kwargs):
        ran.append(1)
        return apply_g(*args, **kwargs)

    monkeypatch.setattr(filter_g, "apply_g", counted)
    rows, runs = {}, {}
    with Localizer.load(tiny_maps["keys"]) as loc:
        for ahead in (False, True):
            ran.clear()
            rows[ahead] = run_drive(
                drive, local_ask(loc), "tracked", odometry="poses", truth=drive.true_poses,
                initial_pose=drive.true_poses[0], ahead=ahead, progress=False,
            )  # fmt: skip
            runs[ahead] = len(ran)
    assert runs == {False: SCANS, True: 0}
    a, b = rows[False], rows[True]
    assert [(r.state, r.verified, r.how) for r in a] == [(r.state, r.verified, r.how) for r in b]
    assert sum(r.verified for r in a) >= SCANS // 2  # it tracked
    for x, y in zip(a, b, strict=True):
        if x.pose_easting is not None:
            # Registrations on small_gicp's two threads vary by a few millimetres a run.
            assert abs(x.pose_easting - y.pose_easting) < 0.01
            assert abs(x.pose_northing - y.pose_northing) < 0.01
            assert x.fitness == pytest.approx(y.fitness, abs=0.01)
