"""preprocess.filter_g: the filter G, step by step, against expectations computed
independently."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_points
from pnvlad_service.preprocess.filter_g import (
    GConfig,
    apply_g,
    crop_mask,
    filter_g,
    ground_mask,
    normalize,
)
from pnvlad_service.preprocess.ground import fit_ground_plane
from tests.preprocess.helpers import road_surface

# --- crop ------------------------------------------------------------------------------------


def test_crop_mask_matches_a_plain_loop() -> None:
    pts = np.random.default_rng(1).uniform(-30, 30, size=(500, 3))
    box = (-10.0, -5.0, -2.0, 20.0, 15.0, 3.0)
    mask = crop_mask(pts, min_range=2.0, max_range=25.0, box=box)
    expected = []
    for x, y, z in pts.tolist():
        r = math.sqrt(x * x + y * y + z * z)
        inside = box[0] <= x <= box[3] and box[1] <= y <= box[4] and box[2] <= z <= box[5]
        expected.append(2.0 <= r <= 25.0 and inside)
    assert mask.tolist() == expected
    assert 0 < mask.sum() < 500
    assert crop_mask(pts).all()


# --- exact count ------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(min_value=16, max_value=3000),
    target=st.integers(min_value=2, max_value=2000),
    seed=st.integers(min_value=0, max_value=2**31),
)
def test_exact_point_count_for_any_size(n: int, target: int, seed: int) -> None:
    pts = np.random.default_rng(seed).normal(size=(n, 3)) * [10.0, 10.0, 2.0]
    cfg = GConfig(target_points=target, remove_ground=False)
    out = filter_g(pts, cfg, seed=seed)
    assert out.shape == (target, 3) and out.dtype == np.float64
    assert np.abs(out).max() <= 1.0


# --- normalisation ---------------------------------------------------------------------------


def test_normalize_without_clipping_has_exact_invariants() -> None:
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(1000, 3))
    pts = directions / np.linalg.norm(directions, axis=1, keepdims=True) * 7.0 + [100, -50, 3]
    out = normalize(pts, rng=rng)  # a sphere: no point leaves [-1, 1]
    assert out.shape == (1000, 3)
    np.testing.assert_allclose(out.mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(out, axis=1).mean() == pytest.approx(0.5, abs=1e-12)


def test_normalize_clips_and_refills_from_independently_scaled_points() -> None:
    rng = np.random.default_rng(5)
    pts = np.r_[rng.normal(size=(500, 3)), [[40.0, 0, 0], [0, -60.0, 0]]]
    centred = pts - pts.mean(axis=0)
    scaled = centred * (0.5 / np.mean([math.dist(p, (0, 0, 0)) for p in centred.tolist()]))
    inside = {tuple(p) for p in scaled.tolist() if max(abs(v) for v in p) <= 1.0}
    assert len(inside) < len(pts)  # the two far points and some tail points are clipped
    out = normalize(pts, 700, rng=np.random.default_rng(0))
    assert out.shape == (700, 3)
    assert np.abs(out).max() <= 1.0
    for row in out.tolist():
        assert min(math.dist(row, q) for q in inside) < 1e-12


def test_normalize_refuses_a_single_repeated_point() -> None:
    with pytest.raises(InputError, match="coincide"):
        normalize(np.ones((50, 3)), rng=np.random.default_rng(0))


# --- ground ----------------------------------------------------------------------------------


def _tilted_plane_with_boxes(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, vertical height above the plane z = 0.1 x - 0.05 y + 0.3, is-plane flags."""
    rng = np.random.default_rng(seed)
    g = np.arange(-20.0, 20.0, 0.25)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    plane_h = rng.normal(scale=0.02, size=x.shape)
    boxes = []
    for cx, cy in [(5.0, 5.0), (-8.0, 2.0), (0.0, -12.0)]:  # 2 m x 2 m x 1.5 m boxes
        s = np.arange(-1.0, 1.0001, 0.1)
        h = np.arange(0.0, 1.5001, 0.1)
        for sx, hh in np.array(np.meshgrid(s, h)).reshape(2, -1).T:
            boxes += [(cx + sx, cy - 1, hh), (cx + sx, cy + 1, hh)]
            boxes += [(cx - 1, cy + sx, hh), (cx + 1, cy + sx, hh)]
        for sx, sy in np.array(np.meshgrid(s, s)).reshape(2, -1).T:
            boxes.append((cx + sx, cy + sy, 1.5))
    b = np.array(boxes)
    xs, ys, hs = np.r_[x, b[:, 0]], np.r_[y, b[:, 1]], np.r_[plane_h, b[:, 2]]
    zs = 0.1 * xs - 0.05 * ys + 0.3 + hs
    is_plane = np.r_[np.ones(x.size, bool), np.zeros(len(b), bool)]
    return np.c_[xs, ys, zs], hs, is_plane


