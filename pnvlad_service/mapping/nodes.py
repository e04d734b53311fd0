"""The pose graph's nodes: a map's entries, run by run, as the recording laid them.

A node is one map entry (a keyframe by default: one scan every few metres) with its points in
metres in its local frame and the pose that frame was laid with: UTM axes at the entry's
recorded origin (:attr:`~pnvlad_service.data.frames.SubmapFrame.map_pose`). Alignment finds,
for each node, the pose that frame truly has; the recorded one is never changed.

Poses in this stage are float64 [4, 4], local frame -> UTM (easting, northing, height).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pnvlad_service.data.frames import SubmapFrame
from pnvlad_service.data.tree import BenchmarkTree, Kind
from pnvlad_service.errors import InputError
from pnvlad_service.io.submap import read_submap

log = logging.getLogger(__name__)

#: The largest step between two consecutive nodes of a run that is not a jump in its poses:
#: keyframes lie 5 m apart, test submaps 20 m (default ``max_step_m`` is 4 strides).
MAX_STEP_STRIDES = 4.0


@dataclass
class RunNodes:
    """The nodes of one run, in drive order.

    ``name``: ``dataset/run``; ``stamps`` int64 [N] microseconds; ``poses`` float64 [N, 4, 4]
    the recorded (laid) poses; ``truth`` float64 [N, 4, 4] the simulator's true poses of the
    same frames, or ``None``; ``frames`` the sidecar rows; ``paths`` the ``.bin`` files (or
    ``None`` for nodes made in memory, whose ``clouds`` hold the metres); ``motion`` float64
    [N, 3] each node's heading, speed and yaw rate through its sweep
    (:func:`~.deskew.run_motion`), or ``None``: with it, :meth:`metres` gives the scans
    de-skewed at ``sweep_hz``; ``skewed``: whether each node is one scan given as its sensor
    fired it through a moving sweep (what :func:`~.deskew.run_motion` then corrects);
    ``recorded_motion`` float64 [N, 3]: the same three as the recording's poses gave them at
    each node (:attr:`~pnvlad_service.data.frames.SubmapFrame.sweep_motion`), or ``None``;
    ``sensor_hz``: the sweeps a second of the run's sensor where the tree records it (a
    synthetic tree's ``synth.json``), ``None`` where it does not."""

    name: str
    stamps: np.ndarray
    poses: np.ndarray
    truth: np.ndarray | None = None
    frames: list[SubmapFrame] = field(default_factory=list)
    paths: list[Path] | None = None
    clouds: list[np.ndarray] | None = None
    motion: np.ndarray | None = None
    sweep_hz: float = 10.0
    skewed: bool = False
    recorded_motion: np.ndarray | None = None
    sensor_hz: float | None = None

    def __len__(self) -> int:
        return len(self.stamps)

    def metres(self, k: int) -> np.ndarray:
        """Node ``k``'s points in metres in its local frame: float64 [M, 3]."""
        if self.clouds is not None:
            points = np.asarray(self.clouds[k], dtype=np.float64)
        else:
            assert self.paths is not None
            points = self.frames[k].local_m(read_submap(self.paths[k]))
        if self.motion is None:
            return points
        from pnvlad_service.mapping.deskew import deskew_points

        heading, speed, rate = self.motion[k]
        return deskew_points(points, heading, speed, rate, self.sweep_hz)

    def normalised(self, k: int) -> np.ndarray:
        """Node ``k``'s cloud as the encoder sees it: float32 [4096, 3] (tree nodes only)."""
        if self.paths is None:
            raise InputError("nodes made in memory have no encoder input", self.name)
        return read_submap(self.paths[k]).astype(np.float32)


