"""Missing returns written as points, counted for a drive's report: the points at the sensor's
origin that :func:`~pnvlad_service.io.readers.drop_no_returns` takes out of each scan (an
Ouster driver's beams that saw nothing)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)


@dataclass
class NoReturnCount:
    """``points`` dropped so far from ``scans`` scans of one drive (they grow as its scans are
    read)."""

    points: int = 0
    scans: int = 0

    def add(self, dropped: int, where: str | Path) -> None:
        """Count ``dropped`` points of one scan (``where``: the scan, named once in the log)."""
        if not dropped:
            return
        if not self.scans:
            log.info(
                "%s: %d points at the sensor's origin dropped (missing returns written as "
                "points); the drive's later ones are counted in its report",
                where,
                dropped,
            )
        self.points += dropped
        self.scans += 1

    def line(self) -> str | None:
        """'N missing returns (points at the sensor's origin) dropped from M scans', or
        ``None`` when there were none."""
        if not self.points:
            return None
        return (
            f"{self.points:,} missing returns (points at the sensor's origin) dropped from "
            f"{self.scans} scans"
        )
