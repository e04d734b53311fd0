"""The push-broom line scanner (synth.sensors.PushbroomConfig, synth.linescan, synth.pushbroom)
against hand-computed rays, its checks, and its presets end to end."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest

from pnvlad_service.data.tree import check_tree
from pnvlad_service.errors import InputError
from pnvlad_service.synth.generate import generate, get_preset, simulated_drive
from pnvlad_service.synth.linescan import cast_line, line_fan
from pnvlad_service.synth.presets import AreaSpec
from pnvlad_service.synth.sensors import LMS_FRONT, pushbroom
from pnvlad_service.synth.world import KIND_BUILDING, Boxes, Scene
from tests.synth.scenes import FLAT, NO_CYL, NO_ELL

#: The scanner with none of a real sensor's failures.
PERFECT = {
    "range_noise": 0.0,
    "range_noise_per_100m": 0.0,
    "dropout": 0.0,
    "dropout_far": 0.0,
    "dropout_grazing": 0.0,
    "glass_loss": 0.0,
    "dark_loss": 0.0,
    "foliage_depth": 0.0,
}


def _side_wall(y: float) -> Scene:
    """A 30 m tall building's side along the street at ``y`` metres (left > 0), 100 m long."""
    side = 1.0 if y > 0 else -1.0
    box = Boxes(
        np.array([[0.0, y + side * 1.0]]),
        np.array([[50.0, 1.0]]),
        np.array([[0.0, 30.0]]),
        np.zeros(1),
        np.array([KIND_BUILDING], np.int8),
    )
    return Scene(box, NO_CYL, NO_ELL)


def test_a_vertical_fan_hits_a_side_wall_where_hand_computed_rays_do() -> None:
    # Pitch -pi/2 (SDK frame: x forward, y right, z down): the scanner's x axis points straight
    # down, its y axis right, so the ray at angle a is (0, -sin a, -cos a) in x forward, y left,
    # z up: a vertical plane across the road.
    cfg = pushbroom(mount=(2.0, 0.0, 1.0, 0.0, -math.pi / 2, 0.0), **PERFECT)
    h = cfg.reference_height - 1.0  # the scanner above the road
    pts = cast_line(
        _side_wall(-6.0), FLAT, np.array([0, 0, h]), np.eye(3), cfg, np.random.default_rng(0)
    )
    expected = []
    for a in np.deg2rad(np.arange(-135.0, 135.0 + 1e-9, 0.5)):
        d = np.array([0.0, -math.sin(a), -math.cos(a)])
        t_wall = -6.0 / d[1] if d[1] < -1e-12 else math.inf
        t_road = h / -d[2] if d[2] < -1e-12 else math.inf
        t = min(t_wall, t_road)
        if 0.5 <= t <= 50.0:
            expected.append(d * t)
    expected = np.array(expected)
    assert pts.shape == expected.shape
    np.testing.assert_allclose(np.sort(pts, axis=0), np.sort(expected, axis=0), atol=1e-4)
    on_wall = np.abs(pts[:, 1] + 6.0) < 1e-4
    # up to 45 degrees above the scanner (the fan's edge), 6 m away
    assert pts[on_wall, 2].max() == pytest.approx(6.0, abs=0.01)


def test_the_robotcar_mounting_leans_the_scan_plane_as_its_pitch_says() -> None:
    cfg = pushbroom(**PERFECT)
    fan = line_fan(cfg)
    h = float(cfg.origin()[2])
    assert h == pytest.approx(cfg.reference_height - LMS_FRONT[2])
    pts = cast_line(
        _side_wall(8.0), FLAT, np.array([0, 0, h]), np.eye(3), cfg, np.random.default_rng(0), fan
    )
    wall = pts[np.abs(pts[:, 1] - 8.0) < 1e-4]
    assert len(wall) > 50
    # Every hit lies in the scan plane (its normal is the scanner's z axis) ...
    assert np.abs(pts.astype(np.float64) @ fan.axes[:, 2]).max() < 1e-5
    # ... which leans back 90 deg + pitch (6.5 degrees) from the vertical: independently of the
    # code's rotation, a wall's hits move back tan(pi/2 + pitch) metres a metre up (roll and yaw
    # of a few hundredths of a radian move it by less than 0.01).
    slope = np.polyfit(wall[:, 2], wall[:, 0], 1)[0]
    assert slope == pytest.approx(-math.tan(math.pi / 2 + LMS_FRONT[4]), abs=0.01)
    assert math.degrees(math.atan(-slope)) == pytest.approx(6.5, abs=0.2)
    # The road under the bumper: the fan's middle looks down and a little forward.
    road = pts[np.abs(pts[:, 2] + h) < 1e-4]
    assert len(road) > 100 and np.median(road[:, 0]) > 0


