"""A whole drive from its :class:`~.config.DriveConfig`: the drive run by its policy, the CSV,
the PNG and the report (``pnvlad localize --rosbag`` / ``--kitti``).

:func:`run_job` takes the drive already opened (any source: a bag, a KITTI sequence, ...) and
the :class:`~.service.Service` to ask; it returns a :class:`DriveResult` whose
:meth:`~DriveResult.lines` are what the command prints.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.localization.drive.config import DriveConfig, OutputConfig
from pnvlad_service.localization.drive.maps import DriveMap
from pnvlad_service.localization.drive.plot import plot_drive
from pnvlad_service.localization.drive.report import DriveSummary, stage_means, summarise
from pnvlad_service.localization.drive.rows import PER_SCAN, TRACKED, DriveRow, write_rows
from pnvlad_service.localization.drive.runner import Windows, choose_odometry, run_drive
from pnvlad_service.localization.drive.service import Service
from pnvlad_service.localization.outputs.sinks import Outputs, open_outputs

#: The default name of each policy's outputs: DRIVE.follow.csv, DRIVE.replay.csv.
STEM = {TRACKED: "follow", PER_SCAN: "replay"}


@dataclass(frozen=True)
class DriveResult:
    """A drive done: its ``rows``, ``summary``, the files ``written`` and, tracked, the
    ``odometry`` used; ``errors``: the outputs that failed (one line each; the CSV is written
    whatever they did)."""

    rows: list[DriveRow]
    summary: DriveSummary
    written: list[Path]
    odometry: str | None = None
    errors: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """What ``pnvlad localize`` prints: the files written, the odometry and the stages'
        mean times (tracked), the summary line."""
        out = [f"wrote {', '.join(str(p) for p in self.written)}"]
        if self.summary.policy == TRACKED:
            out.append(f"odometry: {self.odometry}")
            for mode, means in stage_means(self.rows).items():
                parts = ", ".join(f"{k} {v:.1f}" for k, v in means.items() if k != "scans")
                what = "searching" if mode == "search" else "tracking"
                out.append(f"stages, {what} ({int(means['scans'])} scans), mean ms: {parts}")
        out.append(self.summary.line())
        return out


def run_job(
    config: DriveConfig,
    drive: Any,
    service: Service,
    *,
    source: Path,
    truth: np.ndarray | None = None,
) -> DriveResult:
    """Run ``drive`` (opened from ``source``, the file or folder it came from) against
    ``service`` as ``config`` says; ``truth``: float64 [T, 4, 4] of every scan (NaN where
    unknown; default: the drive's poses). Writes OUT.csv and (``output.plot``) OUT.png."""
    config.check()
    policy, every = config.policy, config.scan_every
    poses = getattr(drive, "poses", None)
    how = choose_odometry(config.odometry, poses is not None) if policy == TRACKED else None
    truth = poses if truth is None else truth
    out = config.output.out or Path(source).with_name(f"{drive.name}.{STEM[policy]}")
    bundle = config.service.index or config.output.map_bundle
    with_truth = policy == TRACKED and truth is not None
    known = None if bundle is None else DriveMap.load(bundle, with_truth=with_truth)
    windows = None
    if policy == PER_SCAN and config.window_m is not None:
        posed = config.odometry == "kiss-icp" or (config.odometry == "auto" and poses is None)
        record = known.record() if known is not None else service.map_record()
        windows = Windows(config.window_m, odometry=posed, map_record=record)
    outputs = _outputs(config.output, bundle)
    t0 = time.perf_counter()
    try:
        rows = run_drive(
            drive, service.ask, policy, every=every, odometry=how or "none", truth=truth,
            config=config.tracking, windows=windows, progress=config.output.progress,
            positions=None if known is None else known.positions,
            truth_of_map=None if known is None else known.truth, outputs=outputs,
        )  # fmt: skip
    finally:
        wall = time.perf_counter() - t0
        outputs.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    written = [write_rows(rows, out.with_name(out.name + ".csv"), policy)]
    if config.output.plot:
        trajectory = None if poses is None or policy == TRACKED else poses[:, [1, 0], 3]
        written.append(plot_drive(
            rows, out.with_name(out.name + ".png"), policy, title=_title(config, drive.name),
            map_ne=None if known is None else known.ne, trajectory_ne=trajectory,
        ))  # fmt: skip
    written.extend(outputs.written)
    return DriveResult(rows, summarise(rows, policy, wall), written, how, tuple(outputs.errors))


def _outputs(output: OutputConfig, bundle: Path | None) -> Outputs:
    """The robotics outputs ``output`` asks for, opened and started with the map of
    ``bundle`` (its entries, a cloud of them and its zone; ``output.utm_zone`` when given)."""
    outputs = open_outputs(foxglove=output.foxglove, mcap=output.mcap, ros2_bag=output.ros2_bag,
                           trajectories=output.trajectories)  # fmt: skip
    if not outputs.sinks and not outputs.errors:
        return outputs
    view = None
    if bundle is not None and outputs.sinks:
        from pnvlad_service.localization.outputs.map_view import load_map_view

        view = load_map_view(bundle)
    outputs.start(view, output.utm_zone)
    return outputs


def _title(config: DriveConfig, name: str) -> str:
    every = config.scan_every
    if config.policy == TRACKED:
        return f"{name}: every scan" if every == 1 else f"{name}: one scan in {every}"
    window = "" if config.window_m is None else f", the last {config.window_m:g} m a query"
    topic = "" if config.source.cloud_topic is None else f"{config.source.cloud_topic}, "
    return f"{name}: {topic}one scan in {every}{window}"
