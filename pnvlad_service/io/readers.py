"""Point-cloud files in, ``[N, 3]`` coordinates in metres out.

Every reader returns a C-contiguous ``float32`` or ``float64`` array of shape ``[N, 3]`` (x, y, z
in the file's own frame and units, metres for every format here), with any extra columns
(intensity, ring, laser id) left out. Readers are picked from the explicit table ``READERS``,
either by name (``read_points(path, reader="kitti")``, CLI ``--reader kitti``) or by suffix.

Raw ``.bin`` files have no header, and the record sizes of the formats overlap (every multiple
of 16 bytes, a KITTI size, is also a multiple of 8, an NCLT size; every multiple of 40 fits both
nuScenes and NCLT), so a ``.bin`` is read without a reader name only when it cannot be anything
else: exactly 98,304 bytes whose float64 values all lie in [-1, 1] and look like a normalised
submap (centroid near 0, mean distance from it between 0.2 and 0.8). Anything else is refused
with an :class:`~pnvlad_service.errors.InputError` that lists the readers whose record size fits.

Readers (name: suffixes; layout; returned dtype):

- ``benchmark``: .bin; float64 x, y, z, exactly 4096 points (98,304 bytes); float64.
- ``kitti``: .bin; float32 x, y, z, reflectance (KITTI, SemanticKITTI), 16 B a point; float32.
- ``nuscenes``: .bin; float32 x, y, z, intensity, ring, 20 B a point; float32.
- ``nclt``: .bin; little-endian uint16 x, y, z, uint8 intensity, uint8 laser id, 8 B a point,
  metres = value * 0.005 - 100; float64. NCLT's frame has z pointing down; it is kept as is.
- ``npy``: .npy; numeric [N, >=3], first three columns; float32/float64 as saved, else float64.
- ``pcd``: .pcd; fields x, y, z (pypcd4, extra ``io``); as saved.
- ``ply``: .ply; element ``vertex`` with x, y, z (plyfile, extra ``io``); as saved.
- ``las``: .las, .laz; scaled coordinates X * scale + offset (laspy + lazrs, extra ``io``);
  float64 (UTM-sized values keep full precision).

A *scan* (one sweep of a LiDAR, in its sensor's frame) is read by :func:`read_scan`: the same,
less its missing returns. Some drivers write a beam that saw nothing as a point at the sensor's
origin instead of leaving it out or writing NaN (Ouster's, in organised clouds: x = y = z = 0,
or the beam's own origin a few centimetres from it); :func:`drop_no_returns` drops every point
nearer the sensor than :data:`NO_RETURN_M` and counts them. Submaps and map files are not
scans (their origin is a place like any other) and keep every point.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.extras import require
from pnvlad_service.io.points import validate_points
from pnvlad_service.io.submap import (
    SUBMAP_BOUND,
    SUBMAP_BYTES,
    SUBMAP_POINTS,
    read_bin_points,
    read_submap,
)

log = logging.getLogger(__name__)

NCLT_SCALE = 0.005
NCLT_OFFSET = -100.0
_NCLT_DTYPE = np.dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"), ("l", "u1")])


@dataclass(frozen=True)
class Reader:
    """One point-cloud format: its name, the suffixes it claims, a reader function.

    ``record_bytes`` is the size of one point for headerless binary formats (``None`` for the
    others); ``read(path) -> ndarray [N, 3]`` float32/float64 metres, not yet validated.
    """

    name: str
    suffixes: tuple[str, ...]
    description: str
    read: Callable[[Path], np.ndarray]
    record_bytes: int | None = None


def _check_record_size(path: Path, record: int, what: str) -> int:
    size = path.stat().st_size
    if size % record:
        raise InputError(
            f"size {size:,} bytes is not a multiple of {record} bytes ({what}): "
            "truncated file or wrong --reader",
            source=path,
        )
    return size // record


def _read_float32_records(path: Path, columns: int, what: str) -> np.ndarray:
    _check_record_size(path, 4 * columns, what)
    data = np.fromfile(path, dtype="<f4").reshape(-1, columns)
    return np.ascontiguousarray(data[:, :3], dtype=np.float32)


def _read_kitti(path: Path) -> np.ndarray:
    return _read_float32_records(path, 4, "KITTI float32 x, y, z, reflectance")


def _read_nuscenes(path: Path) -> np.ndarray:
    return _read_float32_records(path, 5, "nuScenes float32 x, y, z, intensity, ring")


def _read_nclt(path: Path) -> np.ndarray:
    _check_record_size(path, _NCLT_DTYPE.itemsize, "NCLT uint16 x, y, z, uint8 intensity, laser")
    rec = np.fromfile(path, dtype=_NCLT_DTYPE)
    out = np.empty((rec.shape[0], 3), dtype=np.float64)
    for j, name in enumerate("xyz"):
        out[:, j] = rec[name] * NCLT_SCALE + NCLT_OFFSET
    return out


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message (parsers' messages can run to pages)."""
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _as_xyz(array: np.ndarray, path: Path, what: str) -> np.ndarray:
    """First three columns of a numeric 2-D array as float32/float64 [N, 3]."""
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError(
            f"{what} must be a 2-D array with at least 3 columns (x, y, z); got shape "
            f"{tuple(array.shape)}",
            source=path,
        )
    if not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)):
        raise InputError(f"{what} must be numeric, got dtype {array.dtype}", source=path)
    dtype = array.dtype if array.dtype in (np.float32, np.float64) else np.float64
    return np.ascontiguousarray(array[:, :3], dtype=dtype)


