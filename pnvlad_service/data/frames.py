"""The frame sidecar: where each submap's normalised points sit in metres, and (for the
simulator) where that frame truly is.

A benchmark ``.bin`` holds the filter G's output: 4096 points centred, scaled to a mean
distance of 0.5 and clipped to [-1, 1]. That is what the network wants, and all that the
published layout keeps. Geometric verification needs the points back in metres, so
``pnvlad data prepare`` and ``pnvlad synth`` write, beside each locations CSV, a sidecar
``<csv stem>.frames.csv`` with one row per submap (same timestamps, same order):

``timestamp``
    the submap's timestamp, as in the locations CSV.
``origin_easting, origin_northing, origin_height``
    UTM metres of the local frame's origin (the submap's centre scan position, snapped to the
    millimetre grid the accumulation used).
``centre_x, centre_y, centre_z, scale``
    what G did: ``local = centre + scale * bin`` in metres (``scale`` is metres per
    normalised unit, negative where G negated the cloud).
``frame``
    the axes of the local frame: ``enu`` (x east, y north, z up; the accumulated submaps).
``true_easting, true_northing, true_height, true_yaw_deg`` (optional, ``pnvlad synth``)
    the simulator's true pose of that local frame in UTM, before the simulated GNSS/INS
    error: a local point ``p`` truly lies at ``R(true_yaw) p + true_position``. Empty when
    unknown.
``heading_deg, speed_mps, yaw_rate_dps`` (optional: keyframes)
    the vehicle's motion at the scan as the recording's poses give it
    (:func:`~.motion.drive_motion`): the sensor's forward axis in the local frame's axes
    (degrees anticlockwise from east), its forward speed and its yaw rate (degrees a second,
    anticlockwise positive). ``pnvlad map align --sweep-hz`` de-skews the scan by it. Empty
    when unknown.

Tools that read the published layout ignore the file; ``pnvlad data check`` validates it.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text, read_csv_text

FRAMES_SUFFIX = ".frames.csv"
FRAME_KINDS = ("enu",)
_BASE = (
    "timestamp",
    "origin_easting",
    "origin_northing",
    "origin_height",
    "centre_x",
    "centre_y",
    "centre_z",
    "scale",
    "frame",
)
_TRUE = ("true_easting", "true_northing", "true_height", "true_yaw_deg")
_MOTION = ("heading_deg", "speed_mps", "yaw_rate_dps")
COLUMNS = _BASE + _TRUE + _MOTION


@dataclass(frozen=True)
class SubmapFrame:
    """One sidecar row (see the module docstring). Vectors are float64 [3]."""

    timestamp: int
    origin: np.ndarray
    centre: np.ndarray
    scale: float
    frame: str = "enu"
    true_position: np.ndarray | None = None
    true_yaw_deg: float | None = None
    motion: np.ndarray | None = None

    def local_m(self, normalised: np.ndarray) -> np.ndarray:
        """The submap's points in metres in its local frame: float64 [N, 3]."""
        return self.centre + self.scale * np.asarray(normalised, dtype=np.float64)

    @property
    def true_pose(self) -> np.ndarray | None:
        """float64 [4, 4]: local frame -> true UTM (easting, northing, height), or ``None``."""
        if self.true_position is None or self.true_yaw_deg is None:
            return None
        return pose_matrix(self.true_position, self.true_yaw_deg)

    @property
    def sweep_motion(self) -> np.ndarray | None:
        """float64 [3]: the recorded heading (radians), speed (m/s) and yaw rate (rad/s) as
        :mod:`pnvlad_service.mapping.deskew` takes them, or ``None``."""
        if self.motion is None:
            return None
        h, v, w = (float(x) for x in self.motion)
        return np.array([math.radians(h), v, math.radians(w)])

    @property
    def map_pose(self) -> np.ndarray:
        """float64 [4, 4]: local frame -> UTM as the map records it (axes UTM, at ``origin``)."""
        out = np.eye(4)
        out[:3, 3] = self.origin
        return out