@pytest.mark.parametrize("mode", ["local", "plane"])
def test_ground_on_a_tilted_plane_with_boxes(mode: str) -> None:
    pts, height, is_plane = _tilted_plane_with_boxes()
    cfg = GConfig(ground_mode=mode)
    ground, up = ground_mask(pts, cfg, rng=np.random.default_rng(0))
    true_normal = np.array([-0.1, 0.05, 1.0]) / math.sqrt(1 + 0.01 + 0.0025)
    assert up @ true_normal > 0.9999
    assert ground[is_plane].all()
    # The threshold is perpendicular to the plane (plane mode); the vertical height is a bit
    # larger, so allow a small margin either side.
    assert not ground[~is_plane & (height > 0.55)].any()
    assert ground[~is_plane & (height < 0.45)].all()


def _two_level_ground_with_slope() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Road z = 0 (y < 4), kerb and pavement 0.15 m higher (4 <= y < 8), then a slope of 12%
    up to 3.99 m (y < 40); two poles and a 3 m wall. Returns points, ground height, is-ground."""
    g = np.arange(-20.0, 20.0, 0.2)
    x, y = (a.ravel() for a in np.meshgrid(g, np.arange(-10.0, 40.0, 0.2)))

    def ground_z(yv: np.ndarray) -> np.ndarray:
        return np.where(yv < 4, 0.0, np.where(yv < 8, 0.15, 0.15 + 0.12 * (yv - 8)))

    obj = []
    h = np.arange(0.0, 4.0, 0.05)
    for px, py in [(3.0, 6.0), (-7.0, 20.0)]:  # poles on the pavement and on the slope
        for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
            obj += [(px + 0.15 * np.cos(a), py + 0.15 * np.sin(a), hh) for hh in h]
    for wx in np.arange(-15.0, -5.0, 0.1):  # a wall along the pavement
        obj += [(wx, 7.5, hh) for hh in h[h < 3.0]]
    o = np.array(obj)
    xs, ys = np.r_[x, o[:, 0]], np.r_[y, o[:, 1]]
    hs = np.r_[np.zeros(x.size), o[:, 2]]
    gz = ground_z(ys)
    is_ground = np.r_[np.ones(x.size, bool), np.zeros(len(o), bool)]
    return np.c_[xs, ys, gz + hs], hs, is_ground


def test_local_ground_follows_kerb_and_slope_where_one_plane_cannot() -> None:
    pts, height, is_ground = _two_level_ground_with_slope()
    local, _ = ground_mask(pts, GConfig(), rng=np.random.default_rng(0))
    assert local[is_ground].all()
    assert not local[~is_ground & (height > 0.5)].any()
    plane, _ = ground_mask(pts, GConfig(ground_mode="plane"), rng=np.random.default_rng(0))
    assert plane[is_ground].mean() < 0.9  # the paper's single plane misses part of the ground


def test_ground_up_side_is_found_in_a_z_down_frame() -> None:
    pts, height, is_ground = _two_level_ground_with_slope()
    flipped = pts * [1.0, -1.0, -1.0]  # 180 deg about x: z points down, as in NCLT
    mask_up, n_up = ground_mask(pts, rng=np.random.default_rng(0))
    mask_down, n_down = ground_mask(flipped, rng=np.random.default_rng(0))
    assert n_up[2] > 0.9 and n_down[2] < -0.9
    # The grids differ (the frame is turned), so the two planes differ a little: only points at
    # the threshold (object points 0.5-0.55 m up) may fall on different sides of it.
    at_threshold = ~is_ground & (height >= 0.45) & (height <= 0.6)
    assert np.array_equal(mask_up[~at_threshold], mask_down[~at_threshold])
    assert mask_down[is_ground].all()
    forced, _ = ground_mask(flipped, GConfig(up="z"), rng=np.random.default_rng(0))
    # Told the wrong side, the objects hang below the "ground" and are all removed with it.
    assert forced[~is_ground].mean() > 0.99
    assert not mask_down[~at_threshold & ~is_ground & (height > 0.5)].any()


def _street_window(seed: int) -> tuple[np.ndarray, int]:
    """An accumulated 20 m window as a sensor 1.9 m up sees a street: ground rolling by about
    1.4 m over 120 m (20,000 points, uniform over a 60 m disc) and two 6 m walls at y = +-8
    whose returns bunch in a 0.4 m band at the sensor's height (70 % of 40,000: the beams near
    the horizon of every scan hit the walls there). Points, then how many are ground."""
    rng = np.random.default_rng(seed)
    r = 60 * np.sqrt(rng.uniform(0, 1, 20_000))
    a = rng.uniform(0, 2 * np.pi, r.size)
    x, y = r * np.cos(a), r * np.sin(a)

    def ground_z(xv: np.ndarray, yv: np.ndarray) -> np.ndarray:
        return -1.9 + 0.8 * np.sin(xv / 25) + 0.6 * np.cos(yv / 30)

    ground = np.c_[x, y, ground_z(x, y) + rng.normal(0, 0.02, r.size)]
    wx = rng.uniform(-60, 60, 40_000)
    wy = np.where(rng.uniform(size=wx.size) < 0.5, -8.0, 8.0)
    band = rng.uniform(size=wx.size) < 0.7
    wz = np.where(
        band, rng.uniform(-0.2, 0.2, wx.size), ground_z(wx, wy) + rng.uniform(0, 6, wx.size)
    )
    return np.r_[ground, np.c_[wx, wy, wz]], ground.shape[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_ground_plane_is_under_the_sensor_not_at_its_height(seed: int) -> None:
    # Over every point, the plane at the sensor's height holds more than the rolling road does
    # (the plane RANSAC fitted until 2026-12-03 chose it there, and up came out as -z, so the
    # walls went as ground and the road stayed); through each column's lowest point it is the road.
    pts, n_ground = _street_window(seed)
    for frame, flip in (("z up", 1.0), ("z down", -1.0)):
        p = pts * [1.0, flip, flip]
        normal, offset = fit_ground_plane(p, rng=np.random.default_rng(0))
        assert normal[2] * flip > 0.99, frame
        assert 1.0 < offset < 2.2, frame  # the sensor (the origin) stands above the ground
        mask, _ = ground_mask(p, rng=np.random.default_rng(0))
        assert mask[:n_ground].mean() > 0.99, frame
        assert mask[n_ground:].mean() < 0.15, frame  # the walls' feet only


# --- the whole filter ------------------------------------------------------------------------


def _scene(seed: int = 0) -> np.ndarray:
    pts, _, _ = _two_level_ground_with_slope()
    rng = np.random.default_rng(seed)
    return pts + rng.normal(scale=0.01, size=pts.shape)


def test_filter_g_is_deterministic_and_seeded() -> None:
    pts = _scene()
    a = filter_g(pts, seed=7)
    b = filter_g(pts.copy(), seed=7)
    assert a.tobytes() == b.tobytes()
    cfg = GConfig(target_points=2000)  # fewer than the non-ground points: voxels dropped
    assert filter_g(pts, cfg, seed=1).tobytes() != filter_g(pts, cfg, seed=2).tobytes()


def test_negate_and_no_normalize() -> None:
    pts = _scene()
    base = filter_g(pts, seed=3)
    assert filter_g(pts, GConfig(negate=True), seed=3).tolist() == (-base).tolist()
    res = apply_g(pts, GConfig(normalize=False, target_points=10_000), seed=3)
    raw = res.points
    assert raw.shape == (10_000, 3)
    assert res.n_nonground < 10_000 and res.leaf_size == 0.0  # fewer points: only refilled
    rows = {tuple(p) for p in pts.tolist()}
    assert all(tuple(p) in rows for p in raw.tolist())  # input frame, input points


def test_too_few_points_and_bad_input_are_refused() -> None:
    flat = np.c_[np.random.default_rng(0).uniform(-5, 5, (500, 2)), np.zeros(500)]
    with pytest.raises(InputError, match="after ground removal"):
        filter_g(flat)
    with pytest.raises(InputError, match="after cropping"):
        filter_g(_scene(), GConfig(max_range=0.01))
    with pytest.raises(InputError, match=r"shape \[N, 3\]"):
        filter_g(np.zeros((10, 4)))
    with pytest.raises(InputError, match="NaN"):
        filter_g(np.array([[0.0, np.nan, 1.0]] * 20))
    huge = _scene().copy()
    huge[0, 0] = 1e308  # finite, but squaring it overflows in the plane fit
    with pytest.raises(InputError, match="coordinates beyond"):
        filter_g(huge)
    with pytest.raises(ValidationError):
        GConfig(box=(0, 0, 0, -1, 1, 1))
    with pytest.raises(ValidationError):
        GConfig(min_range=5, max_range=2)


def test_defaults_are_the_papers() -> None:
    cfg = GConfig()
    assert cfg.target_points == 4096 and cfg.ground_threshold == 0.5
    assert cfg.mean_distance == 0.5 and cfg.normalize and not cfg.negate


def test_g_config_from_file_yaml_json_and_empty(tmp_path: Path) -> None:
    (tmp_path / "g.yaml").write_text("target_points: 1024\nground_mode: plane\n")
    (tmp_path / "g.json").write_text('{"target_points": 1024, "ground_mode": "plane"}')
    (tmp_path / "empty.yaml").write_text("")
    expected = GConfig(target_points=1024, ground_mode="plane")
    assert GConfig.from_file(tmp_path / "g.yaml") == expected
    assert GConfig.from_file(str(tmp_path / "g.json")) == expected
    assert GConfig.from_file(tmp_path / "empty.yaml") == GConfig()


def test_g_config_from_file_errors_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    path.write_text("target_points: [1\n")
    with pytest.raises(InputError, match="not valid YAML/JSON") as exc:
        GConfig.from_file(path)
    assert exc.value.source == str(path)
    for text in ("target_points: -5\n", "no_such_setting: 1\n"):
        path.write_text(text)
        with pytest.raises(InputError, match="bad filter G settings") as exc:
            GConfig.from_file(path)
        assert exc.value.source == str(path)
    with pytest.raises(FileNotFoundError):
        GConfig.from_file(tmp_path / "missing.yaml")


# --- real scans ------------------------------------------------------------------------------

# What G does to a real scan, no pose needed: the two KITTI files are real HDL-64E scans of
# unknown frames (not frames 0 and 5 of sequence 00; the data README).
REAL = [
    ("kitti00_000000.bin", "kitti", 1.0),
    ("kitti00_000005.bin", "kitti", 1.0),
    ("nuscenes_lidar_top.bin", "nuscenes", 1.0),
    ("nclt_1326652795280148.bin", "nclt", -1.0),  # NCLT's z points down
]


@pytest.mark.real_scans
@pytest.mark.parametrize(("name", "reader", "up"), REAL)
def test_real_scan_ground_is_removed(real_scans: Path, name: str, reader: str, up: float) -> None:
    raw = read_points(real_scans / name, reader).astype(np.float64)
    res = apply_g(raw, GConfig(normalize=False))
    assert res.up is not None and res.up[2] * up > 0.99
    flip = np.array([1.0, up, up])
    surface = road_surface(raw * flip)
    raw_near = np.mean(np.abs((raw * flip)[:, 2] - surface(raw * flip)) < 0.2)
    kept = res.points * flip
    kept_near = np.mean(np.abs(kept[:, 2] - surface(kept)) < 0.2)
    assert raw_near > 0.30, raw_near
    assert kept_near < 0.05, kept_near
    assert res.points.shape == (4096, 3)


@pytest.mark.real_scans
@pytest.mark.parametrize(("name", "reader", "up"), REAL)
def test_real_scan_submap_properties(real_scans: Path, name: str, reader: str, up: float) -> None:
    raw = read_points(real_scans / name, reader)
    out = filter_g(raw, seed=0)
    assert out.shape == (4096, 3) and out.dtype == np.float64
    assert np.abs(out).max() <= 1.0
    # Clipping a lopsided scene (NCLT: buildings on one side) moves the centroid a little.
    assert np.linalg.norm(out.mean(axis=0)) < 0.25
    # Clipping to [-1, 1] drops the far tail of a scan and pulls the mean distance below 0.5.
    assert 0.2 < np.linalg.norm(out - out.mean(axis=0), axis=1).mean() <= 0.5 + 1e-9
    # Voxel averaging spreads points out: few exact duplicates unless the cloud was refilled.
    assert len(np.unique(out, axis=0)) > 3500


# --- CLI -------------------------------------------------------------------------------------


@pytest.mark.real_scans
@pytest.mark.parametrize(("name", "reader", "up"), REAL)
def test_cli_writes_a_benchmark_submap(
    real_scans: Path, tmp_path: Path, name: str, reader: str, up: float
) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    out = tmp_path / "sub" / "submap.bin"
    args = ["data", "preprocess", str(real_scans / name), "--reader", reader, "--out", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert out.stat().st_size == 98_304
    back = read_points(out)  # no reader name: recognised as a benchmark submap
    assert back.shape == (4096, 3) and np.abs(back).max() <= 1.0
    count = f"{read_points(real_scans / name, reader).shape[0]:,} points in"
    assert count in result.output and "4,096 out" in result.output
    # Same seed, same bytes, whatever the route.
    expected = filter_g(read_points(real_scans / name, reader), seed=0)
    assert out.read_bytes() == expected.astype("<f8").tobytes()


def test_cli_options_and_errors(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from pnvlad_cli.main import app

    scan = tmp_path / "scene.npy"
    np.save(scan, _scene())
    out = tmp_path / "scene_out.npy"
    runner = CliRunner()
    options = ["--points", "512", "--no-normalize", "--box", "-30,-30,-5,30,30,10"]
    options += ["--max-range", "35", "--seed", "4"]
    ok = runner.invoke(app, ["data", "preprocess", str(scan), "-o", str(out), *options])
    assert ok.exit_code == 0, ok.output
    cfg = GConfig(target_points=512, normalize=False, box=(-30, -30, -5, 30, 30, 10), max_range=35)
    assert np.load(out).tolist() == filter_g(_scene(), cfg, seed=4).tolist()
    bad_box = runner.invoke(app, ["data", "preprocess", str(scan), "-o", str(out), "--box", "1,2"])
    assert bad_box.exit_code == 2 and "--box" in bad_box.output
    bad_up = runner.invoke(app, ["data", "preprocess", str(scan), "-o", str(out), "--up", "x"])
    assert bad_up.exit_code == 2 and "--up" in bad_up.output
    raw_bin = tmp_path / "scan.bin"
    raw_bin.write_bytes(np.zeros((100, 4), "<f4").tobytes())
    refused = runner.invoke(
        app, ["data", "preprocess", str(raw_bin), "-o", str(tmp_path / "o.bin")]
    )
    assert refused.exit_code == 2 and "--reader" in refused.output
    assert not (tmp_path / "o.bin").exists()


def test_wide_crown_over_unseen_ground_is_not_ground() -> None:
    # A 14 m x 14 m tree crown (3-6 m up) hides the ground below it, wider than the
    # morphological window: only its link to the real ground tells it is not ground.
    rng = np.random.default_rng(8)
    xy = rng.uniform(-25, 25, size=(40_000, 2))
    under = (np.abs(xy[:, 0] - 10) < 7) & (np.abs(xy[:, 1]) < 7)
    floor = np.c_[xy[~under], rng.normal(0, 0.02, (~under).sum())]
    crown = np.c_[rng.uniform(3, 17, 6000), rng.uniform(-7, 7, 6000), rng.uniform(3, 6, 6000)]
    pts = np.r_[floor, crown]
    mask, _ = ground_mask(pts, rng=np.random.default_rng(0))
    assert mask[: len(floor)].all()
    assert not mask[len(floor) :].any()


def test_prevoxel_keeps_g_close_to_the_full_cloud_in_a_fraction_of_the_points() -> None:
    """G with ``prevoxel`` averages the cropped points in small voxels first: the submap's
    points move by a fraction of G's own voxel, its scale hardly at all."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    ground = np.c_[rng.uniform(-40, 40, (60_000, 2)), rng.normal(0.0, 0.02, 60_000)]
    walls = np.c_[
        rng.uniform(-40, 40, 40_000),
        np.where(rng.random(40_000) < 0.5, -12.0, 12.0) + rng.normal(0, 0.05, 40_000),
        rng.uniform(0.2, 8.0, 40_000),
    ]
    cloud = np.concatenate([ground, walls])
    full = apply_g(cloud, GConfig(max_range=50.0))
    fast = apply_g(cloud, GConfig(max_range=50.0, prevoxel=0.2))
    a, b = full.centre + full.scale * full.points, fast.centre + fast.scale * fast.points
    assert np.median(cKDTree(a).query(b)[0]) < 0.5 * full.leaf_size
    assert abs(fast.scale / full.scale - 1) < 0.02
    assert fast.n_nonground < full.n_nonground  # what G worked on after the average
