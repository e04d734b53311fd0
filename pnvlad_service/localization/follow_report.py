"""What is made of a followed drive's rows (:func:`~.follow.follow_drive`): the
:class:`FollowRow` record, a CSV of them and back (to summarise a drive again), the
:class:`FollowSummary` (first fix, share verified, errors, losses, off the map, kidnappings,
speed), the stages' mean times and a PNG. The thresholds the summary judges a pose by are here
too (docs/TRACKING.md)."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.fileio import atomic_write_rows
from pnvlad_service.localization.replay import save_track_figure, style_track_axes
from pnvlad_service.localization.tracking import LOST, SEARCHING, TRACKING

#: A verified pose farther than this from the truth is a wrong one.
WRONG_POSE_M = 5.0
#: The accuracy a verified pose should have: within this many metres and ...
GOOD_M = 1.0
#: ... degrees of the truth.
GOOD_DEG = 2.0
#: The truth farther than this from every map entry is off the map (docs/TRACKING.md).
OFF_MAP_M = 25.0
#: The truth moving more than this between two scans jumped (a kidnapped robot).
JUMP_M = 30.0


@dataclass
class FollowRow:
    """One scan of a followed drive (``None`` where unknown): the localiser's ``state``,
    ``verified``, ``how`` and ``event``; the pose; ``fitness``, ``sigma_m`` and
    ``correction_m`` (how far the registration moved the prediction) when tracking,
    ``confidence`` when searching; the ``anchor`` entry; the truth and the pose's errors
    (``pose_error_m``, ``pose_yaw_error_deg``), the errors against the map's own truth
    (``map_error_m``, ``map_yaw_error_deg``), the truth's distance to the nearest map entry
    (``off_map_m``) and the distance driven (``driven_m``); the times of the stages (ms):
    reading the scan, odometry, the localiser's step (its request included), what the service
    was ``asked`` (``search``, or ``prior``: a registration near the prediction) and its
    answer's ``server_ms`` total; ``reason``."""

    scan: int
    timestamp: int
    time_s: float
    state: str = SEARCHING
    verified: bool = False
    how: str | None = None
    event: str | None = None
    pose_northing: float | None = None
    pose_easting: float | None = None
    pose_yaw_deg: float | None = None
    fitness: float | None = None
    sigma_m: float | None = None
    correction_m: float | None = None
    confidence: float | None = None
    anchor: str | None = None
    true_northing: float | None = None
    true_easting: float | None = None
    true_yaw_deg: float | None = None
    pose_error_m: float | None = None
    pose_yaw_error_deg: float | None = None
    map_error_m: float | None = None
    map_yaw_error_deg: float | None = None
    off_map_m: float | None = None
    driven_m: float | None = None
    read_ms: float = 0.0
    odometry_ms: float = 0.0
    step_ms: float = 0.0
    asked: str | None = None
    server_ms: float | None = None
    reason: str | None = None
    stages_ms: dict[str, float] = field(default_factory=dict, repr=False)


#: The CSV's columns, in order.
COLUMNS = tuple(c for c in FollowRow.__dataclass_fields__ if c != "stages_ms")


def write_follow_csv(rows: Sequence[FollowRow], path: str | Path) -> Path:
    """The rows as a CSV (atomically), one column a :class:`FollowRow` field (:data:`COLUMNS`)."""
    return atomic_write_rows(rows, COLUMNS, path, digits=6)