def pose_matrix(position: np.ndarray, yaw_deg: float) -> np.ndarray:
    """float64 [4, 4]: rotation about z (up) by ``yaw_deg``, then ``position``."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:3, 3] = position
    return out


def frames_path(locations_csv: str | Path) -> Path:
    """The sidecar beside a locations CSV: ``<stem>.frames.csv``."""
    p = Path(locations_csv)
    return p.with_name(p.stem + FRAMES_SUFFIX)


def _fmt(x: float) -> str:
    return repr(float(x))


def write_frames_csv(path: str | Path, frames: list[SubmapFrame]) -> None:
    """Write a sidecar atomically; floats with ``repr``, so a round trip is exact."""
    lines = [",".join(COLUMNS)]
    for k, f in enumerate(frames):
        nums = [*f.origin, *f.centre, f.scale]
        has_true = f.true_position is not None and f.true_yaw_deg is not None
        if has_true:
            nums += [*f.true_position, f.true_yaw_deg]
        if f.motion is not None:
            nums += [*f.motion]
        if not all(math.isfinite(float(v)) for v in nums):
            raise InputError(f"row {k}: non-finite value in the frame record", source=path)
        row = [str(int(f.timestamp)), *map(_fmt, [*f.origin, *f.centre, f.scale]), f.frame]
        if has_true:
            row += [*map(_fmt, f.true_position), _fmt(f.true_yaw_deg)]
        else:
            row += [""] * len(_TRUE)
        row += [""] * len(_MOTION) if f.motion is None else [*map(_fmt, f.motion)]
        lines.append(",".join(row))
    atomic_write_text(path, "\n".join(lines) + "\n")


def _floats(row: dict[str, str], names: tuple[str, ...], where: str, path: Path) -> list[float]:
    out = []
    for name in names:
        try:
            v = float(row[name])
        except (TypeError, ValueError):
            raise InputError(f"{where}: {name} {row.get(name)!r} is not a number", path) from None
        if not math.isfinite(v):
            raise InputError(f"{where}: {name} is not finite", path)
        out.append(v)
    return out


def _all_or_none(
    row: dict[str, str], names: tuple[str, ...], what: str, where: str, path: Path
) -> list[float] | None:
    """The optional columns ``names`` of ``row``: their numbers, or ``None`` when all are
    empty; ``InputError`` naming ``what`` when only some are given."""
    given = [bool((row.get(n) or "").strip()) for n in names]
    if not any(given):
        return None
    if not all(given):
        raise InputError(f"{where}: {what} needs all of {', '.join(names)}", path)
    return _floats(row, names, where, path)


def _row(row: dict[str, str], line: int, path: Path) -> SubmapFrame:
    where = f"line {line}"
    try:
        ts = int(row["timestamp"])
    except (TypeError, ValueError):
        bad = row.get("timestamp")
        raise InputError(f"{where}: timestamp {bad!r} is not an integer", path) from None
    v = _floats(row, _BASE[1:8], where, path)
    if v[6] == 0.0:
        raise InputError(f"{where}: scale is 0", path)
    frame = (row.get("frame") or "").strip()
    if frame not in FRAME_KINDS:
        raise InputError(f"{where}: frame {frame!r} is not one of {list(FRAME_KINDS)}", path)
    t = _all_or_none(row, _TRUE, "the true pose", where, path)
    true_pos, true_yaw = (None, None) if t is None else (np.array(t[:3]), t[3])
    m = _all_or_none(row, _MOTION, "the motion", where, path)
    motion = None if m is None else np.array(m)
    return SubmapFrame(
        ts, np.array(v[:3]), np.array(v[3:6]), v[6], frame, true_pos, true_yaw, motion
    )


def read_frames_csv(path: str | Path) -> list[SubmapFrame]:
    """Read a sidecar, in file order. ``InputError`` naming the file and line for a missing
    column, a bad number, a zero scale, an unknown frame or a half-given true pose."""
    path = Path(path)
    reader = csv.DictReader(read_csv_text(path, "frame sidecar").splitlines())
    missing = [c for c in _BASE if c not in (reader.fieldnames or [])]
    if missing:
        raise InputError(f"missing column(s) {', '.join(missing)}", source=path)
    return [_row(row, k + 2, path) for k, row in enumerate(reader)]


def check_frames(path: str | Path, timestamps: list[int]) -> list[SubmapFrame]:
    """Read a sidecar and check it lists exactly ``timestamps`` (the locations CSV's), in
    order. ``InputError`` naming the first disagreement."""
    frames = read_frames_csv(path)
    if len(frames) != len(timestamps):
        raise InputError(
            f"{len(frames)} rows where the locations CSV has {len(timestamps)} submaps", path
        )
    for k, (f, t) in enumerate(zip(frames, timestamps, strict=True)):
        if f.timestamp != t:
            raise InputError(
                f"line {k + 2}: timestamp {f.timestamp} where the locations CSV has {t}", path
            )
    return frames


# --- the journal: rows one JSON line each, as a prepare run writes them (resumable) --------


def journal_line(f: SubmapFrame) -> str:
    """One row as a JSON line (floats as JSON writes them: a round trip is exact)."""
    true = None if f.true_position is None else [*map(float, f.true_position), f.true_yaw_deg]
    row = {"t": f.timestamp, "o": [*map(float, f.origin)], "c": [*map(float, f.centre)]}
    row = {**row, "s": f.scale, "f": f.frame, "true": true}
    if f.motion is not None:
        row["m"] = [*map(float, f.motion)]
    return json.dumps(row) + "\n"


def read_journal(path: str | Path) -> list[SubmapFrame]:
    """The rows of a journal, up to the first line a crash cut short."""
    rows = []
    for line in Path(path).read_text(encoding="utf-8").splitlines():
        try:
            d = json.loads(line)
            true = d["true"]
            rows.append(
                SubmapFrame(
                    int(d["t"]),
                    np.array(d["o"], dtype=np.float64),
                    np.array(d["c"], dtype=np.float64),
                    float(d["s"]),
                    str(d["f"]),
                    None if true is None else np.array(true[:3], dtype=np.float64),
                    None if true is None else float(true[3]),
                    None if d.get("m") is None else np.array(d["m"], dtype=np.float64),
                )
            )
        except (ValueError, KeyError, TypeError, IndexError):
            break  # a line cut short by a crash: what follows it was not recorded
    return rows
