"""Generate a synthetic benchmark tree: areas, runs, submaps, test regions and splits.

``generate(preset, out, seed)`` writes, in the public PointNetVLAD layout::

    OUT/<area>/<run>/pointcloud_20m_10overlap/<timestamp>.bin  training layout, every 10 m
    OUT/<area>/<run>/pointcloud_locations_20m_10overlap.csv
    OUT/<area>/<run>/pointcloud_20m/<timestamp>.bin            test layout, every 20 m
    OUT/<area>/<run>/pointcloud_locations_20m.csv
    OUT/<area>/<run>/pointcloud_keyframes/<timestamp>.bin      keyframe map: one scan every 5 m
    OUT/<area>/<run>/pointcloud_locations_keyframes.csv
    OUT/<area>/<run>/raw_scans/<timestamp>.bin, raw_scans.csv  the raw scan at each test submap
                                                               (sensor frame, KITTI .bin, poses)
    OUT/<area>/test_regions.json     squares chosen on the area's route (read by `data splits`),
                                     or the published ones (an area named oxford laid over them)
    OUT/splits.json                  training tuples and evaluation sets (data.splits)
    OUT/splits_keyframes.json        the same of the keyframe maps (single-scan encoders)
    OUT/synth.json                   preset, seed, parameters, sizes and timings

Every run is a :class:`~pnvlad_service.synth.runs.SimulatedDrive` cut into submaps by
:func:`pnvlad_service.data.prepare.prepare_drive`, the path a user's own drive takes (accumulation
over 20 m of trajectory, filter G, 4096 points). Runs are generated in parallel processes; every
random stream is derived from ``(seed, area, run)``, so the bytes do not depend on the number of
workers. The tree is built under a temporary name and renamed when complete.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.synth.city import generate_world
from pnvlad_service.synth.lidar import LidarConfig
from pnvlad_service.synth.presets import (
    PRESETS,
    REAL_CITY,
    REAL_CONDITIONS,
    AreaSpec,
    SynthPreset,
    get_preset,
)
from pnvlad_service.synth.pushbroom import PushbroomDrive
from pnvlad_service.synth.runs import Route, SimulatedDrive, make_route
from pnvlad_service.synth.sensors import checked_pushbroom
from pnvlad_service.synth.world import DISTRICTS, CityDetail, World, WorldConfig

__all__ = [
    "PRESETS",
    "REAL_CITY",
    "REAL_CONDITIONS",
    "AreaSpec",
    "SynthPreset",
    "generate",
    "get_preset",
    "simulated_drive",
]

log = logging.getLogger(__name__)


def run_name(area_index: int, run: int, seed: int) -> tuple[str, int]:
    """Folder name (Oxford style ``YYYY-MM-DD-HH-MM-SS``) and start time (µs) of a run.

    Runs of an area are days to weeks apart, at different hours, like the benchmark's."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, area_index, run, 5]))
    day = dt.datetime(2026, 3, 2, tzinfo=dt.timezone.utc) + dt.timedelta(
        days=int(9 * run + rng.integers(0, 6)),
        hours=int(rng.integers(7, 19)),
        minutes=int(rng.integers(0, 60)),
        seconds=int(rng.integers(0, 60)),
    )
    return day.strftime("%Y-%m-%d-%H-%M-%S"), int(day.timestamp()) * 1_000_000


def run_seed_of(seed: int, area_index: int, run: int) -> int:
    """The seed of every random stream of one run."""
    return int(np.random.SeedSequence([seed, area_index, run, 1]).generate_state(1)[0])


def simulated_drive(spec: SynthPreset, area_index: int, run: int, seed: int) -> SimulatedDrive:
    """Rebuild run ``run`` of area ``area_index`` exactly as :func:`generate` drove it
    (generated routes only), e.g. to look at its raw scans."""
    jobs = _run_jobs_of_area(Path("."), area_index, spec.areas[area_index], spec, seed, {})
    return _job_drive(jobs[run])


