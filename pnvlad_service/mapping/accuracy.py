"""How right a map is, where the simulator's truth is known: read from the tree's own files.

- **Position error** of each entry: the horizontal distance between where the map puts its
  frame's origin (the sidecar's origin) and where that frame truly is (its true position).
- **Disagreement between runs** at one place: for each entry and its truly nearest entry of
  another run (within ``pair_m``), how far apart the two runs' maps put the same physical
  point (the second entry's true origin), horizontally. It is what a drive localised against
  one run and then another sees as a jump.

Both read a tree's frame sidecars only, so a recorded tree and its aligned copy are measured
alike and independently of how the alignment was computed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from pnvlad_service.data.tree import BenchmarkTree, Kind
from pnvlad_service.errors import InputError


@dataclass(frozen=True)
class Accuracy:
    """``errors_m`` float64 [N]: each entry's position error; ``yaw_errors_deg`` [N];
    ``disagreement_m`` [P]: each pair's (see the module doc)."""

    errors_m: np.ndarray
    yaw_errors_deg: np.ndarray
    disagreement_m: np.ndarray

    def summary(self) -> dict[str, Any]:
        def q(x: np.ndarray) -> dict[str, float]:
            if not len(x):
                return {}
            p = np.percentile(x, [50, 90, 99])
            return {
                "median": round(float(p[0]), 4),
                "p90": round(float(p[1]), 4),
                "p99": round(float(p[2]), 4),
                "max": round(float(x.max()), 4),
            }

        return {
            "entries": len(self.errors_m),
            "position_error_m": q(self.errors_m),
            "yaw_error_deg": q(self.yaw_errors_deg),
            "pairs": len(self.disagreement_m),
            "disagreement_m": q(self.disagreement_m),
        }


def tree_accuracy(
    root: str | Path, kind: Kind = "keyframe", pair_m: float = 2.5, dataset: str | None = None
) -> Accuracy:
    """The accuracy of the ``kind`` entries of the tree at ``root`` (see the module doc), or
    of its ``dataset`` alone. ``InputError`` when an entry has no true pose."""
    tree = BenchmarkTree(root)
    origin, true_pos, yaw, run_of = [], [], [], []
    for name in [dataset] if dataset is not None else tree.datasets:
        for run in tree.runs(name):
            frames = tree.frames(name, run, kind) if tree.has(name, run, kind) else None
            if not frames:
                continue
            for f in frames:
                if f.true_position is None or f.true_yaw_deg is None:
                    raise InputError("no true pose in the frame sidecar", f"{name}/{run}")
                origin.append(f.origin)
                true_pos.append(f.true_position)
                yaw.append(f.true_yaw_deg)
                run_of.append(f"{name}/{run}")
    if not origin:
        raise InputError(f"no {kind} entries with frame sidecars", source=root)
    o, t, y = np.array(origin), np.array(true_pos), np.radians(np.array(yaw))
    errors = np.linalg.norm(o[:, :2] - t[:, :2], axis=1)
    # The laid frame has UTM axes: the true frame is turned by true_yaw against it.
    yaw_err = np.abs(np.degrees(np.angle(np.exp(1j * y))))
    return Accuracy(errors, yaw_err, _disagreement(o, t, y, np.array(run_of), pair_m))


def _disagreement(
    o: np.ndarray, t: np.ndarray, yaw: np.ndarray, runs: np.ndarray, pair_m: float
) -> np.ndarray:
    """Each entry against the truly nearest entry of every other run within ``pair_m``."""
    tree = cKDTree(t[:, :2])
    out = []
    for i, near in enumerate(tree.query_ball_point(t[:, :2], pair_m)):
        best: dict[str, int] = {}
        for j in near:
            if runs[j] == runs[i]:
                continue
            d = float(np.hypot(*(t[j, :2] - t[i, :2])))
            if runs[j] not in best or d < np.hypot(*(t[best[runs[j]], :2] - t[i, :2])):
                best[runs[j]] = j
        for j in best.values():
            c, s = np.cos(-yaw[i]), np.sin(-yaw[i])
            rel = t[j, :2] - t[i, :2]
            local = np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]])
            out.append(float(np.linalg.norm(o[i, :2] + local - o[j, :2])))
    return np.array(out)
