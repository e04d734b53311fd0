"""Drives built for the data tests: KITTI-style sequences of the real scans, street scans."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from pnvlad_service.data.drive import Drive

FRAMES = 40  # scans in the synthetic KITTI sequence
STEP_M = 1.5  # metres between consecutive scans (camera z, i.e. forward)
FAST = {"max_points_per_scan": 2000, "progress": False}  # small windows keep G quick


def make_kitti_sequence(
    root: Path,
    real_scans: Path,
    frames: int = FRAMES,
    step: float = STEP_M,
    forward: list[float] | None = None,
) -> Path:
    """A KITTI-style sequence: two real scans alternating, camera moving along z.

    The scans are kitti00_000000.bin and kitti00_000005.bin, real HDL-64E scans of unknown
    frames (not frames 0 and 5 of KITTI 00, whatever their names say): the poses here are made
    up, and the tests that use this need real clouds, not their true poses.

    ``forward``: the camera's z position of each frame (default ``step * i``).
    """
    seq = root / "seq"
    (seq / "velodyne").mkdir(parents=True)
    names = ["kitti00_000000.bin", "kitti00_000005.bin"]
    if forward is None:
        forward = [step * i for i in range(frames)]
    frames = len(forward)
    lines = []
    for i, z in enumerate(forward):
        os.symlink(real_scans / names[i % 2], seq / "velodyne" / f"{i:06d}.bin")
        lines.append(f"1 0 0 0 0 1 0 0 0 0 1 {z!r}")
    (seq / "poses.txt").write_text("\n".join(lines) + "\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6f}\n" for i in range(frames)))
    return seq


class CountingDrive:
    """A drive that counts scan reads and can fail at one scan (to interrupt a run)."""

    def __init__(self, inner: Drive, fail_at: int | None = None) -> None:
        self.inner = inner
        self.name = inner.name
        self.timestamps = inner.timestamps
        self.poses = inner.poses
        self.fail_at = fail_at
        self.reads: list[int] = []

    def __len__(self) -> int:
        return len(self.inner)

    def scan(self, i: int) -> np.ndarray:
        if i == self.fail_at:
            raise RuntimeError(f"simulated crash reading scan {i}")
        self.reads.append(i)
        return self.inner.scan(i)


def plain_cuts(d: list[float], window: float, stride: float) -> list[tuple[int, list[int]]]:
    """Reference cutting: (centre scan, window scans) by plain loops over travelled distance."""
    out: list[tuple[int, list[int]]] = []
    half = window / 2
    k = 0
    while half + k * stride + half <= d[-1]:
        s = half + k * stride
        k += 1
        best = 0
        for i in range(len(d)):
            if abs(d[i] - s) < abs(d[best] - s):
                best = i
        if out and out[-1][0] == best:
            continue
        out.append((best, [i for i in range(len(d)) if s - half <= d[i] <= s + half]))
    return out


class ListDrive:
    """An in-memory drive (as the synthetic city builds one): scans and poses in lists."""

    def __init__(self, scans: list[np.ndarray], poses: np.ndarray, stamps: list[int]) -> None:
        self.name = "memory"
        self.scans = scans
        self.poses = poses
        self.timestamps = np.asarray(stamps, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.scans)

    def scan(self, i: int) -> np.ndarray:
        return self.scans[i]


def read_csv_rows(path: Path) -> list[tuple[int, float, float]]:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["timestamp", "northing", "easting"]
    return [(int(t), float(n), float(e)) for t, n, e in rows[1:]]


def tree_bytes(run: Path) -> dict[str, bytes]:
    """Every submap and CSV of a run folder, by relative path."""
    return {
        str(p.relative_to(run)): p.read_bytes()
        for p in sorted(run.rglob("*"))
        if p.is_file() and not p.name.startswith(".")
    }


def write_street(scans: Path, stamps: list[int], rng: np.random.Generator) -> None:
    """Scans of a street (ground + two walls), sensor frame, as .npy files."""
    scans.mkdir(parents=True, exist_ok=True)
    for ts in stamps:
        x = rng.uniform(-15, 15, 3000)
        ground = np.c_[x[:1000], rng.uniform(-8, 8, 1000), np.full(1000, -1.7)]
        walls = np.c_[x[1000:], np.repeat([-8.0, 8.0], 1000), rng.uniform(-1.7, 6, 2000)]
        np.save(scans / f"{ts}.npy", np.vstack([ground, walls]))
