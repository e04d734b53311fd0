"""Where a run's map entries are, for the splits: their aligned positions where the run has
them, else the ones recorded when it was prepared.

A run aligned with the others of its map (multi-session alignment, ``pnvlad map align``)
holds its corrected trajectory beside the recorded one::

    <run>/poses_aligned.csv    timestamp (µs), northing, easting (UTM metres), any other
                               columns after or between them (heights, rotations) ignored

The recorded locations CSVs are never rewritten; :func:`run_locations` gives the entries of a
layout (submaps or keyframes, each named by the timestamp of its centre scan) at the aligned
positions, interpolated linearly in time between the two aligned poses around each entry
(exact where the file lists the entry's own timestamp). An entry outside the aligned
trajectory's time span is an :class:`InputError` naming the file: a partial alignment would
mix two frames in one set of tuples.
"""

from __future__ import annotations

import logging

import numpy as np

from pnvlad_service.data.tree import BenchmarkTree, Kind, Locations, read_locations_csv
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

#: The corrected trajectory of a run, beside its recorded files.
ALIGNED_POSES = "poses_aligned.csv"


def run_locations(tree: BenchmarkTree, dataset: str, run: str, kind: Kind) -> Locations:
    """The ``kind`` entries of one run (CSV order) at their aligned positions where the run
    has :data:`ALIGNED_POSES`, else as recorded."""
    recorded = tree.locations(dataset, run, kind)
    path = tree.root / dataset / run / ALIGNED_POSES
    if not path.is_file():
        return recorded
    aligned = read_locations_csv(path)
    t = aligned.timestamp
    if len(t) < 2 or np.any(np.diff(t) <= 0):
        raise InputError("aligned poses need at least 2 rows, timestamps increasing", path)
    outside = (recorded.timestamp < t[0]) | (recorded.timestamp > t[-1])
    if outside.any():
        first = int(recorded.timestamp[np.flatnonzero(outside)[0]])
        raise InputError(
            f"{int(outside.sum())} {kind} entries of {run} (first at {first}) lie outside the "
            f"aligned poses' time span {int(t[0])}..{int(t[-1])}",
            path,
        )
    # Interpolate in offsets from the first timestamp: µs since 1970 lose precision as floats.
    at = (recorded.timestamp - t[0]).astype(np.float64)
    grid = (t - t[0]).astype(np.float64)
    north = np.interp(at, grid, aligned.northing)
    east = np.interp(at, grid, aligned.easting)
    moved = np.hypot(north - recorded.northing, east - recorded.easting)
    log.info(
        "%s/%s: %d %s entries at their aligned positions (%s; moved %.2f m median, %.2f m max)",
        dataset,
        run,
        len(moved),
        kind,
        ALIGNED_POSES,
        float(np.median(moved)) if len(moved) else 0.0,
        float(moved.max()) if len(moved) else 0.0,
    )
    return Locations(recorded.timestamp, north, east)
