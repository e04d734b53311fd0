"""The recorded poses' steps refined by registering each scan onto the one before it."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pnvlad_service.localization.drive.scan_steps import ScanStepConfig, ScanSteps, StepsAhead
from pnvlad_service.localization.verify.registration import apart


def _street(rng: np.random.Generator) -> np.ndarray:
    """A street 200 m long: two facades with doorways and recesses of random widths, trees'
    trunks and parked vans at random along it, a ground plane."""
    parts = []
    for side in (-8.0, 8.0):
        x = rng.uniform(-20, 220, 40000)
        edges = np.sort(rng.uniform(-20, 220, 40))
        recessed = np.searchsorted(edges, x) % 2 == 1  # every other stretch set back
        depth = side + np.sign(side) * rng.choice([1.0, 2.5]) * recessed
        parts.append(np.c_[x, depth, rng.uniform(0, 10, len(x))])
    for x0 in rng.uniform(-20, 220, 50):  # trees' trunks, poles
        a = rng.uniform(0, 2 * math.pi, 400)
        y0 = rng.uniform(4.5, 6.5) * rng.choice([-1, 1])
        r = rng.uniform(0.15, 0.5)
        parts.append(np.c_[x0 + r * np.cos(a), y0 + r * np.sin(a), rng.uniform(0, 5, 400)])
    for x0 in rng.uniform(-20, 220, 25):  # parked vans
        p = rng.uniform(0, 1, (1500, 3)) * [rng.uniform(3, 6), 2.0, rng.uniform(1.4, 2.6)]
        parts.append(p + np.array([x0, rng.choice([-6.5, 4.5]), 0.0]))
    ground = np.c_[rng.uniform(-20, 220, 20000), rng.uniform(-8, 8, 20000), np.zeros(20000)]
    parts.append(ground)
    return np.concatenate(parts)


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:3, 3] = (x, y, 1.8)
    return t


def _scan(world: np.ndarray, pose: np.ndarray, reach_m: float = 40.0) -> np.ndarray:
    """The world's points within reach of the sensor, in the sensor's frame, thinning with
    range as a spinning sensor's rings do (kept with probability (8 / range)^2), the same
    points for the same pose."""
    d = np.linalg.norm(world[:, :2] - pose[:2, 3], axis=1)
    keep = np.random.default_rng(int(abs(pose[0, 3]) * 1000)).random(len(world))
    near = world[(d < reach_m) & (keep < (8.0 / np.maximum(d, 8.0)) ** 2)]
    inv = np.linalg.inv(pose)
    return near @ inv[:3, :3].T + inv[:3, 3]


def _step_error(a: np.ndarray, b: np.ndarray, ta: np.ndarray, tb: np.ndarray) -> float:
    """Metres between the step from pose a to b and the true step from ta to tb."""
    d = np.linalg.inv(np.linalg.inv(ta) @ tb) @ (np.linalg.inv(a) @ b)
    return float(np.linalg.norm(d[:3, 3]))


@pytest.fixture(scope="module")
def drive() -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(4)
    world = _street(rng)
    truth = [_pose(10 + 2.5 * k, 0.3 * math.sin(k / 5), 2.0 * math.sin(k / 7)) for k in range(12)]
    # the recording: the truth with a wandering error of decimetres a step (a GNSS/INS)
    walk = np.cumsum(rng.normal(0, 0.3, (12, 2)), axis=0)
    recorded = []
    for t, e in zip(truth, walk, strict=True):
        r = t.copy()
        r[:2, 3] += e
        recorded.append(r)
    return world, truth, recorded


def test_each_step_is_the_scans_not_the_recordings(drive) -> None:
    world, truth, recorded = drive
    steps = ScanSteps()
    chain = [steps.update(_scan(world, t), r) for t, r in zip(truth, recorded, strict=True)]
    assert np.allclose(chain[0], recorded[0])  # the chain starts where the recording does
    raw = [_step_error(recorded[k], recorded[k + 1], truth[k], truth[k + 1]) for k in range(11)]
    refined = [_step_error(chain[k], chain[k + 1], truth[k], truth[k + 1]) for k in range(11)]
    assert np.median(raw) > 0.2  # the recording's steps are decimetres off
    assert max(refined) < 0.05  # the scans' steps are centimetres off
    assert steps.refined == 11 and steps.kept == 0


@pytest.mark.parametrize("off_m", [1.0, -1.2])
def test_a_recorded_step_a_metre_off_is_started_from_the_last_ones_shift(drive, off_m) -> None:
    """Along a street the registration from a start a metre off stays about a metre off; the
    last refined step's shift (the vehicle's motion changes little between scans) starts it
    right."""
    world, truth, _ = drive
    recorded = [t.copy() for t in truth[:6]]
    for r in recorded[4:]:
        r[0, 3] += off_m  # the recording jumps along the street between scans 3 and 4
    errors = {}
    for name, carry in (("recorded", False), ("carried", True)):
        steps = ScanSteps(ScanStepConfig(carry_shift=carry))
        chain = [steps.update(_scan(world, t), r) for t, r in zip(truth, recorded, strict=False)]
        errors[name] = _step_error(chain[3], chain[4], truth[3], truth[4])
    assert errors["recorded"] > 0.5  # what the carried shift is for
    assert errors["carried"] < 0.05


def test_a_stop_the_carried_shift_misses_is_started_from_the_recording(drive) -> None:
    """The vehicle stops between two scans: the last step's shift carried on starts the
    registration 2.5 m ahead, where the street's facades leave it, beyond the gate; the
    recorded step (right here) starts it again and the step is the scans' own."""
    world, truth, _ = drive
    poses = [t.copy() for t in truth[:5]] + [truth[4].copy()]  # scan 5 where scan 4 was
    steps = ScanSteps()
    chain = [steps.update(_scan(world, t), t) for t in poses]
    assert _step_error(chain[4], chain[5], poses[4], poses[5]) < 0.05
    assert steps.refined == 5 and steps.kept == 0


