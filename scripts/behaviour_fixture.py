"""The inputs of a behaviour snapshot, built once (scripts/behaviour_snapshot.py explains).

``build_fixture(out)`` makes them with stable commands; ``read_fixture(root)`` checks that
none changed since (every file's sha256 is in ``fixture.json``, written last).
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
FIXTURE_FORMAT = 1
#: The environment every process of a snapshot runs in (PNVLAD_* inherited are dropped).
FIXED_ENV = {
    "TERMINAL_WIDTH": "100",
    "COLUMNS": "100",
    "NO_COLOR": "1",
    "_TYPER_FORCE_DISABLE_TERMINAL": "1",
    "PYTHONHASHSEED": "0",
    "TZ": "UTC",
    "OMP_NUM_THREADS": "2",
    "PNVLAD_THREADS": "2",
}

#: The commands that make the fixture (the held-out run is the first of the city's three).
SYNTH = "-q synth --preset tiny --seed 3 --workers 2 --no-progress"
TRAIN = "-q train -c compact --max-steps 2 --seed 0 --workers 2 --no-progress"
INDEX = "-q index build --no-progress --layout"
BAG = "--preset tiny --seed 3 --run 0 --max-scans 30"


def pnvlad(*args: str) -> str:
    """Run ``pnvlad ARGS`` with this python; its stdout (SystemExit with its output if it
    fails)."""
    done = subprocess.run(
        [sys.executable, "-m", "pnvlad_cli.main", *args],
        env=child_env(),
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(
            f"pnvlad {' '.join(args[:3])} failed ({done.returncode}):\n"
            f"{done.stdout[-2000:]}{done.stderr[-4000:]}"
        )
    return done.stdout


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment without PNVLAD_* variables, with FIXED_ENV and ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PNVLAD_")}
    return {**env, **FIXED_ENV, **(extra or {})}


def build_fixture(out: Path) -> None:
    """Every input of a snapshot under ``out``, fixture.json last (the bundles record the
    model's and the tree's paths: a fixture is built where it stays)."""
    import numpy as np

    if out.exists():
        raise SystemExit(f"{out}: exists; remove it first (a fixture is built once)")
    out.mkdir(parents=True)
    work, t0 = out, time.perf_counter()
    city, model = work / "city", work / "train" / "model"
    print(f"synth: pnvlad {SYNTH}")
    pnvlad(*SYNTH.split(), "--out", str(city))
    runs = sorted(p.name for p in (city / "business").iterdir() if p.is_dir())
    held, mapped = runs[0], runs[1:]
    print(f"train: pnvlad {TRAIN}")
    pnvlad(*TRAIN.split(), "--root", str(city), "-o", str(work / "train"))
    for name, layout in (("map.index", "test"), ("keys.index", "keyframe")):
        print(f"index: pnvlad {INDEX} {layout} -o {name}")
        runs_args = [a for r in mapped for a in ("--run", r)]
        where = ["-m", str(model), "-r", str(city), "-o", str(work / name)]
        pnvlad(*INDEX.split(), layout, *where, *runs_args)
    print(f"drive: benchmarks/make_rosbag.py {BAG}")
    script = str(REPO / "benchmarks" / "make_rosbag.py")
    made = subprocess.run(
        [sys.executable, script, *BAG.split(), "--out", str(work / "drive")],
        env=child_env(),
        capture_output=True,
        text=True,
        check=True,
    )
    origin = re.search(r"--origin (\S+)", made.stdout).group(1)  # type: ignore[union-attr]
    queries = write_queries(work, city / "business" / held, mapped[0], np)
    kitti = write_kitti(work / "kitti", np)
    record = {
        "format": FIXTURE_FORMAT,
        "held_out_run": f"business/{held}",
        "map_runs": [f"business/{r}" for r in mapped],
        "model": "train/model",
        "maps": {"map": "map.index", "keys": "keys.index"},
        "server_env": SERVER_ENV,
        "queries": queries,
        "bag": {"path": "drive", "origin": origin, "scans": 30},
        "kitti": kitti,
        "files": digests(work),
    }
    (work / "fixture.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    print(f"fixture: {out} in {time.perf_counter() - t0:.0f} s")


#: The servers' settings (a 2-step model: every candidate may be registered, a low threshold,
#: sigma not checked, as tests/localization/test_cli_follow.py serves the tiny city).
SERVER_ENV = {
    "PNVLAD_RERANK": "100",
    "PNVLAD_VERIFY_THRESHOLD": "0.04",
    "PNVLAD_PRIOR_MAX_SIGMA": "0",
    "PNVLAD_VERIFY_CROWDED_THREADS": "0",
    "PNVLAD_WARM_UP": "2",
}


def write_queries(work: Path, run: Path, map_run: str, np: Any) -> dict[str, Any]:
    """queries/*.npy from the held-out ``run``: three submaps (with their frames' scales),
    two raw scans (with priors 1.5 m and 3 degrees off their true poses) and a window."""
    q = work / "queries"
    q.mkdir()
    subs = sorted((run / "pointcloud_20m").glob("*.bin"))
    frames = {r["timestamp"]: r for r in read_rows(run / "pointcloud_locations_20m.frames.csv")}
    out: dict[str, Any] = {"submaps": [], "scans": []}
    for k, path in enumerate(subs[i] for i in (1, len(subs) // 2, len(subs) - 2)):
        np.save(q / f"submap{k}.npy", np.fromfile(path, "<f8").reshape(-1, 3))
        scale = abs(float(frames[path.stem]["scale"]))
        entry = {"file": f"queries/submap{k}.npy", "timestamp": int(path.stem), "scale": scale}
        out["submaps"].append(entry)
    scans = read_rows(run / "raw_scans.csv")
    for k, row in enumerate(scans[i] for i in (2, len(scans) // 2)):
        pts = np.fromfile(run / "raw_scans" / f"{row['timestamp']}.bin", "<f4").reshape(-1, 4)
        np.save(q / f"scan{k}.npy", pts[:, :3])
        prior = {
            "northing": round(float(row["true_northing"]) + 1.5, 3),
            "easting": round(float(row["true_easting"]) - 1.0, 3),
            "yaw_deg": round(float(row["true_yaw_deg"]) + 3.0, 3),
            "radius_m": 20.0,
        }
        stamp = int(row["timestamp"])
        out["scans"].append({"file": f"queries/scan{k}.npy", "timestamp": stamp, "prior": prior})
    out["prior_run"] = f"business/{map_run}"
    out["window"] = write_window(q / "window.npy", work / "map.index", np)
    return out


def read_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def write_window(path: Path, bundle: Path, np: Any) -> dict[str, Any]:
    """The first 20 m of the held-out run laid as the map's windows (the client's way)."""
    from pnvlad_service.data.accumulate import WindowAccumulator
    from pnvlad_service.index.manifest import Manifest
    from pnvlad_service.synth.generate import get_preset, simulated_drive

    drive = simulated_drive(get_preset("tiny"), 0, 0, 3)
    window = WindowAccumulator.for_map(Manifest.read(bundle).map_record, 20.0)
    last = 0
    for i in range(len(drive)):
        window.add(drive.scan(i), drive.poses[i])
        last = i
        if np.linalg.norm(drive.poses[i][:2, 3] - drive.poses[0][:2, 3]) >= 24.0:
            break
    np.save(path, np.asarray(window.cloud(), dtype=np.float64))
    return {"file": "queries/window.npy", "scans": f"0..{last}", "window_m": 20.0}


def write_kitti(folder: Path, np: Any) -> dict[str, Any]:
    """The held-out run's first 20 scans as a KITTI sequence: velodyne/*.bin, poses.txt (the
    run's recorded poses, relative to its first), times.txt and an identity calib.txt."""
    import math

    from pnvlad_service.synth.generate import get_preset, simulated_drive

    drive = simulated_drive(get_preset("tiny"), 0, 0, 3)
    (folder / "velodyne").mkdir(parents=True)
    first = drive.poses[0]
    lines, times = [], []
    for i in range(20):
        pts = np.asarray(drive.scan(i), dtype=np.float32)
        np.c_[pts, np.zeros(len(pts), np.float32)].tofile(folder / "velodyne" / f"{i:06d}.bin")
        rel = np.linalg.inv(first) @ drive.poses[i]
        lines.append(" ".join(f"{v:.9e}" for v in rel[:3, :4].ravel()))
        times.append(f"{(drive.timestamps[i] - drive.timestamps[0]) / 1e6:.6f}")
    (folder / "poses.txt").write_text("\n".join(lines) + "\n")
    (folder / "times.txt").write_text("\n".join(times) + "\n")
    (folder / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    yaw = math.degrees(math.atan2(first[1, 0], first[0, 0]))
    return {
        "path": "kitti",
        "origin": f"{float(first[1, 3])!r},{float(first[0, 3])!r}",
        "yaw": repr(float(yaw)),
    }


def digests(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` but fixture.json, by path relative to it."""
    out = {}
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if rel != "fixture.json":
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def read_fixture(root: Path) -> dict[str, Any]:
    """fixture.json, after checking that every file it lists is there and unchanged."""
    try:
        record = json.loads((root / "fixture.json").read_text())
    except (OSError, ValueError) as exc:
        why = f"not a fixture ({exc}); build one with `fixture --out DIR`"
        raise SystemExit(f"{root}: {why}") from None
    if record.get("format") != FIXTURE_FORMAT:
        raise SystemExit(
            f"{root}/fixture.json: format {record.get('format')}, expected {FIXTURE_FORMAT}"
        )
    now = digests(root)
    changed = sorted(p for p, d in record["files"].items() if now.get(p) != d)
    if changed:
        raise SystemExit(f"{root}: the fixture changed since it was built: {changed[:5]}")
    return record
