"""Position fixes: a drive's GNSS positions without orientation (NavSatFix-like), read,
checked, laid beside the run and fitted to its LiDAR odometry.

A fleet that records only fixes (metres of noise, no heading, one a second or so) and the
LiDAR gets its run's poses from :class:`~.fix_odometry.FixOdometryDrive`: the scans'
odometry (KISS-ICP) laid onto the fixes by :func:`fit_to_fixes`. The fixes are kept beside
the run in ``fixes.csv`` (:func:`write_run_fixes`), each with the position the odometry laid
at its time, so that ``pnvlad map align`` takes them as the run's priors and the odometry as
its steps (:mod:`pnvlad_service.mapping.fixes`). The file's presence is what marks a run as
fix-only.

``fixes.csv`` columns: ``timestamp`` (µs), ``easting``, ``northing``, ``height`` (UTM metres,
the fix), ``std_m`` (its horizontal standard deviation, empty where the receiver gave none),
``laid_easting``, ``laid_northing``, ``laid_height`` (where the run's poses put the sensor at
that time).

A fixes CSV (:func:`read_fixes_csv`, for a drive built in Python) has a header with
``timestamp`` (µs) and either ``easting``, ``northing`` (UTM metres) or ``latitude``,
``longitude`` (WGS 84 degrees, turned into UTM in the zone given), optionally ``height`` /
``altitude`` (metres) and ``std_m``.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text, read_csv_text

FIXES_CSV = "fixes.csv"
COLUMNS = (
    "timestamp",
    "easting",
    "northing",
    "height",
    "std_m",
    "laid_easting",
    "laid_northing",
    "laid_height",
)
#: Two consecutive fixes whose error against the odometry changes by more than this (metres,
#: horizontal), and by more than four standard deviations of that change, jump.
JUMP_M = 5.0


@dataclass(frozen=True)
class Fixes:
    """Position fixes: ``stamps`` int64 [F] µs, strictly increasing; ``enu`` float64 [F, 3]
    UTM easting, northing, height (metres); ``std_m`` float64 [F] each fix's horizontal
    standard deviation (NaN: not given)."""

    stamps: np.ndarray
    enu: np.ndarray
    std_m: np.ndarray

    def __len__(self) -> int:
        return len(self.stamps)

    def checked(self, source: str | Path) -> Fixes:
        """These fixes, or ``InputError`` naming ``source``: fewer than 3, stamps that do not
        increase, positions that are not finite."""
        if len(self) < 3:
            raise InputError(f"{len(self)} position fixes: at least 3 are needed", source)
        if np.any(np.diff(self.stamps) <= 0):
            k = int(np.flatnonzero(np.diff(self.stamps) <= 0)[0]) + 1
            raise InputError(f"fix timestamps must increase (fix {k}: {self.stamps[k]})", source)
        if not np.isfinite(self.enu).all():
            raise InputError("a fix's position is not finite", source)
        return self

    def within(self, start: int, stop: int) -> Fixes:
        """The fixes stamped from ``start`` to ``stop`` (µs), both included."""
        keep = (self.stamps >= start) & (self.stamps <= stop)
        return Fixes(self.stamps[keep], self.enu[keep], self.std_m[keep])


def _float_column(rows: list[dict[str, str]], name: str, path: Path) -> np.ndarray:
    try:
        return np.array([float(r[name]) if r[name] != "" else math.nan for r in rows])
    except ValueError:
        raise InputError(f"column {name!r} holds a value that is not a number", path) from None


def read_fixes_csv(path: str | Path, utm_zone: str = "") -> Fixes:
    """The fixes of a CSV (module doc); latitude and longitude need ``utm_zone``.
    ``InputError`` naming the file for a missing column or a bad value."""
    path = Path(path)
    rows = list(csv.DictReader(io.StringIO(read_csv_text(path, "fixes CSV"))))
    names = set(rows[0]) if rows else set()
    if "timestamp" not in names:
        raise InputError("a fixes CSV needs a timestamp column (µs)", path)
    try:
        stamps = np.array([int(r["timestamp"]) for r in rows], dtype=np.int64)
    except ValueError:
        raise InputError("column 'timestamp' must hold integer microseconds", path) from None
    height_name = "height" if "height" in names else "altitude" if "altitude" in names else None
    height = _float_column(rows, height_name, path) if height_name else np.zeros(len(rows))
    if {"easting", "northing"} <= names:
        east, north = _float_column(rows, "easting", path), _float_column(rows, "northing", path)
    elif {"latitude", "longitude"} <= names:
        if not utm_zone:
            raise InputError("fixes in latitude/longitude need --utm-zone", "--utm-zone")
        from pnvlad_service.io.utm import from_latlon

        east, north = from_latlon(
            utm_zone, _float_column(rows, "latitude", path), _float_column(rows, "longitude", path)
        )
    else:
        raise InputError("a fixes CSV needs easting,northing or latitude,longitude", path)
    std = _float_column(rows, "std_m", path) if "std_m" in names else np.full(len(rows), np.nan)
    fixes = Fixes(stamps, np.stack([east, north, height], axis=1), std)
    return fixes.checked(path)


def write_run_fixes(run_dir: str | Path, fixes: Fixes, laid: np.ndarray) -> Path:
    """``run_dir/fixes.csv``: the fixes and ``laid`` float64 [F, 3], where the run's poses put
    the sensor at each fix's time; written atomically."""
    buf = io.StringIO()
    out = csv.writer(buf, lineterminator="\n")
    out.writerow(COLUMNS)
    for t, f, s, p in zip(fixes.stamps, fixes.enu, fixes.std_m, laid, strict=True):
        std = "" if not math.isfinite(s) else repr(float(s))
        out.writerow([int(t), *(repr(float(v)) for v in f), std, *(repr(float(v)) for v in p)])
    path = Path(run_dir) / FIXES_CSV
    atomic_write_text(path, buf.getvalue())
    return path


