"""The report of a drive, either policy's: :class:`DriveSummary` (its figures and its summary
line) and the stages' mean times. The thresholds a pose is judged by are here
(docs/TRACKING.md).

A per-scan drive is judged by its answers (how many named a place, how far the top-1 match was
from the truth, how many were verified and how far their poses were); a tracked one by the
localiser's work (the first fix, the share verified after it, the errors, the losses, the
stretches off the map, the jumps of the truth, the speed). The pose errors of the verified
scans are the same figures in both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.rows import PER_SCAN, DriveRow, Policy

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
#: A per-scan answer whose top-1 match is farther than this from the truth is at a wrong place.
FAR_M = 25.0


@dataclass(frozen=True)
class DriveSummary:
    """The figures of a drive (``None`` where the truth, a verification or a fix is missing).

    Both policies: ``scans`` asked about; ``duration_s`` of the drive and ``wall_s`` of the
    run; ``verified``: scans with a verified answer (``None`` when the service does not
    verify); the verified poses' errors against the truth (median and p99, metres and
    degrees) and ``wrong``: those more than :data:`WRONG_POSE_M` off.

    Per-scan: ``answered`` (a top-1 match), ``within`` / ``beyond_m`` ``far_m`` of the truth
    and ``median_place_error_m``, the top-1 match's.

    Tracked: ``first_fix_*``: the scan, time (s) and distance driven (m) to the first verified
    pose; ``verified_share``: of the scans from the first fix on, those with a verified pose;
    ``good_share``: ... within :data:`GOOD_M` and :data:`GOOD_DEG` of the truth; the errors
    against the map's own truth; ``relocalisations``: fixes after the first; ``lost``: times
    the localiser said lost; ``resets``; ``off_map``: scans whose truth is more than
    ``off_map_m`` from the map, ``off_map_verified`` of them verified; ``to_lost``: per stretch
    off the map, (scans, seconds, metres from the map) from its first scan off the map to the
    last ``lost`` before the localiser next has a fix (negative: it said lost before the truth
    was that far off); ``back_to_fix``: per stretch off the map, (scans, seconds, metres
    driven) from the first scan back on the map to the next fix; ``jumps``: per jump of the
    truth (a kidnapped robot: :data:`JUMP_M` between two scans), (scans, seconds) from the
    first scan after it to the localiser's lost or reset, and to its next fix (``None`` when
    it never came); ``to_fix``: per loss of the track (lost or a reset), (scans, seconds,
    metres) to the next fix."""

    policy: Policy
    scans: int
    duration_s: float
    wall_s: float
    verified: int | None
    median_error_m: float | None
    p99_error_m: float | None
    median_yaw_deg: float | None
    p99_yaw_deg: float | None
    wrong: int | None
    answered: int
    within: int | None
    median_place_error_m: float | None
    beyond_m: int | None
    first_fix_scan: int | None
    first_fix_s: float | None
    first_fix_m: float | None
    verified_share: float | None
    good_share: float | None
    median_map_error_m: float | None
    p99_map_error_m: float | None
    relocalisations: int
    lost: int
    resets: int
    off_map: int | None
    off_map_verified: int | None
    to_lost: tuple[tuple[int, float, float], ...] = ()
    back_to_fix: tuple[tuple[int, float, float | None], ...] = ()
    jumps: tuple[tuple[int | None, float | None, int | None, float | None], ...] = ()
    to_fix: tuple[tuple[int, float, float | None], ...] = ()
    far_m: float = FAR_M

    @property
    def scans_per_s(self) -> float:
        return self.scans / self.wall_s if self.wall_s > 0 else math.inf

    @property
    def realtime(self) -> float:
        """The drive's duration over the run's wall time (>1: faster than real time)."""
        return self.duration_s / self.wall_s if self.wall_s > 0 else math.inf

    def line(self) -> str:
        """The summary line of the drive's policy."""
        return self._per_scan_line() if self.policy == PER_SCAN else self._tracked_line()

    def _per_scan_line(self) -> str:
        text = f"replay: {self.answered} of {self.scans} queries answered"
        if self.within is not None:
            text += f", {self.within} within {self.far_m:g} m"
        if self.verified is not None:
            text += f", {self.verified} verified"
        if self.median_place_error_m is not None:
            text += f"; median error {self.median_place_error_m:.1f} m, {self.beyond_m} beyond "
            text += f"{self.far_m:g} m"
        elif self.beyond_m is None:
            text += " (no poses in the bag: errors unknown)"
        if self.median_error_m is not None:
            text += (
                f"; verified poses {self.median_error_m:.2f} m / "
                f"{self.median_yaw_deg or 0.0:.2f} deg off (median), "
                f"{self.wrong} more than {WRONG_POSE_M:g} m off"
            )
        return text

    def _tracked_line(self) -> str:
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
        return text + self._losses()

    def _losses(self) -> str:
        text = f"; {self.relocalisations} relocalisations, lost {self.lost} times"
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