def _read_npy(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        if "pickle" in str(exc):  # not the .npy format, or an object array: never unpickled
            reason = "not the NumPy .npy format, or pickled objects, which are never loaded"
        else:
            reason = _first_line(exc)
        raise InputError(f"not a plain numeric .npy array ({reason})", source=path) from None
    if not isinstance(array, np.ndarray):
        raise InputError("expected a single array (.npy), not an archive", source=path)
    return _as_xyz(array, path, ".npy array")


def _stack_fields(columns: list[np.ndarray]) -> np.ndarray:
    dtype = np.result_type(*columns)
    if not np.issubdtype(dtype, np.floating) or dtype not in (np.float32, np.float64):
        dtype = np.float64
    return np.stack([np.asarray(c, dtype=dtype) for c in columns], axis=1)


def _read_pcd(path: Path) -> np.ndarray:
    pypcd4 = require("pypcd4", "pypcd4", "io", "reading .pcd files")
    try:
        cloud = pypcd4.PointCloud.from_path(path)
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        raise InputError(f"cannot parse PCD file ({_first_line(exc)})", source=path) from None
    missing = [f for f in "xyz" if f not in cloud.fields]
    if missing:
        raise InputError(
            f"PCD file has no field(s) {', '.join(missing)}; fields are {list(cloud.fields)}",
            source=path,
        )
    return _stack_fields([cloud.numpy((f,))[:, 0] for f in "xyz"])


def _read_ply(path: Path) -> np.ndarray:
    plyfile = require("plyfile", "plyfile", "io", "reading .ply files")
    try:
        ply = plyfile.PlyData.read(str(path))
    except (plyfile.PlyParseError, ValueError, EOFError) as exc:
        raise InputError(f"cannot parse PLY file ({_first_line(exc)})", source=path) from None
    if "vertex" not in ply:
        raise InputError("PLY file has no 'vertex' element", source=path)
    vertex = ply["vertex"].data
    missing = [f for f in "xyz" if f not in (vertex.dtype.names or ())]
    if missing:
        raise InputError(f"PLY vertex element has no property {', '.join(missing)}", source=path)
    return _stack_fields([vertex[f] for f in "xyz"])


def _read_las(path: Path) -> np.ndarray:
    laspy = require("laspy", "laspy", "io", "reading .las/.laz files")
    try:
        las = laspy.read(path)
    except laspy.errors.LaspyException as exc:
        if path.suffix.lower() == ".laz" and "backend" in str(exc).lower():
            raise MissingDependencyError("lazrs", "io", "reading .laz files") from None
        raise InputError(f"cannot read LAS/LAZ file ({_first_line(exc)})", source=path) from None
    # x, y, z are the scaled coordinates: X * scale + offset, in float64.
    return np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(
        np.float64, copy=False
    )


READERS: dict[str, Reader] = {
    r.name: r
    for r in (
        Reader(
            "benchmark",
            (".bin",),
            f"PointNetVLAD submap: float64 x, y, z, exactly {SUBMAP_POINTS} points",
            read_submap,
            24,
        ),
        Reader("kitti", (".bin",), "KITTI / SemanticKITTI: float32 x, y, z, r", _read_kitti, 16),
        Reader("nuscenes", (".bin",), "nuScenes: float32 x, y, z, i, ring", _read_nuscenes, 20),
        Reader(
            "nclt",
            (".bin",),
            "NCLT velodyne_sync: uint16 x, y, z, uint8 intensity, laser (z down)",
            _read_nclt,
            8,
        ),
        Reader("npy", (".npy",), "NumPy array [N, >=3]", _read_npy),
        Reader("pcd", (".pcd",), "PCD with fields x, y, z (pypcd4)", _read_pcd),
        Reader("ply", (".ply",), "PLY vertex x, y, z (plyfile)", _read_ply),
        Reader("las", (".las", ".laz"), "LAS/LAZ scaled x, y, z (laspy)", _read_las),
    )
}

_BIN_READERS = ("kitti", "nuscenes", "nclt", "benchmark")


def _looks_like_benchmark(path: Path) -> bool:
    values = read_bin_points(path)
    if not np.isfinite(values).all() or np.abs(values).max() > SUBMAP_BOUND:
        return False
    centroid = values.mean(axis=0)
    spread = float(np.linalg.norm(values - centroid, axis=1).mean())
    return bool(np.linalg.norm(centroid) < 0.25 and 0.2 <= spread <= 0.8)


def _choose_bin_reader(path: Path) -> str:
    size = path.stat().st_size
    if size == SUBMAP_BYTES and _looks_like_benchmark(path):
        return "benchmark"
    fits = [
        f"{name} ({size // READERS[name].record_bytes:,} points)"  # type: ignore[operator]
        for name in _BIN_READERS
        if name != "benchmark" and size and size % READERS[name].record_bytes == 0  # type: ignore[operator]
    ]
    if size == SUBMAP_BYTES:
        fits.append(
            f"benchmark ({SUBMAP_POINTS:,} points, but the values do not look like a normalised "
            "submap)"
        )
    hint = f"its size, {size:,} bytes, fits " + (", ".join(fits) if fits else "none of them")
    raise InputError(
        "a raw .bin has no header, so its format cannot be told safely; pass "
        f"--reader {'|'.join(_BIN_READERS)} ({hint})",
        source=path,
    )


def reader_for(path: str | Path, reader: str | None = None) -> Reader:
    """The table entry that reads ``path``: ``reader`` by name, else chosen by suffix."""
    path = Path(path)
    if reader is not None:
        if reader not in READERS:
            raise InputError(
                f"unknown reader {reader!r}; choose one of {', '.join(READERS)}", source="reader"
            )
        return READERS[reader]
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return READERS[_choose_bin_reader(path)]
    for entry in READERS.values():
        if suffix in entry.suffixes:
            return entry
    known = sorted({s for r in READERS.values() for s in r.suffixes})
    raise InputError(
        f"unknown point-cloud suffix {suffix or '(none)'!r}; known: {', '.join(known)} "
        f"(or pass --reader {'|'.join(READERS)})",
        source=path,
    )


#: Metres: a scan's point nearer its sensor than this is a missing return written as a point
#: (at the origin, or at the beam's origin: Ouster's OS sensors place that 1 to 3 cm off it).
#: Spinning LiDARs' minimum ranges are several times this (Ouster OS1: 0.3 m or more).
NO_RETURN_M = 0.1


def drop_no_returns(points: np.ndarray) -> tuple[np.ndarray, int]:
    """``points`` (a scan, ``[N, 3]`` in its sensor's frame) without those nearer the sensor
    than :data:`NO_RETURN_M` (row order kept), and how many were dropped."""
    x, y, z = (np.asarray(points[:, k], dtype=np.float64) for k in range(3))
    keep = x * x + y * y + z * z >= NO_RETURN_M**2
    dropped = len(keep) - int(np.count_nonzero(keep))
    return (points[keep] if dropped else points), dropped


def read_scan(path: str | Path, reader: str | None = None) -> tuple[np.ndarray, int]:
    """A LiDAR scan from a file (:func:`read_points`) without its missing returns
    (:func:`drop_no_returns`): ``(points [N, 3], how many were dropped)``. :class:`InputError`
    naming the file when no point is left."""
    points = read_points(path, reader)
    kept, dropped = drop_no_returns(points)
    if dropped:
        log.debug("%s: %d points at the sensor's origin (missing returns) dropped", path, dropped)
    if len(kept) == 0:
        raise InputError(
            f"all {dropped:,} points lie within {NO_RETURN_M} m of the sensor: a scan without "
            "returns",
            path,
        )
    return kept, dropped


def read_points(path: str | Path, reader: str | None = None) -> np.ndarray:
    """Read a point-cloud file into ``[N, 3]`` coordinates in metres.

    Args:
        path: the file; its suffix picks the reader unless ``reader`` is given.
        reader: a key of :data:`READERS` (``benchmark``, ``kitti``, ``nuscenes``, ``nclt``,
            ``npy``, ``pcd``, ``ply``, ``las``).

    Returns:
        C-contiguous float32 or float64 array ``[N, 3]`` (benchmark submaps stay float64),
        x, y, z in the file's frame; extra columns are dropped.

    Raises:
        FileNotFoundError: no such file.
        InputError: unknown or ambiguous format, truncated file, NaN/inf, empty cloud.
        MissingDependencyError: a .pcd/.ply/.las/.laz reader's package is not installed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    entry = reader_for(path, reader)
    points = entry.read(path)
    log.debug("read %d points from %s with reader %s", points.shape[0], path, entry.name)
    return validate_points(points, path)
