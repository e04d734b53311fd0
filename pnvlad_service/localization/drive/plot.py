"""A drive as a PNG (extra ``plot``), either policy's: the map's entries in grey, the drive's
track, the answers or poses coloured by what became of them and, with the truth, their errors
along the drive in a second panel."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import MissingDependencyError
from pnvlad_service.fileio import atomic_open
from pnvlad_service.localization.drive.report import (
    FAR_M,
    GOOD_M,
    WRONG_POSE_M,
    summarise,
)
from pnvlad_service.localization.drive.rows import PER_SCAN, DriveRow, Policy
from pnvlad_service.localization.drive.tracking import LOST, SEARCHING, TRACKING


def plot_drive(
    rows: Sequence[DriveRow],
    path: str | Path,
    policy: Policy,
    *,
    map_ne: np.ndarray | None = None,
    trajectory_ne: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """The drive as a PNG at ``path`` (written atomically): a map (easting right, northing up)
    and, with the truth, the errors along the drive.

    ``map_ne``: float [M, 2] (northing, easting) of the map's entries, in grey;
    ``trajectory_ne`` (per-scan): float [T, 2] of the drive's poses, a line. Per-scan: each
    answer's top-1 match, a dot coloured by its verification (green verified, red rejected,
    blue when the service does not verify), with a thin line to where the scan really was;
    its error in the second panel. Tracked: the truth as a black line and the poses coloured
    by state (verified tracking green, a fix blue, predicted orange, the scans that searched
    red on the truth, lost circled); the pose errors and the states in the second panel."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        what = "The replay figure" if policy == PER_SCAN else "The follow figure"
        raise MissingDependencyError("matplotlib", "plot", what) from None
    draw = _per_scan if policy == PER_SCAN else _tracked
    fig = draw(plt, rows, map_ne, trajectory_ne, title)
    fig.tight_layout()
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, dpi=110, format="png")
    plt.close(fig)
    return path