def test_the_body_blocks_the_rays_it_stands_in() -> None:
    # The scanner 2 m above the road, 5 cm ahead of a body 1.5 m tall, its plane leaning 17
    # degrees so that the rays going down also go back: over the body's top.
    body = ((-3.0, 0.45, -0.9, 0.9, 0.2, 1.5),)
    cfg = pushbroom(mount=(0.5, 0.0, -0.25, 0.0, -math.pi / 2 - 0.3, 0.0), body=body, **PERFECT)
    fan = line_fan(cfg)
    blocked = fan.bundle.roof
    assert 0 < blocked.sum() < len(blocked)
    # independently: a ray going down from (0.5, 0, 2.0) is blocked where it reaches the body's
    # top (z 1.5) within its outline (it is behind x 0.45 by then)
    o = cfg.origin()
    for d, hit in zip(fan.dirs, blocked, strict=True):
        if d[2] < -1e-9:
            t = (o[2] - 1.5) / -d[2]
            x, y = o[0] + t * d[0], o[1] + t * d[1]
            if abs(abs(y) - 0.9) > 1e-6:
                assert hit == (-3.0 < x < 0.45 and abs(y) < 0.9)
        else:
            assert not hit
    pts = cast_line(_side_wall(-6.0), FLAT, o, np.eye(3), cfg, np.random.default_rng(0), fan)
    ray = np.argmax((pts / np.linalg.norm(pts, axis=1, keepdims=True)) @ fan.dirs.T, axis=1)
    assert len(pts) > 100 and not blocked[ray].any()  # every return by a ray the body lets by
    road_under = (pts[:, 2] < -1.9) & (np.abs(pts[:, 1]) < 0.9) & (pts[:, 0] < 0.45 - 0.5)
    assert not road_under.any()


@pytest.mark.parametrize(
    ("update", "field"),
    [
        ({"rate_hz": 0.0}, "pushbroom.rate_hz"),
        ({"rate_hz": float("inf")}, "pushbroom.rate_hz"),
        ({"fov_deg": 400.0}, "pushbroom.fov_deg"),
        ({"step_deg": -0.5}, "pushbroom.step_deg"),
        ({"mount": (0.0, 0.0, 1.0, 0.0, -1.457, 0.0)}, "pushbroom.mount"),  # inside the body
        ({"mount": (float("nan"), 0.227, 1.041, -0.044, -1.457, 0.036)}, "pushbroom.mount"),
        ({"mount": (1.759, 0.227, 3.0, -0.044, -1.457, 0.036)}, "pushbroom.mount"),  # underground
        ({"min_range": 60.0}, "pushbroom.min_range"),
    ],
)
def test_an_impossible_mounting_or_rate_is_one_line_naming_the_field(
    update: dict, field: str
) -> None:
    with pytest.raises(InputError) as err:
        pushbroom(**update)
    assert err.value.source == field
    assert "\n" not in str(err.value) and str(err.value).startswith(field + ": ")


