"""The benchmark submap format: one submap is 4096 points, x, y, z in the normalised frame.

On disk (the published PointNetVLAD layout) a submap is a ``<timestamp>.bin`` file of
little-endian float64 x, y, z interleaved, no header: 4096 × 3 × 8 = 98,304 bytes, every
coordinate in [-1, 1]. In memory the encoder takes float32 [B, 4096, 3].

Every ``.bin`` of this layout is read here: :func:`read_submap` (exactly one benchmark submap)
and :func:`read_bin_points` (any number of float64 triples, for trees whose submaps hold another
point count); :func:`write_submap` writes one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_open
from pnvlad_service.io.points import validate_points

#: Points in one submap (the encoder's input size).
SUBMAP_POINTS = 4096
#: Element type of a ``.bin`` submap on disk.
SUBMAP_DTYPE = "<f8"
#: Bytes of one ``.bin`` submap: float64 × 3 × 4096.
SUBMAP_BYTES = SUBMAP_POINTS * 3 * 8
#: Largest |coordinate| of a submap (the normalised frame is [-1, 1]).
SUBMAP_BOUND = 1.0


def read_bin_points(path: str | Path) -> np.ndarray:
    """The float64 x, y, z triples of a headerless ``.bin``: float64 [N, 3], any N.

    Raises ``FileNotFoundError`` for a missing file and :class:`InputError` naming the file when
    its float64 count is not a multiple of 3.
    """
    raw = np.fromfile(Path(path), dtype=SUBMAP_DTYPE)
    if raw.size % 3:
        raise InputError(f"{raw.size} float64 values, not a multiple of 3", path)
    return raw.reshape(-1, 3)


def read_submap(path: str | Path) -> np.ndarray:
    """One benchmark submap ``.bin``: float64 [4096, 3], values as stored (not validated).

    Raises ``FileNotFoundError`` for a missing file and :class:`InputError` naming the file when
    it is not exactly :data:`SUBMAP_BYTES` (98,304) bytes.
    """
    path = Path(path)
    size = path.stat().st_size
    if size != SUBMAP_BYTES:
        raise InputError(
            f"a benchmark submap holds exactly {SUBMAP_POINTS} float64 points "
            f"({SUBMAP_BYTES:,} bytes); this file has {size:,} bytes",
            source=path,
        )
    return read_bin_points(path).astype(np.float64, copy=False)


def write_submap(path: str | Path, points: np.ndarray) -> None:
    """Write ``points [N, 3]`` atomically: ``.bin`` as little-endian float64 x, y, z with no
    header (98,304 bytes for a 4096-point benchmark submap), or ``.npy`` (float64).

    Raises :class:`InputError` for points that are not a non-empty finite ``[N, 3]`` array or a
    suffix other than ``.bin``/``.npy``; an existing file is then left as it was.
    """
    path = Path(path)
    points = validate_points(np.asarray(points), "points")
    data = np.ascontiguousarray(points, dtype=SUBMAP_DTYPE)
    suffix = path.suffix.lower()
    if suffix == ".bin":
        with atomic_open(path, "wb") as fh:
            fh.write(data.tobytes())
    elif suffix == ".npy":
        with atomic_open(path, "wb") as fh:
            np.save(fh, data, allow_pickle=False)
    else:
        raise InputError(f"a submap is written as .bin or .npy, not {suffix!r}", source=path)
