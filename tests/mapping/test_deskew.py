"""De-skewing the nodes' scans (mapping.deskew): the simulator's own sweep (synth.lidar casts
each column at its time while the vehicle moves) is undone, the motion is read back from the
steps between nodes, and the alignment registers the de-skewed scans of the runs whose sensor
does not de-skew, and only theirs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.mapping.deskew import SWEEP_HZ, deskew_points, run_motion, skewed_sensors
from pnvlad_service.synth.lidar import cast_scan
from pnvlad_service.synth.sensors import LidarConfig
from pnvlad_service.synth.world import KIND_BUILDING, Boxes, Scene
from tests.synth.scenes import CLEAN, FLAT, NO_CYL, NO_ELL, four_walls


def _room_scans(speed: float, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """The same rays and draws of a room of four walls, cast standing still and cast through
    a sweep while moving ``speed`` m/s and turning ``rate`` rad/s (sensor frame)."""
    cfg = LidarConfig(beams=8, columns=720, deskewed=False, **CLEAN)
    scene = four_walls()
    o = np.array([0.0, 0.0, 1.5])
    still = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(3), motion=(0.0, 0.0))
    moved = cast_scan(scene, FLAT, o, 0.0, cfg, np.random.default_rng(3), motion=(speed, rate))
    assert still.shape == moved.shape
    return still.astype(np.float64), moved.astype(np.float64)


def _turned(points: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.stack(
        [c * points[:, 0] - s * points[:, 1], s * points[:, 0] + c * points[:, 1], points[:, 2]],
        1,
    )


@pytest.mark.parametrize("heading", [0.0, 1.1, -2.5])
def test_deskew_undoes_the_simulators_sweep(heading: float) -> None:
    speed, rate = 11.0, 0.35
    still, moved = _room_scans(speed, rate)
    # the keyframes keep the map's axes: the sensor's forward axis lies at ``heading``
    local_still, local_moved = _turned(still, heading), _turned(moved, heading)
    fixed = deskew_points(local_moved, heading, speed, rate)
    # away from the seam behind the vehicle (where a column's time jumps a whole sweep)
    az = np.degrees(np.arctan2(still[:, 1], still[:, 0]))
    keep = np.abs(az) < 175.0
    skew = np.linalg.norm(local_moved - local_still, axis=1)[keep]
    left = np.linalg.norm(fixed - local_still, axis=1)[keep]
    assert np.median(skew) > 0.2  # the sweep moved the points a lot
    assert left.max() < 2e-3, f"{left.max():.4f} m left of the sweep's skew"
    np.testing.assert_array_equal(fixed[:, 2], local_moved[:, 2])


def test_standing_still_changes_nothing() -> None:
    pts = np.random.default_rng(0).normal(0.0, 10.0, (500, 3))
    np.testing.assert_allclose(deskew_points(pts, 0.7, 0.0, 0.0), pts, atol=1e-12)


@pytest.mark.parametrize("turning_frames", [False, True])
def test_motion_is_read_back_from_the_steps(turning_frames: bool) -> None:
    # A constant turn at 8 m/s and 0.2 rad/s, nodes 0.6 s apart; the local frames either keep
    # the map's axes (keyframes) or turn with the vehicle.
    v, w, dt, n = 8.0, 0.2, 0.6, 7
    t = np.arange(n) * dt
    psi = 0.3 + w * t
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = v / w * (np.sin(psi) - np.sin(psi[0]))
    poses[:, 1, 3] = -v / w * (np.cos(psi) - np.cos(psi[0]))
    if turning_frames:
        for k in range(n):
            c, s = math.cos(psi[k]), math.sin(psi[k])
            poses[k, :2, :2] = [[c, -s], [s, c]]
    steps = [np.linalg.inv(poses[k]) @ poses[k + 1] for k in range(n - 1)]
    steps[3] = None  # a failed step: the recorded one stands in
    got = run_motion((t * 1e6).astype(np.int64), steps, poses)
    expect_heading = np.zeros(n) if turning_frames else psi
    chord = 2 * v / w * math.sin(w * dt / 2) / dt  # a step's length over its time
    np.testing.assert_allclose(got[1:-1, 0], expect_heading[1:-1], atol=1e-9)
    np.testing.assert_allclose(got[:, 1], chord, rtol=1e-5)  # stamps in microseconds
    np.testing.assert_allclose(got[:, 2], w, rtol=1e-5)


def test_a_synthetic_tree_says_which_sensors_skew(tmp_path: Path) -> None:
    meta = {
        "preset": {
            "lidar": {"name": "", "beams": 32, "deskewed": True},
            "lidars": [
                {"name": "VLP-16", "beams": 16, "deskewed": False},
                {"name": "fast", "beams": 16, "deskewed": False, "rotation_hz": 20.0},
            ],
        },
        "runs": [
            {"area": "a", "run": "r1", "sensor": "VLP-16"},
            {"area": "a", "run": "r2", "sensor": "32 beams"},
            {"area": "a", "run": "r3", "sensor": "fast"},
        ],
    }
    (tmp_path / "synth.json").write_text(json.dumps(meta))
    assert skewed_sensors(tmp_path) == {"a/r1": 10.0, "a/r2": 0.0, "a/r3": 20.0}
    assert skewed_sensors(tmp_path / "nothing") is None


def test_the_alignment_deskews_only_skewed_runs(tiny: Path) -> None:
    pytest.importorskip("gtsam")
    from dataclasses import replace

    from pnvlad_service.mapping.align import AlignConfig, deskewed_nodes
    from pnvlad_service.mapping.edges import Edge
    from pnvlad_service.mapping.nodes import MapNodes, read_tree_nodes

    nodes = read_tree_nodes(tiny)  # the tiny preset's sensor de-skews (synth.json)
    assert not any(r.skewed for r in nodes.runs)
    odometry = [
        Edge("odometry", g, g + 1, np.linalg.inv(nodes.poses[g]) @ nodes.poses[g + 1], None, 1, 1)
        for s, r in zip(nodes.starts(), nodes.runs, strict=True)
        for g in range(s, s + len(r) - 1)
    ]
    assert deskewed_nodes(nodes, odometry, AlignConfig(sweep_hz=SWEEP_HZ)) is None
    # the prepared keyframes carry the motion the recording's poses give (without it, below)
    recorded = nodes.runs[0].recorded_motion
    assert recorded is not None
    one = MapNodes([replace(nodes.runs[0], skewed=True), *nodes.runs[1:]])
    by_record = deskewed_nodes(one, odometry, AlignConfig(sweep_hz=SWEEP_HZ))
    assert by_record is not None
    np.testing.assert_array_equal(by_record.runs[0].motion, recorded)
    # by default a run is de-skewed at its sensor's rate where the tree records one
    assert nodes.runs[0].sensor_hz == 0.0  # the tiny preset's sensor de-skews
    rated = MapNodes([replace(nodes.runs[0], skewed=True, sensor_hz=20.0), *nodes.runs[1:]])
    auto = deskewed_nodes(rated, odometry, AlignConfig())
    assert auto is not None and auto.runs[0].sweep_hz == 20.0
    assert deskewed_nodes(rated, odometry, AlignConfig(sweep_hz=0.0)) is None
    one = MapNodes([replace(nodes.runs[0], skewed=True, recorded_motion=None), *nodes.runs[1:]])
    assert deskewed_nodes(one, odometry, AlignConfig()) is None  # no rate: off unless asked
    out = deskewed_nodes(one, odometry, AlignConfig(sweep_hz=SWEEP_HZ))
    assert out is not None and out.runs[0].motion is not None
    assert all(r.motion is None for r in out.runs[1:])
    # the first run's scans are de-skewed by the motion its steps give, the others' untouched
    first = one.runs[0]
    steps = [e.transform for e in odometry[: len(first) - 1]]
    motion = run_motion(first.stamps, steps, first.poses)
    np.testing.assert_array_equal(out.runs[0].motion, motion)
    k = len(first) // 2
    assert 3.0 < motion[k, 1] < 15.0  # m/s: the recorded steps over their times
    expect = deskew_points(first.metres(k), *motion[k])
    np.testing.assert_array_equal(out.runs[0].metres(k), expect)
    assert np.median(np.linalg.norm(expect - first.metres(k), axis=1)) > 0.05
    np.testing.assert_array_equal(out.runs[1].metres(0), nodes.runs[1].metres(0))


def _street() -> Scene:
    """Buildings along both sides of a street curving on a 60 m radius."""
    rng = np.random.default_rng(0)
    centres, halves, yaws = [], [], []
    for a in np.linspace(-0.9, 0.9, 24):
        for radius in (51.0 - rng.uniform(0, 3), 69.0 + rng.uniform(0, 3)):
            centres.append([radius * math.sin(a), 60.0 - radius * math.cos(a)])
            halves.append([rng.uniform(1.5, 3.0), rng.uniform(2.0, 4.0)])
            yaws.append(a)
    m = len(centres)
    boxes = Boxes(
        np.array(centres),
        np.array(halves),
        np.tile([[-3.0, 12.0]], (m, 1)),
        np.array(yaws),
        np.full(m, KIND_BUILDING, np.int8),
    )
    return Scene(boxes, NO_CYL, NO_ELL)


def test_the_alignment_recovers_the_still_scans_of_a_turning_drive() -> None:
    # Six keyframes 0.5 s apart of a drive turning at 10 m/s on the street's curve, cast by the
    # simulator through the sweep and standing still (the same rays and draws), laid in the
    # map's axes as keyframes are. The odometry registered on the skewed scans measures the
    # motion; the de-skewed scans are the still ones to a centimetre.
    from pnvlad_service.mapping.align import AlignConfig, deskewed_nodes
    from pnvlad_service.mapping.edges import Clouds, EdgeConfig, odometry_edges
    from pnvlad_service.mapping.nodes import MapNodes, RunNodes

    scene = _street()
    cfg = LidarConfig(beams=16, columns=900, deskewed=False, **CLEAN)
    speed, rate, dt = 10.0, 10.0 / 60.0, 0.5
    moving, still, poses = [], [], []
    for k in range(6):
        heading = -0.4 + rate * dt * k
        pos = np.array([60.0 * math.sin(heading), 60.0 - 60.0 * math.cos(heading), 1.5])
        for out, motion in ((moving, (speed, rate)), (still, (0.0, 0.0))):
            rng = np.random.default_rng(k)
            pts = cast_scan(scene, FLAT, pos, heading, cfg, rng, motion=motion)
            out.append(_turned(pts.astype(np.float64), heading))
        pose = np.eye(4)
        pose[:3, 3] = pos
        poses.append(pose)
    stamps = (np.arange(6) * dt * 1e6).astype(np.int64)
    nodes = MapNodes([RunNodes("d/r", stamps, np.stack(poses), clouds=moving, skewed=True)])
    edges = EdgeConfig()
    odometry = odometry_edges(nodes, Clouds.for_odometry(nodes, edges), edges)
    assert all(e.accepted for e in odometry)
    fixed = deskewed_nodes(nodes, odometry, AlignConfig(sweep_hz=SWEEP_HZ))
    assert fixed is not None
    np.testing.assert_allclose(fixed.runs[0].motion[:, 1], speed, rtol=0.03)
    np.testing.assert_allclose(fixed.runs[0].motion[:, 2], rate, rtol=0.05)
    for k in range(6):
        az = np.degrees(np.arctan2(*_turned(still[k], -(-0.4 + rate * dt * k))[:, 1::-1].T))
        keep = np.abs(az) < 175.0  # away from the seam behind
        before = np.linalg.norm(moving[k] - still[k], axis=1)[keep]
        after = np.linalg.norm(fixed.runs[0].metres(k) - still[k], axis=1)[keep]
        assert np.median(before) > 0.2
        assert np.median(after) < 0.02 and np.percentile(after, 99) < 0.06, k


def test_a_corner_turned_in_a_second_is_deskewed_by_the_recorded_motion() -> None:
    # A 90-degree corner turned in about a second at 8 m/s (the yaw rate peaks at 120 degrees
    # a second), keyframes 0.5 s apart, the recording's poses at 10 Hz. The odometry's steps
    # between keyframes cannot follow the turn (run_motion even from the true steps); the
    # motion the recording gives each keyframe (drive_motion, as prepare writes it) takes
    # the sweep out to a few centimetres.
    from pnvlad_service.data.motion import drive_motion
    from pnvlad_service.mapping.align import AlignConfig, deskewed_nodes
    from pnvlad_service.mapping.edges import Edge
    from pnvlad_service.mapping.nodes import MapNodes, RunNodes

    scene = _street()
    cfg = LidarConfig(beams=16, columns=900, deskewed=False, **CLEAN)
    speed, dt = 8.0, 0.1
    t = np.arange(31) * dt
    # heading: a smooth step of 90 degrees centred at 1.5 s, over about a second
    heading = -0.4 + (math.pi / 2) * 0.5 * (1 + np.tanh((t - 1.5) / 0.3))
    rate = np.gradient(heading, t)
    xy = np.cumsum(speed * dt * np.stack([np.cos(heading), np.sin(heading)], 1), 0)
    xy += np.array([0.0, 5.0])
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :2, :2] = [[[math.cos(h), -math.sin(h)], [math.sin(h), math.cos(h)]] for h in heading]
    poses[:, :2, 3] = xy
    poses[:, 2, 3] = 1.5
    stamps = (t * 1e6).round().astype(np.int64)
    recorded = drive_motion(stamps, poses)
    keys = np.arange(0, len(t), 5)  # keyframes 0.5 s apart
    moving, still, laid = [], [], []
    for i in keys:
        pos = np.array([xy[i, 0], xy[i, 1], 1.5])
        for out, motion in ((moving, (speed, float(rate[i]))), (still, (0.0, 0.0))):
            pts = cast_scan(scene, FLAT, pos, float(heading[i]), cfg, np.random.default_rng(i),
                            motion=motion)  # fmt: skip
            out.append(_turned(pts.astype(np.float64), heading[i]))
        pose = np.eye(4)
        pose[:3, 3] = pos
        laid.append(pose)
    run = RunNodes("d/r", stamps[keys], np.stack(laid), clouds=moving, skewed=True)
    true_steps = [np.linalg.inv(laid[k]) @ laid[k + 1] for k in range(len(keys) - 1)]
    odometry = [Edge("odometry", k, k + 1, s, None, 1, 1) for k, s in enumerate(true_steps)]
    by_steps = deskewed_nodes(MapNodes([run]), odometry, AlignConfig(sweep_hz=SWEEP_HZ))
    assert by_steps is not None
    np.testing.assert_array_equal(by_steps.runs[0].motion, run_motion(run.stamps, true_steps,
                                                                      run.poses))  # fmt: skip
    run.recorded_motion = recorded[keys]
    fixed = deskewed_nodes(MapNodes([run]), odometry, AlignConfig(sweep_hz=SWEEP_HZ))
    assert fixed is not None
    np.testing.assert_array_equal(fixed.runs[0].motion, recorded[keys])
    turning = int(np.argmax(np.abs(rate[keys])))
    assert abs(np.degrees(rate[keys][turning])) > 100
    for k in range(len(keys)):
        az = np.degrees(np.arctan2(*_turned(still[k], -heading[keys[k]])[:, 1::-1].T))
        keep = np.abs(az) < 165.0  # away from the seam behind, which the turn moves 6 degrees
        after = np.linalg.norm(fixed.runs[0].metres(k) - still[k], axis=1)[keep]
        assert np.median(after) < 0.03 and np.percentile(after, 99) < 0.15, k
    # the steps' motion (108 degrees a second at the turn, the truth 145) leaves it smeared
    worse = np.linalg.norm(by_steps.runs[0].metres(turning) - still[turning], axis=1)
    better = np.linalg.norm(fixed.runs[0].metres(turning) - still[turning], axis=1)
    assert np.percentile(worse, 90) > 0.2
    assert np.percentile(worse, 90) > 5 * np.percentile(better, 90)