#: The last world built in this process, by what built it: a worker generating several runs of
#: one area builds it once (an oxford-sized area takes about a minute).
_LAST_WORLD: dict[str, World] = {}


def _world(area: AreaSpec, seed: int, detail: CityDetail | None = None) -> World:
    key = json.dumps([area.model_dump(), seed, (detail or CityDetail()).model_dump()])
    if key not in _LAST_WORLD:
        _LAST_WORLD.clear()
        _LAST_WORLD[key] = _build_world(area, seed, detail)
    return _LAST_WORLD[key]


def _build_world(area: AreaSpec, seed: int, detail: CityDetail | None) -> World:
    if area.district not in DISTRICTS:
        raise InputError(
            f"unknown district {area.district!r}; choose one of {sorted(DISTRICTS)}", area.name
        )
    cfg = WorldConfig(
        district=area.district, size=area.size, origin=area.origin, detail=detail or CityDetail()
    )
    return generate_world(cfg, seed=seed)


def route_from_csv(world: World, path: str | Path) -> Route:
    """A route from a CSV with ``northing`` and ``easting`` columns (UTM metres), as a user
    supplies for `pnvlad synth --trajectories`. Timestamps, if present, are not needed: each
    run keeps its own speed."""
    import csv

    from pnvlad_service.synth.runs import _resample

    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"cannot read trajectory: {exc}", path) from None
    if not rows or not {"northing", "easting"} <= set(rows[0]):
        raise InputError("a trajectory CSV needs the columns northing,easting", path)
    try:
        ne = np.array([[float(r["northing"]), float(r["easting"])] for r in rows])
    except ValueError as exc:
        raise InputError(f"non-numeric position ({exc})", path) from None
    if len(ne) < 2 or not np.isfinite(ne).all():
        raise InputError("a trajectory needs at least two finite positions", path)
    local = np.stack([ne[:, 1], ne[:, 0]], 1) - world.origin
    pts = _resample(local, 1.0)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
    hw = np.full(len(pts), 5.0)
    return Route(pts, s, hw)


def part_of_route(route: Route, start: float, end: float) -> Route:
    """The stretch of ``route`` between the shares ``start`` and ``end`` of its length."""
    s0, s1 = start * route.length, end * route.length
    keep = (route.s >= s0) & (route.s <= s1)
    if keep.sum() < 2:
        raise InputError(f"a part {start}-{end} of a {route.length:.0f} m route is empty", "part")
    return Route(route.points[keep], route.s[keep] - route.s[keep][0], route.half_width[keep])


