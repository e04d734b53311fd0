"""Where submaps are cut along a drive's trajectory.

:class:`Cut` is one submap's place (its window's scans and centre scan): the record
:mod:`.prepare` plans and :mod:`.truth` reads, in its own module so that neither imports the
other for it. :data:`GEOMETRY` holds each layout's default stride, window and box per kind of
submap, :func:`resolve_geometry` fills a call's overrides in, and :func:`submap_cuts` places
the windows along the travelled distance.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pnvlad_service.data.tree import LAYOUTS
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)

Layout = Literal["oxford", "inhouse"]
Kind = Literal["train", "test", "keyframe"]


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


@dataclass(frozen=True)
class Geometry:
    """Default geometry of one benchmark layout for one kind of submap.

    ``stride_m``: distance travelled between submaps; ``window_m``: stretch of trajectory
    accumulated (0: the centre scan alone, a keyframe); ``box_m``: side of the square crop
    around the submap (``None``: no crop).
    Folder and CSV names come from :data:`pnvlad_service.data.tree.LAYOUTS`.
    """

    stride_m: float
    window_m: float
    box_m: float | None


#: Metres driven between two keyframes of a keyframe map.
KEYFRAME_STRIDE_M = 5.0

#: (layout, kind) -> default geometry, as BENCHMARK_FORMAT.md describes the two layouts;
#: keyframes (ours) are single scans, one every ``KEYFRAME_STRIDE_M``, in either layout.
GEOMETRY: dict[tuple[str, str], Geometry] = {
    ("oxford", "train"): Geometry(stride_m=10.0, window_m=20.0, box_m=None),
    ("oxford", "test"): Geometry(stride_m=20.0, window_m=20.0, box_m=None),
    ("inhouse", "train"): Geometry(stride_m=10.0, window_m=25.0, box_m=25.0),
    ("inhouse", "test"): Geometry(stride_m=25.0, window_m=25.0, box_m=25.0),
    ("oxford", "keyframe"): Geometry(stride_m=KEYFRAME_STRIDE_M, window_m=0.0, box_m=None),
    ("inhouse", "keyframe"): Geometry(stride_m=KEYFRAME_STRIDE_M, window_m=0.0, box_m=None),
}


def resolve_geometry(
    layout: str,
    kind: str,
    window_m: float | None,
    box_m: float | None,
    stride_m: float | None,
) -> tuple[str, str, float, float | None, float]:
    """(folder, csv name, window, box, stride) for one layout and kind: the :data:`GEOMETRY`
    defaults where an argument is ``None`` (a box of 0: none, so the in-house layout's box can
    be turned off), each checked: a negative, NaN or infinite box is an error naming
    ``box_m``."""
    if layout not in LAYOUTS or (layout, kind) not in GEOMETRY:
        raise InputError(
            f"unknown layout/kind {layout!r}/{kind!r} (layouts: {', '.join(LAYOUTS)}; kinds: "
            "train, test)",
            "layout",
        )
    geo = GEOMETRY[(layout, kind)]
    window = geo.window_m if window_m is None else float(window_m)
    box = geo.box_m if box_m is None else check_box_m(box_m, allow_zero=True)
    stride = geo.stride_m if stride_m is None else float(stride_m)
    if not (math.isfinite(window) and (window > 0 or (kind == "keyframe" and window == 0))):
        raise InputError(f"must be a positive number of metres, got {window}", "window_m")
    if not (math.isfinite(stride) and stride > 0):
        raise InputError(f"must be a positive number of metres, got {stride}", "stride_m")
    names = LAYOUTS[layout]
    return names.folder(kind), names.csv(kind), window, box, stride


def check_box_m(box_m: float | None, *, allow_zero: bool = False) -> float | None:
    """A submap box side checked: ``None`` stays ``None`` (no box); a finite number of metres
    > 0 is the side; 0 means no box where ``allow_zero`` (``pnvlad data prepare --box 0``).
    Anything else (negative, NaN, infinite, 0 where not allowed) is an :class:`InputError`
    naming ``box_m``."""
    if box_m is None:
        return None
    try:
        box = float(box_m)
    except (TypeError, ValueError):
        raise InputError(f"must be a number of metres, got {box_m!r}", "box_m") from None
    if allow_zero and box == 0:
        return None
    if not (math.isfinite(box) and box > 0):
        raise InputError(f"must be a positive finite number of metres, got {box_m}", "box_m")
    return box


def submap_cuts(travelled: np.ndarray, window_m: float, stride_m: float) -> list[Cut]:
    """Where to cut submaps: a window of ``window_m`` every ``stride_m`` metres travelled.

    Window ``k`` is centred at distance ``window_m / 2 + k * stride_m`` and holds the scans whose
    travelled distance lies within ``window_m / 2`` of it (inclusive); only whole windows are cut
    (centre + window_m / 2 <= total distance). A cut whose centre scan is the same as the previous
    cut's (a gap in the scans longer than the stride) is dropped. ``window_m`` 0 cuts keyframes:
    the scan nearest each ``k * stride_m`` alone (``first`` = ``last`` = ``scan``).
    """
    if not (window_m >= 0 and stride_m > 0):
        raise InputError("window must be >= 0 and stride > 0 (metres)", "window_m/stride_m")
    d = np.asarray(travelled, dtype=np.float64)
    if d.ndim != 1 or len(d) == 0 or np.any(np.diff(d) < 0):
        raise InputError("travelled distances must be a non-decreasing [T] array", "travelled")
    half = window_m / 2.0
    total = float(d[-1])
    cuts: list[Cut] = []
    k = 0
    while True:
        s = half + k * stride_m
        k += 1
        if s + half > total:
            break
        j = int(np.searchsorted(d, s, side="left"))  # first scan with d >= s
        if j == len(d) or (j > 0 and s - d[j - 1] <= d[j] - s):
            j = int(np.searchsorted(d, d[j - 1], side="left"))  # nearer below: its first scan
        first = int(np.searchsorted(d, s - half, side="left"))
        last = int(np.searchsorted(d, s + half, side="right")) - 1
        if window_m == 0:
            first = last = j
        if cuts and cuts[-1].scan == j:
            log.warning("no scan near %.1f m of travel (gap in the drive); submap skipped", s)
            continue
        cuts.append(Cut(distance_m=s, scan=j, first=first, last=last))
    return cuts
