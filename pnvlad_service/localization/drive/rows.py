"""One row a scan of a drive, whichever policy ran it (:class:`DriveRow`), and its CSV.

A drive is asked about scan by scan (``per-scan``: each scan alone, a search) or followed
(``tracked``: the :class:`~.tracking.DriveLocalizer`). Both make :class:`DriveRow`; each
policy's CSV has the columns that policy fills (:data:`COLUMNS`), in a fixed order: a
per-scan CSV the top-1 match and the answer's verification, a tracked one the localiser's
state, the registration and the stages' times. :func:`write_rows` writes them atomically,
:func:`read_rows` reads them back (to summarise a drive again).
"""

from __future__ import annotations

import csv
import dataclasses
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_rows
from pnvlad_service.localization.outputs.step import COVARIANCE_COLUMNS

#: How a drive is asked: each scan alone (a search), or followed by the tracker.
Policy = Literal["per-scan", "tracked"]
PER_SCAN: Policy = "per-scan"
TRACKED: Policy = "tracked"
POLICIES: tuple[Policy, ...] = (PER_SCAN, TRACKED)


@dataclass
class DriveRow:
    """One scan of a drive (``None`` where unknown or not that policy's).

    Both policies: ``scan``, ``timestamp`` (µs), ``time_s`` since the first scan,
    ``verified`` (the answer's verdict; per-scan: ``None`` when the service does not verify or
    gave no match), ``confidence``, the pose (``pose_northing``, ``pose_easting``,
    ``pose_yaw_deg``; UTM metres, degrees counter-clockwise from east), the truth
    (``true_*``) and the pose's errors (``pose_error_m``, ``pose_yaw_error_deg``).

    Per-scan: ``status`` (``ok``, ``no match`` or ``refused: ...``), the top-1 match
    (``submap``, ``run``, ``kind``, ``northing``, ``easting``, ``distance``) and its error
    ``error_m``.

    Tracked: the localiser's ``state``, ``how`` and ``event``; ``fitness``, ``sigma_m`` and
    ``correction_m`` (how far the registration moved the prediction) when tracking; the
    ``anchor`` entry; the errors against the map's own truth (``map_error_m``,
    ``map_yaw_error_deg``), the truth's distance to the nearest map entry (``off_map_m``), the
    distance driven (``driven_m``); the stages' times (ms): reading the scan, odometry, the
    step (the request included), what the service was ``asked`` (``search``, or ``prior``: a
    registration near the prediction) and its ``server_ms`` total; ``reason``;
    ``stages_ms``: the service's stages (not a column).

    Both policies, after the columns above: the pose's ``pose_height`` (metres, UTM up),
    ``pose_roll_deg`` and ``pose_pitch_deg`` (ROS's fixed axes, docs/TRACKING.md) and its
    ``covariance`` (the 21 values on and above the diagonal of the [6, 6], columns
    ``cov_x_x`` ... ``cov_yaw_yaw``: a registered pose's point-to-plane covariance; empty for
    a pose found by search or carried on by the odometry)."""

    scan: int
    timestamp: int
    time_s: float
    status: str = "ok"
    state: str | None = None
    verified: bool | None = None
    how: str | None = None
    event: str | None = None
    submap: int | None = None
    run: str | None = None
    kind: str | None = None
    northing: float | None = None
    easting: float | None = None
    distance: float | None = None
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
    error_m: float | None = None
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
    pose_height: float | None = None
    pose_roll_deg: float | None = None
    pose_pitch_deg: float | None = None
    covariance: tuple[float, ...] | None = field(default=None, repr=False)
    stages_ms: dict[str, float] = field(default_factory=dict, repr=False)

    def __getattr__(self, name: str) -> float | None:
        # The covariance's columns (cov_x_x, ...) read from ``covariance``.
        if name.startswith("cov_") and name in _COV_INDEX:
            cov = self.covariance
            return None if cov is None else cov[_COV_INDEX[name]]
        raise AttributeError(name)

    @property
    def answered(self) -> bool:
        """Whether the service named a place (a top-1 match)."""
        return self.northing is not None