def choose_test_regions(
    route_xy: np.ndarray, share: float, half_size: float, max_regions: int = 6
) -> list[tuple[float, float]]:
    """Square test regions (centres as local x, y) covering about ``share`` of a route.

    Greedy and deterministic: candidates are route points every 25 m; each step takes the
    square that adds the most uncovered route, never overlapping an earlier square, until the
    share is reached.
    """
    pts = np.asarray(route_xy, dtype=np.float64)
    covered = np.zeros(len(pts), bool)
    centres: list[tuple[float, float]] = []
    cands = pts[:: max(len(pts) // max(int(len(pts) / 25), 1), 1)]
    for _ in range(max_regions):
        if covered.mean() >= share:
            break
        best, gain = None, 0
        for c in cands:
            if any(max(abs(c[0] - a), abs(c[1] - b)) < 2 * half_size for a, b in centres):
                continue
            inside = (np.abs(pts[:, 0] - c[0]) < half_size) & (np.abs(pts[:, 1] - c[1]) < half_size)
            g = int((inside & ~covered).sum())
            # Do not overshoot the share by much: prefer the square closest to the remainder.
            remaining = share * len(pts) - covered.sum()
            score = g if g <= remaining * 1.3 else remaining * 1.3 - (g - remaining * 1.3)
            if best is None or score > gain:
                best, gain = c, score
        if best is None:
            break
        centres.append((float(best[0]), float(best[1])))
        covered |= (np.abs(pts[:, 0] - best[0]) < half_size) & (
            np.abs(pts[:, 1] - best[1]) < half_size
        )
    return centres


def _job_drive(job: dict[str, Any]) -> SimulatedDrive:
    """The drive of one run job (no scan is cast until asked for)."""
    preset = SynthPreset.model_validate(job["preset"])
    area = AreaSpec.model_validate(job["area"])
    world = _world(area, job["seed"], preset.city)
    route = (
        route_from_csv(world, job["trajectory"])
        if job.get("trajectory")
        else make_route(world, area.route_m, job["seed"])
    )
    if job.get("part"):
        route = part_of_route(route, *job["part"])
    lidar = job.get("lidar")
    run = {"seed": job["run_seed"], "start_us": job["start_us"], "conditions": preset.conditions}
    if lidar and lidar.get("kind") == "pushbroom":
        return PushbroomDrive(world, route, job["run"], lidar=checked_pushbroom(lidar), **run)
    return SimulatedDrive(
        world,
        route,
        job["run"],
        lidar=LidarConfig.model_validate(lidar) if lidar else preset.lidar,
        scan_spacing=preset.scan_spacing,
        **run,
    )


def _run_jobs_of_area(
    out: Path, area_index: int, area: AreaSpec, spec: SynthPreset, seed: int, traj: dict
) -> list[dict[str, Any]]:
    """One job per run of an area (what :func:`_run_job` generates)."""
    jobs = []
    for k in range(spec.runs):
        name, start = run_name(area_index, k, seed)
        jobs.append(
            {
                "preset": spec.model_dump(),
                "area": area.model_dump(),
                "seed": seed,
                "run": name,
                "run_seed": run_seed_of(seed, area_index, k),
                "start_us": start,
                "out": str(out),
                "trajectory": str(traj[(area.name, k)]) if traj else None,
                "lidar": spec.run_lidar(area_index, k).model_dump(),
            }
        )
        part = spec.run_part(area_index, k, seed)
        if part is not None:
            jobs[-1]["part"] = part
    return jobs


def _run_job(job: dict[str, Any]) -> dict[str, Any]:
    """Generate one run (in a worker process): world, route, drive, prepare_drive."""
    from pnvlad_service.data.prepare import prepare_drive

    preset = SynthPreset.model_validate(job["preset"])
    area = AreaSpec.model_validate(job["area"])
    drive = _job_drive(job)
    t0 = time.perf_counter()
    keyframes = preset.keyframe_stride is not None
    res = prepare_drive(
        drive,
        Path(job["out"]) / area.name / job["run"],
        layout="oxford",
        kinds=("train", "test", "keyframe") if keyframes else ("train", "test"),
        strides_m={"keyframe": preset.keyframe_stride} if keyframes else None,
        seed=job["run_seed"] % (2**31),
        max_points_per_scan=preset.max_points_per_scan,
        box_m=preset.box_m,
        raw_scans=preset.raw_scans,
        progress=False,
    )
    return {
        "area": area.name,
        "run": job["run"],
        "scans": len(drive),
        "submaps": {r.kind: r.written for r in res.layouts},
        "seconds": time.perf_counter() - t0,
        "speed_mps": drive.speed,
        "reverse": drive.reverse,
        "lane_offset_m": drive.lane,
        "removed_objects": drive.scene.removed,
        "roadworks": len(drive.scene.roadworks),
        "sensor": drive.lidar.name or f"{drive.lidar.beams} beams",
    } | ({"part": job["part"]} if job.get("part") else {})


def _trajectory_files(
    spec: SynthPreset, trajectories: str | Path | None
) -> dict[tuple[str, int], Path]:
    """(area, run) -> the user's trajectory CSV (``<area>_<k>.csv`` or ``<k>.csv``); empty
    without ``trajectories``. ``InputError`` where a run has none."""
    files: dict[tuple[str, int], Path] = {}
    if trajectories is None:
        return files
    tdir = Path(trajectories)
    if not tdir.is_dir():
        raise InputError("not a folder of trajectory CSVs", tdir)
    for area in spec.areas:
        for k in range(spec.runs):
            for cand in (tdir / f"{area.name}_{k}.csv", tdir / f"{k}.csv"):
                if cand.is_file():
                    files[(area.name, k)] = cand
                    break
            else:
                raise InputError(f"no trajectory {area.name}_{k}.csv or {k}.csv", tdir)
    return files


def _area_jobs(
    tmp: Path,
    area_index: int,
    area: AreaSpec,
    spec: SynthPreset,
    seed: int,
    traj_files: dict[tuple[str, int], Path],
) -> list[dict[str, Any]]:
    """Write the area's test regions (chosen on its first route) and return one job per run."""
    from pnvlad_service.data.splits import TestRegions, published_regions_on, save_regions

    world = _world(area, seed, spec.city)
    route = (
        route_from_csv(world, traj_files[(area.name, 0)])
        if traj_files
        else make_route(world, area.route_m, seed)
    )
    if area.test_regions == "published":
        utm = route.points + np.asarray(area.origin)
        regions = published_regions_on(area.name, utm[:, 1], utm[:, 0])
    else:
        local = choose_test_regions(route.points, spec.test_share, spec.region_half_size)
        centres = tuple((float(y + area.origin[1]), float(x + area.origin[0])) for x, y in local)
        regions = TestRegions(centres, spec.region_half_size)
    (tmp / area.name).mkdir(parents=True)
    save_regions(tmp / area.name / "test_regions.json", regions)
    return _run_jobs_of_area(tmp, area_index, area, spec, seed, traj_files)


def _run_jobs(
    jobs: list[dict[str, Any]], workers: int | None, progress: bool, desc: str
) -> tuple[list[dict[str, Any]], int]:
    """Run every job (in worker processes when more than one): (results in job order, workers)."""
    from pnvlad_service.progress import tqdm

    n_workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    results: list[dict[str, Any]] = []
    bar = tqdm(total=len(jobs), desc=desc, unit="run", disable=not progress)
    if n_workers == 1:
        for job in jobs:
            results.append(_run_job(job))
            bar.update()
    else:
        with ProcessPoolExecutor(n_workers) as pool:
            for res in pool.map(_run_job, jobs):
                results.append(res)
                bar.update()
    bar.close()
    return results, n_workers


def _summary(
    spec: SynthPreset, seed: int, runs: list[dict[str, Any]], splits: Any
) -> dict[str, Any]:
    """What the seed determines (no timings), as written to synth.json: equal seeds give
    equal bytes."""
    return {
        "format": "pnvlad-synth",
        "version": 1,
        "preset": spec.model_dump(),
        "seed": seed,
        "runs": [{k: v for k, v in r.items() if k != "seconds"} for r in runs],
        "submaps": sum(n for r in runs for k, n in r["submaps"].items() if k != "keyframe"),
        "keyframes": sum(r["submaps"].get("keyframe", 0) for r in runs),
        "training_anchors": {g: len(t.anchors(2)) for g, t in splits.training.items()},
        "queries": {name: es.n_queries() for name, es in splits.evaluation.items()},
    }


def generate(
    preset: str | SynthPreset,
    out: str | Path,
    *,
    seed: int = 0,
    workers: int | None = None,
    trajectories: str | Path | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Write a synthetic benchmark tree to ``out`` and return its summary (also in synth.json).

    ``trajectories``: a folder of ``<area>_<k>.csv`` or ``<k>.csv`` files (northing, easting),
    one per run, to drive routes a user supplies instead of the generated ones. The steps: test
    regions and one job per run for every area, the runs (in parallel), the splits, synth.json;
    all under a temporary name renamed when complete.
    """
    from pnvlad_service.data.splits import build_splits, save_splits
    from pnvlad_service.fileio import atomic_directory, atomic_write_text

    spec = get_preset(preset) if isinstance(preset, str) else preset
    if spec.pushbroom is not None:  # one line naming the field, before anything is written
        checked_pushbroom(spec.pushbroom.model_dump())
    from pnvlad_service.data.cuts import check_box_m

    check_box_m(spec.box_m)  # model_copy(update=...) skips the field's own check
    out = Path(out)
    started = time.perf_counter()
    traj_files = _trajectory_files(spec, trajectories)
    with atomic_directory(out, overwrite=overwrite) as tmp:
        jobs = [
            job
            for ai, area in enumerate(spec.areas)
            for job in _area_jobs(tmp, ai, area, spec, seed, traj_files)
        ]
        results, n_workers = _run_jobs(jobs, workers, progress, f"synth {spec.name}")
        t_splits = time.perf_counter()
        splits = build_splits(tmp)
        save_splits(tmp / "splits.json", splits)
        if spec.keyframe_stride is not None:
            save_splits(tmp / "splits_keyframes.json", build_splits(tmp, keyframes=True))
        elapsed = time.perf_counter() - started
        runs = sorted(results, key=lambda r: (r["area"], r["run"]))
        summary = _summary(spec, seed, runs, splits)
        n_sub = summary["submaps"]
        atomic_write_text(tmp / "synth.json", json.dumps(summary, indent=1) + "\n")
        summary["seconds"] = round(elapsed, 1)
        summary["splits_seconds"] = round(time.perf_counter() - t_splits, 1)
        summary["submaps_per_second"] = round(n_sub / elapsed, 2)
        summary["workers"] = n_workers
        summary["run_seconds"] = {f"{r['area']}/{r['run']}": round(r["seconds"], 1) for r in runs}
    log.info(
        "synth %s: %d submaps in %.0f s (%.1f submaps/s, %d workers) -> %s",
        spec.name,
        n_sub,
        elapsed,
        n_sub / elapsed,
        n_workers,
        out,
    )
    return summary


def preset_of_tree(root: Path, missing: str) -> tuple[SynthPreset, int]:
    """The preset and seed a ``pnvlad synth`` tree was made with, from its ``synth.json``;
    :class:`InputError` naming the file (``missing``: why the tree needs one) otherwise."""
    meta = Path(root) / "synth.json"
    if not meta.is_file():
        raise InputError(f"no synth.json: {missing}", root)
    try:
        doc = json.loads(meta.read_text(encoding="utf-8"))
        return SynthPreset.model_validate(doc["preset"]), int(doc["seed"])
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"cannot read the preset and seed: {exc}", meta) from None


def refresh_truth(
    out: str | Path, *, trajectories: str | Path | None = None, progress: bool = True
) -> int:
    """Recompute the true poses in every frame sidecar of a ``pnvlad synth`` tree, and the
    keyframes' motion, from its ``synth.json`` (preset and seed; ``trajectories`` as given to
    :func:`generate`), by re-simulating each run's poses (no scan is cast: seconds, not the
    generation's minutes). For trees made before the truth became the window's
    (``data.truth.frame_truth``) or before keyframes carried their motion (``data.motion``);
    the submaps, CSVs and splits are left as they are. Returns the rows rewritten."""
    from pnvlad_service.data.truth import refresh_truth as refresh_run
    from pnvlad_service.progress import tqdm

    out = Path(out)
    spec, seed = preset_of_tree(out, "not a pnvlad synth tree")
    traj = _trajectory_files(spec, trajectories)
    jobs = [
        job
        for ai, area in enumerate(spec.areas)
        for job in _run_jobs_of_area(out, ai, area, spec, seed, traj)
    ]
    rows = 0
    for job in tqdm(jobs, desc="truth", unit="run", disable=None if progress else True):
        run_dir = out / job["area"]["name"] / job["run"]
        if not run_dir.is_dir():
            raise InputError("run folder missing (is this the tree synth.json describes?)", run_dir)
        drive = _job_drive(job)
        rows += refresh_run(run_dir, drive.poses, drive.true_poses, drive.timestamps)
    log.info("refreshed the true poses and keyframes' motion of %d submaps in %s", rows, out)
    return rows
