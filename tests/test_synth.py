"""The synthetic city: determinism, what differs between runs, the sensor, the tree it writes."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pnvlad_cli.main import app
from pnvlad_service.data.splits import load_splits
from pnvlad_service.data.tree import check_tree
from pnvlad_service.synth.generate import choose_test_regions, generate, get_preset
from pnvlad_service.synth.lidar import LidarConfig, cast_scan, ray_bundle
from pnvlad_service.synth.runs import SimulatedDrive, make_route
from pnvlad_service.synth.world import (
    KIND_BUILDING,
    KIND_CAR,
    Boxes,
    Cylinders,
    Ellipsoids,
    Ground,
    Scene,
    WorldConfig,
    generate_world,
)


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("synth") / "tiny"
    generate("tiny", root, seed=3, workers=2, progress=False)
    return root


def test_tiny_tree_is_a_valid_benchmark_with_truth_in_every_run_pair(tiny: Path) -> None:
    report = check_tree(tiny)
    assert report.ok, report.problems
    splits = load_splits(tiny / "splits.json")
    (es,) = splits.evaluation.values()
    runs = len(es.runs)
    assert runs == get_preset("tiny").runs
    for j in range(runs):
        for i in range(runs):
            if i == j:
                continue
            # Some query of run j has a true match in run i: every ordered pair is scored.
            assert any(len(t) > 0 for t in es.truth[j][i]), (i, j)
    (tuples,) = splits.training.values()
    assert len(tuples.anchors(2)) > 10
    for sub in tiny.rglob("*.bin"):
        assert sub.stat().st_size == 98_304


def test_same_seed_same_bytes_other_seed_other_city(tiny: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    generate("tiny", again, seed=3, workers=1, progress=False)  # other worker count too
    assert _tree_digest(again) == _tree_digest(tiny)
    a = generate_world(WorldConfig(district="business", size=(300.0, 250.0)), seed=3)
    b = generate_world(WorldConfig(district="business", size=(300.0, 250.0)), seed=4)
    assert not np.array_equal(a.nodes, b.nodes)
    assert len(a.scene.boxes) != len(b.scene.boxes) or not np.allclose(
        a.scene.boxes.center, b.scene.boxes.center
    )


def test_two_runs_differ_but_the_static_city_is_the_same() -> None:
    world = generate_world(WorldConfig(district="residential", size=(400.0, 300.0)), seed=1)
    route = make_route(world, 300.0, seed=1)
    lidar = LidarConfig(beams=16, columns=180)
    r1 = SimulatedDrive(world, route, "a", seed=10, start_us=0, lidar=lidar)
    r2 = SimulatedDrive(world, route, "b", seed=11, start_us=0, lidar=lidar)
    s1, s2 = r1.scene, r2.scene

    def buildings(s) -> np.ndarray:
        k = s.boxes.kind == KIND_BUILDING
        return np.c_[s.boxes.center[k], s.boxes.half[k], s.boxes.z[k], s.boxes.yaw[k]]

    # Static: every building is where the city put it, in both runs.
    np.testing.assert_array_equal(buildings(s1), buildings(s2))
    world_b = world.scene.boxes.kind == KIND_BUILDING
    assert len(buildings(s1)) == int(world_b.sum())
    # Parked cars: different slots taken.
    p1 = {tuple(c) for c in s1.boxes.center[s1.boxes.kind == KIND_CAR].round(3)}
    p2 = {tuple(c) for c in s2.boxes.center[s2.boxes.kind == KIND_CAR].round(3)}
    assert p1 != p2
    # Vegetation: crowns of other sizes and densities (season).
    assert not np.allclose(s1.crowns.radii.mean(), s2.crowns.radii.mean())
    # Traffic: different vehicles at the same time.
    t = 10.0
    c1 = s1.scene_at(t, route.points[0], 1e9).boxes
    c2 = s2.scene_at(t, route.points[0], 1e9).boxes
    assert len(c1) != len(c2) or not np.allclose(c1.center, c2.center)
    # Moving objects move: the same run at two times.
    m_a = s1.scene_at(0.0, route.points[0], 1e9).boxes.center
    m_b = s1.scene_at(5.0, route.points[0], 1e9).boxes.center
    assert m_a.shape == m_b.shape and not np.allclose(m_a, m_b)
    # Pose noise: the poses used for submaps are off the true trajectory, differently per run.
    err1 = r1.poses[:, :2, 3] - (r1.true_xy + world.origin)
    err2 = r2.poses[:, :2, 3] - (r2.true_xy + world.origin)
    assert 0.2 < np.sqrt((err1**2).sum(1).mean()) < 6.0
    assert not np.allclose(err1, err2)
    # Same scan index, same points (deterministic whatever the order of the calls).
    np.testing.assert_array_equal(r1.scan(3), (r1.scan(5), r1.scan(3))[1])


def _one_box_scene(distance: float) -> tuple[Scene, Ground]:
    boxes = Boxes(
        center=np.array([[distance + 0.5, 0.0]]),
        half=np.array([[0.5, 2.0]]),
        z=np.array([[-5.0, 50.0]]),
        yaw=np.array([0.0]),
        kind=np.array([KIND_BUILDING], np.int8),
    )
    empty_c = Cylinders(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), np.zeros(0, np.int8))
    empty_e = Ellipsoids(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int8))
    ground = Ground(np.zeros(2), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    return Scene(boxes, empty_c, empty_e), ground


def test_lidar_first_surface_and_occlusion_shadow() -> None:
    # A wall 10 m ahead (x = 10 .. 11, y = -2 .. 2); sensor 2 m above a flat ground, no noise.
    scene, ground = _one_box_scene(10.0)
    cfg = LidarConfig(beams=8, columns=720, range_noise=0.0, dropout=0.0, min_range=0.5)
    pts = cast_scan(scene, ground, np.array([0.0, 0.0, 2.0]), 0.0, cfg, np.random.default_rng(0))
    az = np.arctan2(pts[:, 1], pts[:, 0])
    toward = np.abs(az) < np.arctan2(1.9, 10.0)  # rays that must meet the wall's front face
    rays = ray_bundle(cfg)
    # Expected per ray, computed independently: front face x = 10 unless the ground comes first.
    hits_wall = toward & (pts[:, 2] > -2.0 + 1e-6)
    assert hits_wall.any()
    np.testing.assert_allclose(pts[hits_wall, 0], 10.0, atol=1e-5)
    # Shadow: nothing is seen behind the wall.
    behind = (pts[:, 0] > 11.0) & (np.abs(pts[:, 1]) < 1.5)
    assert not behind.any()
    # Elsewhere the down-looking beams reach the flat ground at z = -2 (sensor frame).
    ground_pts = pts[np.abs(az) > np.arctan2(2.1, 10.0)]
    assert ground_pts.size and np.allclose(ground_pts[:, 2], -2.0, atol=1e-6)
    assert len(rays.elevation) == 8


def test_test_regions_cover_about_the_share_asked() -> None:
    t = np.linspace(0, 1, 2001)
    route = np.c_[t * 2000.0, 100 * np.sin(t * 8)]  # a 2 km wiggly street
    centres = choose_test_regions(route, 0.3, 150.0)
    inside = np.zeros(len(route), bool)
    for cx, cy in centres:
        inside |= (np.abs(route[:, 0] - cx) < 150) & (np.abs(route[:, 1] - cy) < 150)
    assert 0.25 <= inside.mean() <= 0.5
    for i, a in enumerate(centres):  # squares do not overlap
        for b in centres[i + 1 :]:
            assert max(abs(a[0] - b[0]), abs(a[1] - b[1])) >= 300.0


def test_cli_synth_refuses_an_existing_tree_and_renders_previews(
    tiny: Path, tmp_path: Path
) -> None:
    runner = CliRunner()
    res = runner.invoke(app, ["synth", "--preset", "tiny", "--out", str(tiny), "--no-progress"])
    assert res.exit_code == 2 and "exists" in res.output
    res = runner.invoke(app, ["synth", "--preset", "nope", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2 and "tiny" in res.output

    from pnvlad_service.synth.preview import render_previews

    paths = render_previews(tiny, tmp_path / "png")
    assert [p.name for p in paths] == ["map.png", "submap_business.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000


def test_eval_scores_every_area_of_a_multi_area_tree(tiny: Path, tmp_path: Path) -> None:
    """Two identical areas must score identically: ground truth of the second set must point
    at its own runs, not at the first set's (a bug once scored only the first area)."""
    import json
    import shutil

    from pnvlad_service.data.splits import build_splits, save_splits

    root = tmp_path / "two"
    shutil.copytree(tiny / "business", root / "business")
    shutil.copytree(tiny / "business", root / "twin")
    save_splits(root / "splits.json", build_splits(root))
    out = tmp_path / "rep.json"
    args = ["-q", "eval", "--baseline", "--root", str(root)]
    args += ["--splits", str(root / "splits.json"), "-o", str(out), "--no-progress"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rep = json.loads(out.read_text())
    a, b = rep["per_area"]["business"], rep["per_area"]["twin"]
    assert a["n_pairs"] == b["n_pairs"] == 6 and not a["skipped_pairs"] and not b["skipped_pairs"]
    assert a["recall_at_n"] == b["recall_at_n"]
    assert rep["recall_at_1"] == a["recall_at_1"]


def test_runs_follow_trajectories_a_user_supplies(tmp_path: Path) -> None:
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.synth.generate import _world

    spec = get_preset("tiny")
    area = spec.areas[0]
    world = _world(area, 0)
    # A route of our own: an L along the first street, given in UTM as a user would.
    pts = make_route(world, 200.0, seed=42).points[::5] + world.origin
    tdir = tmp_path / "traj"
    tdir.mkdir()
    for k in range(spec.runs):
        rows = ["timestamp,northing,easting"]
        rows += [f"{i},{n:.3f},{e:.3f}" for i, (e, n) in enumerate(pts)]
        (tdir / f"{k}.csv").write_text("\n".join(rows) + "\n")
    root = tmp_path / "tree"
    generate(spec, root, seed=0, workers=1, trajectories=tdir, progress=False)
    tree = BenchmarkTree(root)
    for run in tree.runs(area.name):
        subs = tree.submaps(area.name, run, "train")
        assert subs
        xy = np.array([[s.easting, s.northing] for s in subs])
        # Every submap sits on the supplied path (lane offset + pose drift: a few metres).
        d = np.min(np.linalg.norm(xy[:, None, :] - pts[None, :, :], axis=2), axis=1)
        assert d.max() < 8.0, d.max()
    bad = tmp_path / "bad"
    bad.mkdir()
    from pnvlad_service.errors import InputError

    with pytest.raises(InputError, match=r"no trajectory business_0\.csv"):
        generate(spec, tmp_path / "t2", seed=0, workers=1, trajectories=bad, progress=False)
    for k in range(spec.runs):
        (bad / f"{k}.csv").write_text("timestamp,x,y\n0,1,2\n")
    with pytest.raises(InputError, match="columns northing,easting"):
        generate(spec, tmp_path / "t3", seed=0, workers=1, trajectories=bad, progress=False)
    assert not (tmp_path / "t2").exists() and not (tmp_path / "t3").exists()