#: Each policy's CSV columns, in order.
COLUMNS: dict[Policy, tuple[str, ...]] = {
    PER_SCAN: (
        "scan", "timestamp", "time_s", "status", "submap", "run", "kind", "northing", "easting",
        "distance", "verified", "confidence", "pose_northing", "pose_easting", "pose_yaw_deg",
        "true_northing", "true_easting", "true_yaw_deg", "error_m", "pose_error_m",
        "pose_yaw_error_deg",
    ),
    TRACKED: (
        "scan", "timestamp", "time_s", "state", "verified", "how", "event", "pose_northing",
        "pose_easting", "pose_yaw_deg", "fitness", "sigma_m", "correction_m", "confidence",
        "anchor", "true_northing", "true_easting", "true_yaw_deg", "pose_error_m",
        "pose_yaw_error_deg", "map_error_m", "map_yaw_error_deg", "off_map_m", "driven_m",
        "read_ms", "odometry_ms", "step_ms", "asked", "server_ms", "reason",
    ),
}  # fmt: skip
#: The columns both policies' CSVs end with: the pose's height, roll, pitch and covariance.
POSE_COLUMNS = ("pose_height", "pose_roll_deg", "pose_pitch_deg", *COVARIANCE_COLUMNS)
for _policy in POLICIES:
    COLUMNS[_policy] = (*COLUMNS[_policy], *POSE_COLUMNS)
_COV_INDEX = {name: k for k, name in enumerate(COVARIANCE_COLUMNS)}
#: Decimal places of a float cell (``None``: all a float's repr has).
DIGITS: dict[Policy, int | None] = {PER_SCAN: None, TRACKED: 6}


def write_rows(rows: Sequence[DriveRow], path: str | Path, policy: Policy) -> Path:
    """The rows as a CSV (atomically): ``policy``'s :data:`COLUMNS`, a row a scan (the
    covariance's cells with 9 significant digits: its values are far below a column's
    decimals)."""
    return atomic_write_rows([_Cells(r) for r in rows], COLUMNS[policy], path,
                             digits=DIGITS[policy])  # fmt: skip


class _Cells:
    """A row as its CSV cells: the covariance's written in significant digits."""

    def __init__(self, row: DriveRow) -> None:
        self.row = row

    def __getattr__(self, name: str) -> Any:
        value = getattr(self.row, name)
        if name in _COV_INDEX and value is not None:
            return f"{value:.9g}"
        return value


def read_rows(path: str | Path) -> list[DriveRow]:
    """The rows of a CSV :func:`write_rows` wrote (either policy's columns); InputError naming
    the file when it is not one."""
    hints = typing.get_type_hints(DriveRow)
    names = {f.name: f for f in dataclasses.fields(DriveRow)}
    rows = []
    with open(path, newline="", encoding="utf-8") as fh:
        for doc in csv.DictReader(fh):
            if "scan" not in doc or "timestamp" not in doc:
                raise InputError("not a drive's CSV (no scan and timestamp columns)", path)
            kw: dict[str, Any] = {}
            cov = [doc.get(c) or "" for c in COVARIANCE_COLUMNS]
            if all(cov):
                kw["covariance"] = tuple(float(v) for v in cov)
            for name, text in doc.items():
                f = names.get(name)
                if name == "covariance":
                    continue
                if f is None:
                    continue
                kind = str(hints[name])
                if text == "":
                    kw[name] = None if "None" in kind else f.default
                elif "bool" in kind:
                    kw[name] = text == "true"
                elif "int" in kind:
                    kw[name] = int(text)
                elif "float" in kind:
                    kw[name] = float(text)
                else:
                    kw[name] = text
            rows.append(DriveRow(**kw))
    return rows