def test_a_preset_with_an_impossible_rate_writes_nothing(tmp_path: Path) -> None:
    spec = get_preset("pushbroom_tiny")
    spec.pushbroom = spec.pushbroom.model_copy(update={"rate_hz": -50.0})  # unchecked copy
    with pytest.raises(InputError, match=r"^pushbroom\.rate_hz: "):
        generate(spec, tmp_path / "out", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_lines_follow_the_speed_and_a_line_is_the_same_whatever_the_order() -> None:
    spec = get_preset("pushbroom_tiny")
    d = simulated_drive(spec, 0, 1, 5)
    step = np.linalg.norm(np.diff(d.true_poses[:, :2, 3], axis=0), axis=1)
    # along a straight stretch a line every speed / 50 Hz metres (20,000 us apart)
    assert np.median(step) == pytest.approx(d.speed / 50.0, rel=1e-3)
    assert set(np.diff(d.timestamps).tolist()) <= {20_000, 19_999, 20_001}
    spec.pushbroom = spec.pushbroom.model_copy(update={"rate_hz": 25.0})
    slow = simulated_drive(spec, 0, 1, 5)
    assert slow.speed == d.speed and len(slow) == pytest.approx(len(d) / 2, abs=1)
    # the same seed: the same lines, asked for in any order; another seed: others
    late = [d.scan(i) for i in (901, 900, 3)]
    again = simulated_drive(get_preset("pushbroom_tiny"), 0, 1, 5)
    early = [again.scan(i) for i in (3, 900, 901)]
    assert [p.tobytes() for p in late] == [p.tobytes() for p in early[::-1]]
    other = simulated_drive(get_preset("pushbroom_tiny"), 0, 1, 6)
    assert other.scan(3).tobytes() != early[0].tobytes()


def test_lines_are_laid_with_the_recorded_poses_whose_drift_is_smooth() -> None:
    d = simulated_drive(get_preset("pushbroom_tiny"), 0, 0, 5)
    err = d.poses[:, :2, 3] - d.true_poses[:, :2, 3]
    assert np.abs(err).max() > 0.05  # the GNSS/INS error is there ...
    # ... and smooth from line to line (an INS), not a jitter of its own every line
    assert np.abs(np.diff(err, axis=0)).max() < 0.05


def _small(name: str = "pushbroom_small"):  # a 90 m street, two runs: seconds
    spec = get_preset("pushbroom_tiny")
    spec.name = name
    spec.runs = 2
    spec.areas = [AreaSpec(**{**spec.areas[0].model_dump(), "route_m": 90.0})]
    return spec


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_a_pushbroom_preset_makes_a_benchmark_of_tall_submaps_the_same_by_seed(
    tmp_path: Path,
) -> None:
    spec = _small()
    generate(spec, tmp_path / "a", seed=2, workers=2, progress=False)
    report = check_tree(tmp_path / "a")
    assert report.ok, report.problems
    subs = sorted((tmp_path / "a").rglob("pointcloud_20m_10overlap/*.bin"))
    assert len(subs) >= 8
    heights = []
    for f in subs:
        pts = np.fromfile(f, "<f8").reshape(-1, 3)
        assert pts.shape == (4096, 3) and np.abs(pts).max() <= 1.0
        heights.append(np.ptp(pts[:, 2]))
    # a push-broom sweeps facades to their tops: far taller than the spinning sensors' 0.11
    assert np.median(heights) > 0.3
    generate(_small(), tmp_path / "b", seed=2, workers=1, progress=False)
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")


def test_presets_without_a_line_scanner_dump_as_before() -> None:
    for name in ("tiny", "demo", "benchmark", "benchmark_v1"):
        assert "pushbroom" not in get_preset(name).model_dump()
    dump = get_preset("pushbroom_demo").model_dump()
    assert dump["pushbroom"]["rate_hz"] == 50.0 and dump["pushbroom"]["mount"] == LMS_FRONT


def test_the_line_scanner_fails_as_the_spinning_sensors_do() -> None:
    from pnvlad_service.synth.lidar import _windows

    cfg = pushbroom(**PERFECT)
    h = float(cfg.origin()[2])
    o = np.array([0.0, 0.0, h])

    def wall_hits(**update: float) -> np.ndarray:
        c = pushbroom(**{**PERFECT, **update})
        shifts = [np.array([x, 0.0, 0.0]) for x in np.arange(-10.0, 10.0, 0.1)]
        rays = [
            cast_line(_side_wall(8.0), FLAT, o + d, np.eye(3), c, np.random.default_rng(i)) + d
            for i, d in enumerate(shifts)
        ]
        pts = np.concatenate(rays)
        return pts[np.abs(pts[:, 1] - 8.0) < 1e-4]

    clean = wall_hits()
    on_glass = _windows(clean[:, 0] + 50.0, clean[:, 2] + h)  # metres along the face, up it
    assert 0.1 < on_glass.mean() < 0.5
    # every ray that meets glass lost, the rest of the wall kept
    glass = wall_hits(glass_loss=1.0)
    assert not _windows(glass[:, 0] + 50.0, glass[:, 2] + h).any()
    assert len(glass) == pytest.approx((~on_glass).sum(), abs=2)
    # dropouts: half the returns lost
    half = wall_hits(dropout=0.5)
    assert len(half) == pytest.approx(len(clean) / 2, rel=0.1)
    # range noise: the wall's hits scattered about it by the noise along each ray
    noisy = pushbroom(**{**PERFECT, "range_noise": 0.05})
    pts = cast_line(_side_wall(8.0), FLAT, o, np.eye(3), noisy, np.random.default_rng(0))
    r = np.linalg.norm(pts, axis=1)
    unit = pts / r[:, None]
    wall = (unit[:, 1] > 0.2) & (unit[:, 2] > 0.0)  # rays to the wall above the scanner
    exact = 8.0 / unit[wall, 1]
    assert np.std(r[wall] - exact) == pytest.approx(0.05, rel=0.3)