@dataclass
class MapNodes:
    """Every node of a map: the runs in order and, flattened, node ``g`` of the map is node
    ``local[g]`` of run ``run_of[g]``."""

    runs: list[RunNodes]
    run_of: np.ndarray = field(init=False)
    local: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        sizes = [len(r) for r in self.runs]
        self.run_of = np.repeat(np.arange(len(self.runs)), sizes)
        self.local = np.concatenate([np.arange(n) for n in sizes]) if sizes else np.zeros(0, int)

    def __len__(self) -> int:
        return len(self.run_of)

    @property
    def poses(self) -> np.ndarray:
        """float64 [N, 4, 4]: every node's recorded pose."""
        return np.concatenate([r.poses for r in self.runs])

    @property
    def truth(self) -> np.ndarray | None:
        """float64 [N, 4, 4]: every node's true pose, or ``None`` unless every run has it."""
        if any(r.truth is None for r in self.runs):
            return None
        return np.concatenate([r.truth for r in self.runs])  # type: ignore[misc]

    def starts(self) -> np.ndarray:
        """int [R]: the global index of each run's first node."""
        return np.concatenate([[0], np.cumsum([len(r) for r in self.runs])[:-1]]).astype(int)

    def metres(self, g: int) -> np.ndarray:
        return self.runs[self.run_of[g]].metres(int(self.local[g]))

    def name(self, g: int) -> str:
        run = self.runs[self.run_of[g]]
        return f"{run.name}@{int(run.stamps[self.local[g]])}"


def check_run(run: RunNodes, max_step_m: float) -> None:
    """``InputError`` naming the run (and the timestamps) when its poses are not finite, it
    has fewer than two nodes, or two consecutive nodes lie more than ``max_step_m`` apart (a
    jump in the recorded poses: nothing can be laid across it)."""
    if len(run) < 2:
        raise InputError(f"{len(run)} map entries: a run needs at least 2 to align", run.name)
    if not np.isfinite(run.poses).all():
        raise InputError("non-finite recorded poses", run.name)
    steps = np.linalg.norm(np.diff(run.poses[:, :3, 3], axis=0), axis=1)
    bad = np.flatnonzero(steps > max_step_m)
    if len(bad):
        k = int(bad[0])
        raise InputError(
            f"the recorded poses jump {steps[k]:.1f} m between entries {int(run.stamps[k])} and "
            f"{int(run.stamps[k + 1])} (more than {max_step_m:g} m between neighbours; "
            f"{len(bad)} such jumps): a recording whose poses jump cannot be aligned",
            run.name,
        )


def read_tree_nodes(
    root: str | Path, kind: Kind = "keyframe", max_step_m: float | None = None
) -> MapNodes:
    """The nodes of every run of the tree at ``root``: its ``kind`` entries (default the
    keyframes), laid by their frame sidecars. ``InputError`` naming the run that lacks them,
    has no sidecar, or whose poses jump (:func:`check_run`; ``max_step_m`` default: 4 of the
    kind's strides, measured as the run's median step).

    Keyframes are single scans: :attr:`RunNodes.skewed` unless the tree says its sensor
    de-skews (``synth.json``, which also gives the sensor's sweeps a second; a recording's
    scans are as the driver gave them)."""
    from pnvlad_service.mapping.deskew import skewed_sensors

    tree = BenchmarkTree(root)
    sensors = skewed_sensors(root) or {}
    runs: list[RunNodes] = []
    for dataset in tree.datasets:
        for run in tree.runs(dataset):
            name = f"{dataset}/{run}"
            if not tree.has(dataset, run, kind):
                raise InputError(f"no {kind} entries (prepare the run with them)", name)
            frames = tree.frames(dataset, run, kind)
            if frames is None:
                raise InputError(f"no frame sidecar for its {kind} entries", name)
            subs = tree.submaps(dataset, run, kind)
            truth = None
            if all(f.true_pose is not None for f in frames):
                truth = np.stack([f.true_pose for f in frames])  # type: ignore[misc]
            motion = None
            if frames and all(f.motion is not None for f in frames):
                motion = np.stack([f.sweep_motion for f in frames])  # type: ignore[misc]
            runs.append(
                RunNodes(
                    name,
                    np.array([f.timestamp for f in frames], dtype=np.int64),
                    np.stack([f.map_pose for f in frames]) if frames else np.zeros((0, 4, 4)),
                    truth,
                    frames,
                    [tree.root / s.path for s in subs],
                    skewed=kind == "keyframe" and sensors.get(name, 1.0) > 0,
                    recorded_motion=motion,
                    sensor_hz=sensors.get(name),
                )
            )
    if not runs:
        raise InputError("no runs", source=root)
    for r in runs:
        step = max_step_m
        if step is None:
            gaps = np.linalg.norm(np.diff(r.poses[:, :3, 3], axis=0), axis=1)
            step = MAX_STEP_STRIDES * float(np.median(gaps)) if len(gaps) else np.inf
            step = max(step, 10.0)
        check_run(r, step)
    log.info("%d runs, %d %s entries", len(runs), sum(len(r) for r in runs), kind)
    return MapNodes(runs)