def test_a_step_the_scans_cannot_confirm_is_the_recorded_one(drive) -> None:
    world, truth, recorded = drive
    steps = ScanSteps()
    steps.update(_scan(world, truth[0]), recorded[0])
    empty = np.zeros((0, 3))  # a dropped scan: nothing to register
    second = steps.update(empty, recorded[1])
    assert np.allclose(second, recorded[1])  # the chain started at recorded[0]: its step
    assert steps.kept == 1
    # the gate: a registration may not move the recorded step by more than gate_m
    tight = ScanSteps(ScanStepConfig(gate_m=0.01))
    tight.update(_scan(world, truth[0]), recorded[0])
    out = tight.update(_scan(world, truth[1]), recorded[1])
    assert np.allclose(out, recorded[1]) and tight.kept == 1


def test_a_scan_without_a_recorded_pose_breaks_the_chain(drive) -> None:
    world, truth, recorded = drive
    steps = ScanSteps()
    steps.update(_scan(world, truth[0]), recorded[0])
    assert steps.update(_scan(world, truth[1]), None) is None
    restart = steps.update(_scan(world, truth[2]), recorded[2])
    assert np.allclose(restart, recorded[2])  # started again, not stepped from scan 0


def test_a_straight_step_takes_the_near_points_a_turning_one_all(drive) -> None:
    """``near_m`` / ``turning_deg``: the street's steps turn by tenths of a degree; with
    ``near_m`` 1 m a straight step has only the few ground points under the sensor (too few to
    register) and keeps the recorded step, while the same steps taken as turning ones
    (``turning_deg`` 0) or with every point (``near_m`` None) use all the points and are
    refined."""
    world, truth, recorded = drive
    scans = [_scan(world, t) for t in truth]
    turns = [apart(b, a)[1] for a, b in itertools.pairwise(recorded)]
    assert min(turns) > 0 and max(turns) < ScanStepConfig.turning_deg
    for near, turning, refined in ((1.0, 2.0, False), (1.0, 0.0, True), (None, 2.0, True)):
        steps = ScanSteps(ScanStepConfig(near_m=near, turning_deg=turning))
        chain = [steps.update(p, r) for p, r in zip(scans, recorded, strict=True)]
        assert (steps.refined == len(scans) - 1) is refined, (near, turning, steps.refined)
        if not refined:
            assert steps.kept == len(scans) - 1
            for a, b in zip(chain, recorded, strict=True):
                assert _step_error(chain[0], a, recorded[0], b) < 1e-9


