"""Where a submap is cut along a drive's trajectory: :class:`Cut`, the record that
:mod:`.prepare` plans and :mod:`.truth` reads (its own module, so that neither imports the other
for it)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Cut:
    """One submap position along the trajectory.

    ``distance_m``: travelled distance of the window centre; ``scan``: index of the scan whose
    travelled distance is nearest to it (ties: the earlier scan): it gives the submap's
    timestamp and position; ``first``/``last``: the scans of the window (inclusive).
    """

    distance_m: float
    scan: int
    first: int
    last: int