def _style(ax: Any, title: str) -> None:
    """A drive's map panel: metres east and north, equal scales."""
    ax.set_xlabel("easting (m)")
    ax.set_ylabel("northing (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)


def _figure(plt: Any, two: bool, width: float) -> tuple[Any, Any]:
    fig, axes = plt.subplots(1, 2 if two else 1, figsize=(width if two else 7, 6), squeeze=False)
    return fig, axes


def _per_scan(
    plt: Any, rows: Sequence[DriveRow], map_ne: Any, trajectory_ne: Any, title: str
) -> Any:
    has_errors = any(r.error_m is not None for r in rows)
    fig, axes = _figure(plt, has_errors, 13)
    ax = axes[0, 0]
    if map_ne is not None and len(map_ne):
        m = np.asarray(map_ne, dtype=np.float64)
        ax.scatter(m[:, 1], m[:, 0], s=6, c="0.75", label=f"map ({len(m)} submaps)", zorder=1)
    if trajectory_ne is not None and len(trajectory_ne):
        t = np.asarray(trajectory_ne, dtype=np.float64)
        ax.plot(t[:, 1], t[:, 0], "-", c="0.2", lw=1.0, label="drive (bag poses)", zorder=2)
    groups = [
        ("verified", "tab:green", lambda r: r.verified is True),
        ("not verified", "tab:red", lambda r: r.verified is False),
        ("answer", "tab:blue", lambda r: r.verified is None),
    ]
    answered = [r for r in rows if r.answered]
    for label, colour, pick in groups:
        sel = [r for r in answered if pick(r)]
        if not sel:
            continue
        for r in sel:
            if r.true_easting is not None:
                ax.plot([r.true_easting, r.easting], [r.true_northing, r.northing], "-",
                        c=colour, lw=0.6, alpha=0.6, zorder=3)  # fmt: skip
        e = [r.easting for r in sel]
        n = [r.northing for r in sel]
        ax.scatter(e, n, s=18, c=colour, label=f"{label} ({len(sel)})", zorder=4)
    _style(ax, title or "replay")
    if has_errors:
        ax2 = axes[0, 1]
        for label, colour, pick in groups:
            sel = [r for r in answered if pick(r) and r.error_m is not None]
            if sel:
                ax2.scatter([r.time_s for r in sel], [r.error_m for r in sel], s=14, c=colour,
                            label=label)  # fmt: skip
        ax2.axhline(FAR_M, c="0.4", ls="--", lw=0.8, label=f"{FAR_M:g} m")
        ax2.set_yscale("symlog", linthresh=1.0)
        ax2.set_ylim(bottom=0.0)  # errors are distances: no negative half of the axis
        ax2.set_xlabel("time in the bag (s)")
        ax2.set_ylabel("error of the top-1 submap (m)")
        s = summarise(rows, PER_SCAN)
        ax2.set_title(
            f"median {s.median_place_error_m:.1f} m, {s.beyond_m} of {s.answered} beyond "
            f"{FAR_M:g} m"
            if s.median_place_error_m is not None
            else "errors"
        )
        ax2.legend(loc="best", fontsize=8)
    return fig


def _tracked(
    plt: Any, rows: Sequence[DriveRow], map_ne: Any, trajectory_ne: Any, title: str
) -> Any:
    has_truth = any(r.true_northing is not None for r in rows)
    fig, axes = _figure(plt, has_truth, 14)
    ax = axes[0, 0]
    if map_ne is not None and len(map_ne):
        m = np.asarray(map_ne, dtype=np.float64)
        ax.scatter(m[:, 1], m[:, 0], s=5, c="0.8", label=f"map ({len(m)} entries)", zorder=1)
    if has_truth:
        t = [(r.true_easting, r.true_northing) for r in rows if r.true_northing is not None]
        ax.plot(*zip(*t, strict=True), "-", c="0.15", lw=1.0, label="truth", zorder=2)
    groups = [
        ("tracking, verified", "tab:green", "o", lambda r: r.verified and r.how == "registered"),
        ("fix", "tab:blue", "*", lambda r: r.how == "fix"),
        ("predicted (not verified)", "tab:orange", "o", lambda r: r.how == "predicted"),
    ]
    for label, colour, marker, pick in groups:
        sel = [r for r in rows if pick(r) and r.pose_easting is not None]
        if sel:
            e, n = [r.pose_easting for r in sel], [r.pose_northing for r in sel]
            size = 9 if marker == "o" else 60
            ax.scatter(e, n, s=size, c=colour, marker=marker, label=f"{label} ({len(sel)})",
                       zorder=4)  # fmt: skip
    search = [r for r in rows if r.pose_easting is None and r.true_easting is not None]
    if search:
        ax.scatter([r.true_easting for r in search], [r.true_northing for r in search], s=9,
                   c="tab:red", marker="x", label=f"searching, no pose ({len(search)})",
                   zorder=3)  # fmt: skip
    lost = [r for r in rows if r.event == "lost" and r.true_easting is not None]
    if lost:
        ax.scatter([r.true_easting for r in lost], [r.true_northing for r in lost], s=80,
                   facecolors="none", edgecolors="k", label="lost", zorder=5)  # fmt: skip
    _style(ax, title or "follow")
    if has_truth:
        _tracked_errors(axes[0, 1], rows, groups)
    return fig


def _tracked_errors(ax2: Any, rows: Sequence[DriveRow], groups: list) -> None:
    """The pose errors along the drive, the map's own truth's and the states as bands."""
    for label, colour, _, pick in groups:
        sel = [r for r in rows if pick(r) and r.pose_error_m is not None]
        if sel:
            ax2.scatter([r.time_s for r in sel], [r.pose_error_m for r in sel], s=8, c=colour,
                        label=label)  # fmt: skip
    merr = [r for r in rows if r.verified and r.map_error_m is not None]
    if merr:
        ax2.scatter([r.time_s for r in merr], [r.map_error_m for r in merr], s=4, c="0.5",
                    label="against the map's own truth")  # fmt: skip
    states = {SEARCHING: "tab:red", LOST: "k", TRACKING: None}
    for r in rows:
        c = states.get(r.state or "")
        if c is not None:
            ax2.axvline(r.time_s, c=c, lw=0.4, alpha=0.25)
    ax2.axhline(GOOD_M, c="0.4", ls="--", lw=0.8, label=f"{GOOD_M:g} m")
    ax2.axhline(WRONG_POSE_M, c="tab:red", ls=":", lw=0.8, label=f"{WRONG_POSE_M:g} m")
    ax2.set_yscale("symlog", linthresh=0.1)
    ax2.set_ylim(bottom=0.0)
    ax2.set_xlabel("time in the drive (s); red bands: searching, black: lost")
    ax2.set_ylabel("pose error (m)")
    ax2.legend(loc="best", fontsize=8)