def test_bad_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="min_fitness"):
        ScanStepConfig(min_fitness=1.5)
    with pytest.raises(ValueError, match="gate_m"):
        ScanStepConfig(gate_m=0)
    with pytest.raises(ValueError, match="near_m"):
        ScanStepConfig(near_m=0.0)
    with pytest.raises(ValueError, match="turning_deg"):
        ScanStepConfig(turning_deg=-1.0)


def test_steps_taken_in_a_worker_are_the_same(drive) -> None:
    """The worker's chain is this process's to a few millimetres (small_gicp's two threads
    make the registrations themselves vary by that much from one run to the next)."""
    world, truth, recorded = drive
    here = ScanSteps()
    expected = [here.update(_scan(world, t), r) for t, r in zip(truth, recorded, strict=True)]
    with StepsAhead() as worker:
        futures = [worker.submit(_scan(world, t), r) for t, r in zip(truth, recorded, strict=True)]
        got = [f.result(timeout=60) for f in futures]
    assert max(np.abs(a - b).max() for a, b in zip(got, expected, strict=True)) < 0.01
    with StepsAhead() as worker:  # a scan without a pose breaks the worker's chain too
        assert worker.submit(_scan(world, truth[0]), None).result(timeout=60) is None


def test_a_worker_that_cannot_start_says_why(tmp_path) -> None:
    """A script that makes the worker at its top level, without the ``__main__`` guard: the
    worker, importing the script again, cannot start one of its own; the script fails with
    an error that names the guard (not a bare BrokenProcessPool at its first step)."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(
        "from pnvlad_service.localization.drive.scan_steps import StepsAhead\n"
        "StepsAhead().close()\n"
        "print('started')\n"
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode != 0
    assert "did not start" in done.stderr and "if __name__ == '__main__':" in done.stderr
    assert "started" not in done.stdout
    guarded = tmp_path / "guarded.py"
    guarded.write_text(
        "from pnvlad_service.localization.drive.scan_steps import StepsAhead\n"
        "if __name__ == '__main__':\n"
        "    StepsAhead().close()\n"
        "    print('started')\n"
    )
    done = subprocess.run(
        [sys.executable, str(guarded)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and "started" in done.stdout, done.stderr


class _StreetDrive:
    """The street's scans with their recorded poses; each scan's first point names its index
    (as the stand-in service reads it back)."""

    name = "street"

    def __init__(self, world: np.ndarray, truth: list, recorded: list) -> None:
        self.world, self.truth = world, truth
        self.timestamps = np.arange(len(truth), dtype=np.int64) * 250_000
        self.poses = np.stack(recorded)

    def scan(self, i: int) -> np.ndarray:
        return np.vstack([np.full((1, 3), float(i)), _scan(self.world, self.truth[i])])


@pytest.mark.parametrize("every", [1, 2])
def test_a_follow_with_its_steps_taken_ahead_asks_the_same(drive, every) -> None:
    """The runner hands each scan to the worker while the scan before it is localised: the
    service is asked about the same scans with the same predictions (to the few millimetres
    the registrations vary by) as when the steps are taken in turn, and they are not the
    recorded steps' predictions (the worker's steps are used)."""
    from pnvlad_service.localization.drive.runner import run_drive
    from tests.localization.stand_in import Service

    world, truth, recorded = drive
    calls = {}
    for name, odometry, ahead in [
        ("in turn", "registered", False),
        ("ahead", "registered", True),
        ("recorded", "poses", False),
    ]:
        svc = Service(right=set(range(12)), reach=2.0, scan_truth=lambda i: truth[i])
        street = _StreetDrive(world, truth, recorded)
        rows = run_drive(
            street, svc, "tracked", every=every, odometry=odometry, ahead=ahead, progress=False
        )
        assert [r.scan for r in rows] == list(range(0, 12, every))
        calls[name] = [(i, p and (p.easting, p.northing)) for i, p in svc.calls]

    def apart(a: list, b: list) -> float:
        assert [(i, p is None) for i, p in a] == [(i, p is None) for i, p in b]
        return max(math.dist(p, q) for (_, p), (_, q) in zip(a, b, strict=True) if p is not None)

    assert sum(p is not None for _, p in calls["ahead"]) >= 3  # it tracked with predictions
    assert apart(calls["ahead"], calls["in turn"]) < 0.01
    assert apart(calls["ahead"], calls["recorded"]) > 0.1