def read_follow_csv(path: str | Path) -> list[FollowRow]:
    """The rows of a CSV :func:`write_follow_csv` wrote (to summarise it again)."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(FollowRow)
    rows = []
    with open(path, newline="", encoding="utf-8") as fh:
        for doc in csv.DictReader(fh):
            kw: dict[str, Any] = {}
            for f in dataclasses.fields(FollowRow):
                if f.name not in doc:
                    continue
                text, kind = doc[f.name], str(hints[f.name])
                if text == "":
                    kw[f.name] = None if "None" in kind else f.default
                elif "bool" in kind:
                    kw[f.name] = text == "true"
                elif "int" in kind:
                    kw[f.name] = int(text)
                elif "float" in kind:
                    kw[f.name] = float(text)
                else:
                    kw[f.name] = text
            rows.append(FollowRow(**kw))
    return rows


@dataclass(frozen=True)
class FollowSummary:
    """The figures of a followed drive (``None`` where the truth, or a fix, is missing).

    ``first_fix_*``: the scan, time (s) and distance driven (m) to the first verified pose;
    ``verified_share``: of the scans from the first fix on, those with a verified pose;
    ``good_share``: ... within :data:`GOOD_M` and :data:`GOOD_DEG` of the truth; errors of the
    verified poses (median and p99, against the truth and against the map's own truth);
    ``wrong``: verified poses more than :data:`WRONG_POSE_M` off; ``relocalisations``: fixes
    after the first; ``lost``: times the localiser said lost; ``off_map``: scans whose truth
    is more than ``off_map_m`` from the map, ``off_map_verified`` of them verified;
    ``to_lost``: per stretch off the map, (scans, seconds, metres from the map) from its first
    scan off the map to the last ``lost`` before the localiser next has a fix (negative: it
    said lost before the truth was that far off); ``back_to_fix``: per stretch off the map,
    (scans, seconds, metres driven) from the first scan back on the map to the next fix;
    ``jumps``: per jump of the truth (a kidnapped robot: :data:`JUMP_M` between two scans),
    (scans, seconds) from the first scan after it to the localiser's lost or reset, and to its
    next fix (``None`` when it never came);
    ``to_fix``: per loss of the track (lost or a reset), (scans, seconds, metres) to the next
    fix; ``wall_s`` and ``duration_s``: the replay's wall time and the drive's."""

    scans: int
    duration_s: float
    wall_s: float
    first_fix_scan: int | None
    first_fix_s: float | None
    first_fix_m: float | None
    verified_share: float | None
    good_share: float | None
    median_error_m: float | None
    p99_error_m: float | None
    median_yaw_deg: float | None
    p99_yaw_deg: float | None
    median_map_error_m: float | None
    p99_map_error_m: float | None
    wrong: int | None
    relocalisations: int
    lost: int
    resets: int
    off_map: int | None
    off_map_verified: int | None
    to_lost: tuple[tuple[int, float, float], ...] = ()
    back_to_fix: tuple[tuple[int, float, float | None], ...] = ()
    jumps: tuple[tuple[int | None, float | None, int | None, float | None], ...] = ()
    to_fix: tuple[tuple[int, float, float | None], ...] = ()

    @property
    def scans_per_s(self) -> float:
        return self.scans / self.wall_s if self.wall_s > 0 else math.inf

    @property
    def realtime(self) -> float:
        """The drive's duration over the replay's wall time (>1: faster than real time)."""
        return self.duration_s / self.wall_s if self.wall_s > 0 else math.inf

    def line(self) -> str:
        text = (
            f"follow: {self.scans} scans in {self.wall_s:.1f} s ({self.scans_per_s:.1f} scans/s, "
            f"{self.realtime:.2f}x real time)"
        )
        if self.first_fix_scan is None:
            text += "; no fix"
        else:
            where = f"{self.first_fix_m:.1f} m, " if self.first_fix_m is not None else ""
            text += f"; first fix at scan {self.first_fix_scan} ({where}{self.first_fix_s:.1f} s)"
            text += f"; {100 * (self.verified_share or 0):.1f} % of the scans after it verified"
        if self.median_error_m is not None:
            text += (
                f"; pose error median {self.median_error_m:.2f} m / {self.median_yaw_deg:.2f} "
                f"deg, p99 {self.p99_error_m:.2f} m / {self.p99_yaw_deg:.2f} deg"
            )
            if self.median_map_error_m is not None:
                text += (
                    f" (against the map's own truth {self.median_map_error_m:.2f} m, p99 "
                    f"{self.p99_map_error_m:.2f} m)"
                )
            text += (
                f"; {100 * (self.good_share or 0):.1f} % within {GOOD_M:g} m and {GOOD_DEG:g} "
                f"deg; {self.wrong} verified poses more than {WRONG_POSE_M:g} m off"
            )
        text += f"; {self.relocalisations} relocalisations, lost {self.lost} times"
        if self.resets:
            text += f", {self.resets} resets"
        if self.off_map:
            text += f"; {self.off_map} scans off the map, {self.off_map_verified} verified there"
        if self.to_lost:
            parts = [f"{n:+d} scans ({s:+.1f} s, {m:.0f} m off)" for n, s, m in self.to_lost]
            text += "; lost " + ", ".join(parts) + " from leaving the map"
        if self.back_to_fix:
            parts = [
                f"{n} scans ({s:.1f} s" + (f", {m:.0f} m)" if m is not None else ")")
                for n, s, m in self.back_to_fix
            ]
            text += "; a fix " + ", ".join(parts) + " after coming back"
        for lost_n, lost_s, fix_n, fix_s in self.jumps:
            text += "; the truth jumped: "
            text += "never lost" if lost_n is None else f"lost {lost_n} scans ({lost_s:.1f} s)"
            text += " after it, " + (
                "no fix since" if fix_n is None else f"a fix {fix_n} scans ({fix_s:.1f} s) after it"
            )
        if self.to_fix:
            parts = [
                f"{n} scans ({s:.1f} s" + (f", {m:.0f} m)" if m is not None else ")")
                for n, s, m in self.to_fix
            ]
            text += "; relocalised after " + ", ".join(parts)
        return text


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def summarise_follow(
    rows: Sequence[FollowRow], wall_s: float, off_map_m: float = OFF_MAP_M
) -> FollowSummary:
    """The :class:`FollowSummary` of ``rows`` followed in ``wall_s`` seconds."""
    if not rows:
        raise InputError("no rows to summarise", "rows")
    first = next((k for k, r in enumerate(rows) if r.verified), None)
    after = rows[first:] if first is not None else []
    has_truth = any(r.true_northing is not None for r in rows)
    ver = [r for r in after if r.verified]
    err = [r.pose_error_m for r in ver if r.pose_error_m is not None]
    yaw = [r.pose_yaw_error_deg for r in ver if r.pose_yaw_error_deg is not None]
    merr = [r.map_error_m for r in ver if r.map_error_m is not None]
    good = [
        r
        for r in ver
        if r.pose_error_m is not None
        and r.pose_error_m <= GOOD_M
        and (r.pose_yaw_error_deg or 0.0) <= GOOD_DEG
    ]
    off = [r for r in rows if r.off_map_m is not None and r.off_map_m > off_map_m]
    has_map = any(r.off_map_m is not None for r in rows)
    return FollowSummary(
        scans=len(rows),
        duration_s=rows[-1].time_s - rows[0].time_s,
        wall_s=wall_s,
        first_fix_scan=None if first is None else rows[first].scan,
        first_fix_s=None if first is None else rows[first].time_s,
        first_fix_m=None if first is None else rows[first].driven_m,
        verified_share=len(ver) / len(after) if after else None,
        good_share=len(good) / len(after) if after and has_truth else None,
        median_error_m=_pct(err, 50),
        p99_error_m=_pct(err, 99),
        median_yaw_deg=_pct(yaw, 50),
        p99_yaw_deg=_pct(yaw, 99),
        median_map_error_m=_pct(merr, 50),
        p99_map_error_m=_pct(merr, 99),
        wrong=sum(e > WRONG_POSE_M for e in err) if has_truth else None,
        relocalisations=sum(r.event == "relocalised" for r in rows),
        lost=sum(r.event == "lost" for r in rows),
        resets=sum(r.event == "reset" for r in rows),
        off_map=len(off) if has_map else None,
        off_map_verified=sum(r.verified for r in off) if has_map else None,
        to_lost=_to_lost(rows, off_map_m),
        back_to_fix=_back_to_fix(rows, off_map_m),
        jumps=_jumps(rows),
        to_fix=_to_fix(rows),
    )


def _stretches(rows: Sequence[FollowRow], off_map_m: float) -> list[tuple[int, int]]:
    """(first, last) row of each run of rows whose truth is more than ``off_map_m`` from the
    map."""
    out, start = [], None
    for k, r in enumerate(rows):
        off = r.off_map_m is not None and r.off_map_m > off_map_m
        if off and start is None:
            start = k
        elif not off and start is not None:
            out.append((start, k - 1))
            start = None
    if start is not None:
        out.append((start, len(rows) - 1))
    return out


def _to_lost(rows: Sequence[FollowRow], off_map_m: float) -> tuple[tuple[int, float, float], ...]:
    """Per stretch off the map: (scans, seconds, the truth's distance from the map) from the
    stretch's first scan to the ``lost`` that ended the tracking that went into it (before the
    stretch, with no fix since, or in it)."""
    out = []
    for first, last in _stretches(rows, off_map_m):
        before = [k for k in range(first) if rows[k].event == "lost"]
        if before and all(r.how != "fix" for r in rows[before[-1] : first]):
            lost: int | None = before[-1]  # said lost before the truth was that far off
        else:
            lost = next((j for j in range(first, last + 1) if rows[j].event == "lost"), None)
        if lost is None:
            continue
        r = rows[lost]
        out.append((lost - first, r.time_s - rows[first].time_s, r.off_map_m or 0.0))
    return tuple(out)


def _back_to_fix(
    rows: Sequence[FollowRow], off_map_m: float
) -> tuple[tuple[int, float, float | None], ...]:
    """Per stretch off the map the drive came back from: (scans, seconds, metres) from its
    first scan back on the map to the next fix."""
    out = []
    for _, last in _stretches(rows, off_map_m):
        back = last + 1
        if back >= len(rows):
            continue
        nxt = next((j for j in range(back, len(rows)) if rows[j].how == "fix"), None)
        if nxt is None:
            continue
        metres = None
        if rows[nxt].driven_m is not None and rows[back].driven_m is not None:
            metres = rows[nxt].driven_m - rows[back].driven_m
        out.append((nxt - back, rows[nxt].time_s - rows[back].time_s, metres))
    return tuple(out)


def _jumps(
    rows: Sequence[FollowRow],
) -> tuple[tuple[int | None, float | None, int | None, float | None], ...]:
    """Per jump of the truth between two rows: (scans, seconds) from the row after it to the
    first lost or reset, and to the first fix after that."""
    out = []
    for k in range(1, len(rows)):
        a, b = rows[k - 1], rows[k]
        if None in (a.true_northing, a.true_easting, b.true_northing, b.true_easting):
            continue
        step = math.hypot(b.true_northing - a.true_northing, b.true_easting - a.true_easting)
        if step <= JUMP_M:
            continue
        lost = next((j for j in range(k, len(rows)) if rows[j].event in ("lost", "reset")), None)
        fix = None
        if lost is not None:
            fix = next((j for j in range(lost, len(rows)) if rows[j].how == "fix"), None)
        out.append((
            None if lost is None else lost - k,
            None if lost is None else rows[lost].time_s - b.time_s,
            None if fix is None else fix - k,
            None if fix is None else rows[fix].time_s - b.time_s,
        ))  # fmt: skip
    return tuple(out)


def _to_fix(rows: Sequence[FollowRow]) -> tuple[tuple[int, float, float | None], ...]:
    """For each time the localiser lost its track (lost, or a reset while it had one): the
    scans, seconds and metres to the next fix."""
    out = []
    for k, r in enumerate(rows):
        if r.event not in ("lost", "reset") or (r.event == "reset" and r.how == "fix"):
            continue
        nxt = next((j for j in range(k + 1, len(rows)) if rows[j].how == "fix"), None)
        if nxt is None:
            continue
        metres = None
        if rows[nxt].driven_m is not None and r.driven_m is not None:
            metres = rows[nxt].driven_m - r.driven_m
        out.append((nxt - k, rows[nxt].time_s - r.time_s, metres))
    return tuple(out)


def plot_follow(
    rows: Sequence[FollowRow],
    path: str | Path,
    *,
    map_ne: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """The followed drive as a PNG: the map's entries in grey, the truth as a black line, the
    poses coloured by state (verified tracking green, a fix blue, predicted orange, the scans
    that searched red on the truth); with the truth, a second panel of the errors along the
    drive."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise MissingDependencyError("matplotlib", "plot", "The follow figure") from None
    has_truth = any(r.true_northing is not None for r in rows)
    fig, axes = plt.subplots(1, 2 if has_truth else 1, figsize=(14 if has_truth else 7, 6),
                             squeeze=False)  # fmt: skip
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
    style_track_axes(ax, title or "follow")
    if has_truth:
        ax2 = axes[0, 1]
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
            c = states.get(r.state)
            if c is not None:
                ax2.axvline(r.time_s, c=c, lw=0.4, alpha=0.25)
        ax2.axhline(GOOD_M, c="0.4", ls="--", lw=0.8, label=f"{GOOD_M:g} m")
        ax2.axhline(WRONG_POSE_M, c="tab:red", ls=":", lw=0.8, label=f"{WRONG_POSE_M:g} m")
        ax2.set_yscale("symlog", linthresh=0.1)
        ax2.set_ylim(bottom=0.0)
        ax2.set_xlabel("time in the drive (s); red bands: searching, black: lost")
        ax2.set_ylabel("pose error (m)")
        ax2.legend(loc="best", fontsize=8)
    return save_track_figure(fig, plt, path)


def stage_means(rows: Sequence[FollowRow]) -> dict[str, dict[str, float]]:
    """Mean milliseconds of each stage, by the state the scan was asked in (``searching``:
    retrieval and verification; ``tracking``: a registration near the prediction): the client's
    ``read``, ``odometry`` and ``step`` (the request included) and the server's stages."""
    out: dict[str, dict[str, float]] = {}
    for mode in ("search", "prior"):
        sel = [r for r in rows if r.stages_ms and r.asked == mode]
        if not sel:
            continue
        keys = ["read_ms", "odometry_ms", "step_ms"]
        means = {k.removesuffix("_ms"): float(np.mean([getattr(r, k) for r in sel])) for k in keys}
        for stage in sel[0].stages_ms:
            means[f"server {stage}"] = float(np.mean([r.stages_ms.get(stage, 0.0) for r in sel]))
        means["scans"] = float(len(sel))
        out[mode] = means
    return out
