"""A drive's 6-DoF trajectories as the files trajectory tools read (evo's ``evo_traj`` and
``evo_ape``): TUM (``t x y z qx qy qz qw``, one pose a line) and KITTI (the first three rows of
each 4 x 4, one pose a line), for the pose and for the truth, all in the ``map`` frame
(:mod:`.step`).

:class:`Trajectories` writes, for ``OUT``:

- ``OUT.tum``: every scan with a pose (as the CSV's ``pose_*`` columns: verified or carried
  on by the odometry); ``OUT.truth.tum``: every scan with a truth;
- ``OUT.kitti`` and ``OUT.truth.kitti``: the scans with both, pose and truth line by line
  (KITTI files have no times: ``evo_ape kitti OUT.truth.kitti OUT.kitti`` pairs them by
  line), and ``OUT.kitti.times`` (seconds, a line a pose, as KITTI's ``times.txt``).

Each file starts with ``#`` lines naming the frame and its origin in UTM (evo skips them).
Numbers are written with 9 decimals (nanoseconds, and well below a millimetre).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.fileio import atomic_write_text
from pnvlad_service.localization.outputs.step import DriveStep, Frames, MapView, quaternion


def tum_line(t_s: float, pose: np.ndarray) -> str:
    """One TUM line: time (s), position, quaternion (x, y, z, w)."""
    q = quaternion(pose[:3, :3])
    x, y, z = (float(v) for v in pose[:3, 3])
    return " ".join(f"{v:.9f}" for v in (t_s, x, y, z, *q))


def kitti_line(pose: np.ndarray) -> str:
    """One KITTI line: the first three rows of ``pose``, row by row."""
    return " ".join(f"{float(v):.9f}" for v in np.asarray(pose)[:3, :4].reshape(-1))


class Trajectories:
    """The TUM and KITTI files of a drive (module doc) under ``out`` (a path without suffix:
    ``drive`` writes ``drive.tum``, ...). The files are written at :meth:`close`, each
    atomically; the folder is checked when it is made (an unwritable one fails then)."""

    def __init__(self, out: str | Path) -> None:
        self.out = Path(out)
        self.name = f"--trajectories {self.out}"
        self.out.parent.mkdir(parents=True, exist_ok=True)
        probe = self.out.with_name(f".{self.out.name}.probe")
        probe.write_text("")  # an unwritable folder fails now, not after the drive
        probe.unlink()
        self.frames = Frames((0.0, 0.0))
        self.poses: list[tuple[int, np.ndarray]] = []
        self.truths: list[tuple[int, np.ndarray]] = []
        self.pairs: list[tuple[int, np.ndarray, np.ndarray]] = []

    def start(self, frames: Frames, view: MapView | None) -> None:
        self.frames = frames

    def step(self, step: DriveStep) -> None:
        pose = None if step.pose is None else self.frames.to_map(step.pose)
        truth = None if step.truth is None else self.frames.to_map(step.truth)
        if pose is not None:
            self.poses.append((step.stamp_ns, pose))
        if truth is not None:
            self.truths.append((step.stamp_ns, truth))
        if pose is not None and truth is not None:
            self.pairs.append((step.stamp_ns, pose, truth))

    def _header(self, what: str) -> str:
        east, north = self.frames.origin
        return (
            f"# pnvlad {what}: frame map = UTM east, north, up minus ({east:.3f}, {north:.3f}) m"
            + (f", zone {self.frames.utm_zone}" if self.frames.utm_zone else "")
            + "; sensor -> map\n"
        )

    def close(self) -> list[Path]:
        files = {
            ".tum": (self._header("pose, TUM: t x y z qx qy qz qw"),
                     [tum_line(t / 1e9, p) for t, p in self.poses]),
            ".truth.tum": (self._header("truth, TUM: t x y z qx qy qz qw"),
                           [tum_line(t / 1e9, p) for t, p in self.truths]),
            ".kitti": (self._header("pose, KITTI: scans with a pose and a truth"),
                       [kitti_line(p) for _, p, _ in self.pairs]),
            ".truth.kitti": (self._header("truth, KITTI: scans with a pose and a truth"),
                             [kitti_line(g) for _, _, g in self.pairs]),
            ".kitti.times": ("", [f"{t / 1e9:.9f}" for t, _, _ in self.pairs]),
        }  # fmt: skip
        written = []
        for suffix, (head, lines) in files.items():
            if not lines:
                continue
            path = self.out.with_name(self.out.name + suffix)
            atomic_write_text(path, head + "".join(f"{line}\n" for line in lines))
            written.append(path)
        return written