def summarise(
    rows: Sequence[DriveRow],
    policy: Policy,
    wall_s: float = 0.0,
    *,
    off_map_m: float = OFF_MAP_M,
    far_m: float = FAR_M,
) -> DriveSummary:
    """The :class:`DriveSummary` of ``rows`` asked by ``policy`` in ``wall_s`` seconds."""
    if not rows:
        raise InputError("no rows to summarise", "rows")
    has_truth = any(r.true_northing is not None for r in rows)
    ver = [r for r in rows if r.verified and r.pose_error_m is not None]
    err = [r.pose_error_m for r in ver if r.pose_error_m is not None]
    yaw = [r.pose_yaw_error_deg for r in ver if r.pose_yaw_error_deg is not None]
    flags = [r.verified for r in rows if r.verified is not None]
    answered = [r for r in rows if r.answered]
    places = [r.error_m for r in answered if r.error_m is not None]
    return DriveSummary(
        policy=policy,
        scans=len(rows),
        duration_s=rows[-1].time_s - rows[0].time_s,
        wall_s=wall_s,
        verified=sum(bool(f) for f in flags) if flags else None,
        median_error_m=_pct(err, 50),
        p99_error_m=_pct(err, 99),
        median_yaw_deg=_pct(yaw, 50),
        p99_yaw_deg=_pct(yaw, 99),
        wrong=sum(e > WRONG_POSE_M for e in err) if has_truth else None,
        answered=len(answered),
        within=sum(e <= far_m for e in places) if has_truth else None,
        median_place_error_m=_pct(places, 50),
        beyond_m=sum(e > far_m for e in places) if has_truth else None,
        far_m=far_m,
        **_tracked_figures(rows, has_truth, off_map_m),
    )


def _tracked_figures(rows: Sequence[DriveRow], has_truth: bool, off_map_m: float) -> dict:
    """The figures of the localiser's work: the first fix, the share verified after it, the
    losses and the stretches off the map."""
    first = next((k for k, r in enumerate(rows) if r.verified), None)
    after = rows[first:] if first is not None else []
    ver = [r for r in after if r.verified]
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
    return {
        "first_fix_scan": None if first is None else rows[first].scan,
        "first_fix_s": None if first is None else rows[first].time_s,
        "first_fix_m": None if first is None else rows[first].driven_m,
        "verified_share": len(ver) / len(after) if after else None,
        "good_share": len(good) / len(after) if after and has_truth else None,
        "median_map_error_m": _pct(merr, 50),
        "p99_map_error_m": _pct(merr, 99),
        "relocalisations": sum(r.event == "relocalised" for r in rows),
        "lost": sum(r.event == "lost" for r in rows),
        "resets": sum(r.event == "reset" for r in rows),
        "off_map": len(off) if has_map else None,
        "off_map_verified": sum(bool(r.verified) for r in off) if has_map else None,
        "to_lost": _to_lost(rows, off_map_m),
        "back_to_fix": _back_to_fix(rows, off_map_m),
        "jumps": _jumps(rows),
        "to_fix": _to_fix(rows),
    }


def _stretches(rows: Sequence[DriveRow], off_map_m: float) -> list[tuple[int, int]]:
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


def _to_lost(rows: Sequence[DriveRow], off_map_m: float) -> tuple[tuple[int, float, float], ...]:
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
    rows: Sequence[DriveRow], off_map_m: float
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
    rows: Sequence[DriveRow],
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


def _to_fix(rows: Sequence[DriveRow]) -> tuple[tuple[int, float, float | None], ...]:
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


def stage_means(rows: Sequence[DriveRow]) -> dict[str, dict[str, float]]:
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