def read_run_fixes(run_dir: str | Path) -> tuple[Fixes, np.ndarray] | None:
    """A run's ``fixes.csv`` as (fixes, laid float64 [F, 3]), or ``None`` when the run has
    none (its poses are a GNSS/INS recording). ``InputError`` naming the file when damaged."""
    path = Path(run_dir) / FIXES_CSV
    if not path.is_file():
        return None
    rows = list(csv.DictReader(io.StringIO(read_csv_text(path, "fixes CSV"))))
    if not rows or set(COLUMNS) - set(rows[0]):
        raise InputError(f"needs the columns {', '.join(COLUMNS)}", path)
    try:
        stamps = np.array([int(r["timestamp"]) for r in rows], dtype=np.int64)
    except ValueError:
        raise InputError("column 'timestamp' must hold integer microseconds", path) from None
    cols = {c: _float_column(rows, c, path) for c in COLUMNS[1:]}
    enu = np.stack([cols["easting"], cols["northing"], cols["height"]], axis=1)
    laid = np.stack([cols["laid_easting"], cols["laid_northing"], cols["laid_height"]], axis=1)
    if not np.isfinite(laid).all():
        raise InputError("a laid position is not finite", path)
    return Fixes(stamps, enu, cols["std_m"]).checked(path), laid


def check_jumps(
    fixes: Fixes, laid: np.ndarray, source: str | Path, default_std_m: float = 1.5
) -> None:
    """``InputError`` naming ``source`` (the run) when two consecutive fixes' errors against
    the laid odometry ``laid`` [F, 3] differ by more than :data:`JUMP_M` metres horizontally
    and by more than four standard deviations of the difference (the fixes' ``std_m``, else
    ``default_std_m``): a fix that jumps, which neither the odometry nor the walk of a
    receiver's error explains."""
    resid = fixes.enu[:, :2] - laid[:, :2]
    change = np.linalg.norm(np.diff(resid, axis=0), axis=1)
    std = np.where(np.isfinite(fixes.std_m), fixes.std_m, default_std_m)
    limit = np.maximum(JUMP_M, 4.0 * np.hypot(std[:-1], std[1:]))
    bad = np.flatnonzero(change > limit)
    if len(bad):
        k = int(bad[0])
        raise InputError(
            f"the position fixes jump {change[k]:.1f} m against the odometry between "
            f"{int(fixes.stamps[k])} and {int(fixes.stamps[k + 1])} (more than "
            f"{limit[k]:.1f} m; {len(bad)} such jumps): drop the bad fixes or the run",
            source,
        )


def linear_at(stamps: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """float64 [F, K]: ``values`` [T, K] at ``stamps`` [T], linear in time at ``t`` [F] (the
    first or last row's outside them)."""
    s = np.asarray(stamps).astype(np.float64)
    at = np.asarray(t).astype(np.float64)
    return np.stack([np.interp(at, s, values[:, k]) for k in range(values.shape[1])], axis=1)


def fix_residuals_at(fixes: Fixes, laid: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """float64 [N, 3]: the fixes' error against the laid odometry (fix minus laid), linear in
    time at ``stamps`` int [N] (the first or last fix's outside them)."""
    return linear_at(fixes.stamps, fixes.enu - laid, stamps)
