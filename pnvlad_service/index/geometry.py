"""The database submaps' points in metres, kept in the bundle for geometric verification.

Two files beside the index, recorded in the manifest's ``geometry`` entry
(:class:`~pnvlad_service.index.manifest.GeometryRecord`)::

    <bundle>/geometry.f16   raw little-endian float16 [N, 4096, 3]: row i is submap i's
                            normalised .bin coordinates (in [-1, 1], so float16 keeps them to
                            2**-12 of a unit: millimetres once scaled), 24,576 bytes a row
    <bundle>/geometry.npz   one row per submap (no pickle): origin float64 [N, 3] (UTM
                            easting, northing, height of the local frame's origin), centre
                            float64 [N, 3] and scale float64 [N] (local metres = centre +
                            scale * row), digest uint64 [N] (8-byte BLAKE2b of row i's bytes)

Row ``i`` is vector ``i`` of the index and row ``i`` of the metadata. Where the numbers come
from: the tree's frame sidecars (:mod:`pnvlad_service.data.frames`).

:class:`BundleGeometry` maps ``geometry.f16`` (``mmap``, random access advised) and never reads
it whole: start-up costs the same for a thousand submaps as for a million, and a query reads
only the rows it asks for. Checks at :meth:`BundleGeometry.open`: the file's size is exactly
``N * 24,576`` bytes (else it is refused as truncated, naming it); the table's sha256; the
points file's sha256 when it is small (:data:`FULL_HASH_MAX_BYTES`), else the digests of a
sample of rows (first, last and :data:`SAMPLE_ROWS` seeded random ones). Every row fetched is
checked against its digest.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import mmap
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pnvlad_service.errors import CorruptFileError, InputError, PnvladError
from pnvlad_service.fileio import sha256_file
from pnvlad_service.index.manifest import GeometryRecord
from pnvlad_service.io.submap import SUBMAP_BOUND, SUBMAP_POINTS, read_submap

if TYPE_CHECKING:
    from pnvlad_service.data.frames import SubmapFrame
    from pnvlad_service.data.tree import Submap

POINTS_FILE = "geometry.f16"
TABLE_FILE = "geometry.npz"
DTYPE = "<f2"
DIGEST = "blake2b-64"
#: Bytes of one row of ``geometry.f16``: float16 x 3 x 4096.
ROW_BYTES = SUBMAP_POINTS * 3 * 2
#: Points files up to this size are hashed whole at start-up (like the other files); bigger
#: ones are checked by a sample of rows at start-up and row by row when fetched.
FULL_HASH_MAX_BYTES = 256 * 2**20
#: Random rows checked at start-up when the points file is too big to hash (plus first, last).
SAMPLE_ROWS = 64
_TABLE_COLUMNS = ("origin", "centre", "scale", "digest")
#: Rows read or written at a time when streaming the points file.
_CHUNK_ROWS = 1024


def row_digest(row: bytes | memoryview | np.ndarray) -> int:
    """The 8-byte BLAKE2b digest of one row's bytes, as an unsigned integer."""
    data = row.tobytes() if isinstance(row, np.ndarray) else row
    return int.from_bytes(hashlib.blake2b(data, digest_size=8).digest(), "little")


def to_rows(normalised: np.ndarray, source: str | Path | None = None) -> np.ndarray:
    """Benchmark submaps float [n, 4096, 3] (coordinates in [-1, 1]) -> float16 ``<f2``
    [n, 4096, 3] rows; :class:`InputError` naming ``source`` for values float16 cannot hold to
    the documented precision (non-finite or outside [-1, 1])."""
    a = np.asarray(normalised, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (SUBMAP_POINTS, 3):
        raise InputError(f"expected submaps [n, {SUBMAP_POINTS}, 3], got {a.shape}", source)
    if not np.isfinite(a).all() or np.abs(a).max(initial=0.0) > SUBMAP_BOUND:
        raise InputError(
            f"submap coordinates must be finite and within [-{SUBMAP_BOUND}, {SUBMAP_BOUND}]",
            source,
        )
    return a.astype(DTYPE)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


class GeometryWriter:
    """Writes ``geometry.f16`` and ``geometry.npz`` of exactly ``count`` rows into ``directory``
    (a bundle's temporary directory: :func:`pnvlad_service.fileio.atomic_directory` makes the
    whole bundle appear at once, so nothing here is ever seen half-written).

    Rows go in with :meth:`append` (float16) or :meth:`append_submaps` (benchmark submaps and
    their frames); :meth:`finish` checks the count, writes the table and returns the
    manifest's record. The points file's sha256 is computed while writing when the file will be
    at most ``full_hash_max_bytes``, and recorded as ``None`` otherwise.
    """

    def __init__(
        self, directory: str | Path, count: int, full_hash_max_bytes: int = FULL_HASH_MAX_BYTES
    ) -> None:
        self.directory = Path(directory)
        self.count = int(count)
        self._fh = open(self.directory / POINTS_FILE, "wb")  # noqa: SIM115 - closed in finish
        self._sha = hashlib.sha256() if self.count * ROW_BYTES <= full_hash_max_bytes else None
        self._written = 0
        self._origin: list[np.ndarray] = []
        self._centre: list[np.ndarray] = []
        self._scale: list[np.ndarray] = []
        self._digest: list[np.ndarray] = []

    def append(
        self,
        rows: np.ndarray,
        origin: np.ndarray,
        centre: np.ndarray,
        scale: np.ndarray,
        digests: np.ndarray | None = None,
    ) -> None:
        """Append float16 ``rows`` [n, 4096, 3] with their origin [n, 3], centre [n, 3] and
        scale [n]; ``digests`` uint64 [n], when known (rows copied from a bundle), are checked
        rather than trusted: a mismatch is a :class:`CorruptFileError`."""
        rows = np.ascontiguousarray(rows, dtype=DTYPE)
        n = len(rows)
        if rows.shape[1:] != (SUBMAP_POINTS, 3):
            raise PnvladError(f"geometry rows must be [n, {SUBMAP_POINTS}, 3], got {rows.shape}")
        if self._written + n > self.count:
            raise PnvladError(f"more than the {self.count} geometry rows announced")
        got = np.array([row_digest(r) for r in rows], dtype=np.uint64)
        if digests is not None:
            bad = np.flatnonzero(got != np.asarray(digests, dtype=np.uint64))
            if len(bad):
                raise CorruptFileError(
                    f"a row being copied (row {int(bad[0])} of this chunk) does not match its "
                    "digest",
                    source=POINTS_FILE,
                )
        data = rows.tobytes()
        self._fh.write(data)
        if self._sha is not None:
            self._sha.update(data)
        self._origin.append(np.asarray(origin, dtype=np.float64).reshape(n, 3))
        self._centre.append(np.asarray(centre, dtype=np.float64).reshape(n, 3))
        self._scale.append(np.asarray(scale, dtype=np.float64).reshape(n))
        self._digest.append(got)
        self._written += n

    def append_submaps(
        self, root: str | Path, records: Sequence[Submap], frames: Sequence[SubmapFrame]
    ) -> None:
        """Append the submaps ``records`` (read from ``root / record.path``) with their frame
        sidecar rows ``frames`` (same order), :data:`_CHUNK_ROWS` at a time."""
        root = Path(root)
        if len(records) != len(frames):
            raise PnvladError(f"{len(records)} submaps but {len(frames)} frames")
        for start in range(0, len(records), _CHUNK_ROWS):
            recs = records[start : start + _CHUNK_ROWS]
            frs = frames[start : start + _CHUNK_ROWS]
            rows = np.stack(
                [to_rows(read_submap(root / r.path)[None], root / r.path)[0] for r in recs]
            )
            self.append(
                rows,
                np.stack([f.origin for f in frs]),
                np.stack([f.centre for f in frs]),
                np.array([f.scale for f in frs]),
            )

    def append_bundle(self, geometry: BundleGeometry) -> None:
        """Append every row of an open bundle's geometry, each checked against its digest."""
        for start in range(0, geometry.count, _CHUNK_ROWS):
            stop = min(start + _CHUNK_ROWS, geometry.count)
            self.append(
                geometry._rows[start:stop],
                geometry.origin[start:stop],
                geometry.centre[start:stop],
                geometry._scale[start:stop],
                digests=geometry.digest[start:stop],
            )

    def finish(self) -> GeometryRecord:
        """Close the points file (fsync'ed), write the table; the manifest's record."""
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        if self._written != self.count:
            raise PnvladError(f"{self._written} geometry rows written, {self.count} announced")

        def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: type) -> np.ndarray:
            return np.concatenate(parts) if parts else np.empty(shape, dtype=dtype)

        buf = io.BytesIO()
        np.savez(
            buf,
            origin=cat(self._origin, (0, 3), np.float64),
            centre=cat(self._centre, (0, 3), np.float64),
            scale=cat(self._scale, (0,), np.float64),
            digest=cat(self._digest, (0,), np.uint64),
        )
        table = self.directory / TABLE_FILE
        with open(table, "wb") as fh:
            fh.write(buf.getvalue())
            fh.flush()
            os.fsync(fh.fileno())
        return GeometryRecord(
            points_file=POINTS_FILE,
            table_file=TABLE_FILE,
            count=self.count,
            points=SUBMAP_POINTS,
            dtype=DTYPE,
            bytes=self.count * ROW_BYTES,
            digest=DIGEST,
            table_sha256=sha256_file(table),
            points_sha256=None if self._sha is None else self._sha.hexdigest(),
        )

    def abort(self) -> None:
        """Close the points file without finishing (the temporary directory goes anyway)."""
        self._fh.close()


def database_frames(
    root: str | Path, records: Sequence[Submap]
) -> tuple[list[SubmapFrame] | None, list[str]]:
    """The frame sidecar row of each of ``records`` (in order), or ``None`` and the runs
    (``dataset/run``, sorted) that have no sidecar. :class:`InputError` for a bad sidecar."""
    from pnvlad_service.data.tree import BenchmarkTree

    tree = BenchmarkTree(root)
    by_run: dict[tuple[str, str, str], list[SubmapFrame] | None] = {}
    for r in records:
        key = (r.dataset, r.run, r.kind)
        if key not in by_run:
            by_run[key] = tree.frames(r.dataset, r.run, r.kind)
    missing = sorted({f"{d}/{run}" for (d, run, _), fr in by_run.items() if fr is None})
    if missing:
        return None, missing
    return [by_run[(r.dataset, r.run, r.kind)][r.row] for r in records], []  # type: ignore[index]


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


class BundleGeometry:
    """The geometry of an open bundle: ``count`` submaps of ``points`` (4096) points each.

    ``geometry.f16`` is memory-mapped; :meth:`metres` reads one row (checked against its
    digest) and returns float64 [4096, 3] metres in the submap's local frame; :meth:`map_pose`
    is that frame's pose in UTM. The table (origin, centre, scale, digest: 40 bytes a submap)
    is in memory. Open it with :meth:`open` (what :meth:`IndexBundle.load
    <pnvlad_service.index.bundle.IndexBundle.load>` does).
    """

    def __init__(
        self,
        path: Path,
        record: GeometryRecord,
        origin: np.ndarray,
        centre: np.ndarray,
        scale: np.ndarray,
        digest: np.ndarray,
    ) -> None:
        self.path = path
        self.record = record
        self.origin = origin
        self.centre = centre
        self._scale = scale
        self.digest = digest
        self._file = path / record.points_file
        self._mmap: mmap.mmap | None = None
        self._rows = np.empty((0, SUBMAP_POINTS, 3), dtype=DTYPE)
        if record.count:
            with open(self._file, "rb") as fh:
                self._mmap = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
            if hasattr(mmap, "MADV_RANDOM"):
                self._mmap.madvise(mmap.MADV_RANDOM)  # a query reads a few scattered rows
            self._rows = np.frombuffer(self._mmap, dtype=DTYPE).reshape(
                record.count, SUBMAP_POINTS, 3
            )

    # -- opening and its checks ----------------------------------------------------------
    @classmethod
    def open(
        cls,
        bundle_dir: str | Path,
        record: GeometryRecord,
        *,
        verify: bool = True,
        full_hash_max_bytes: int = FULL_HASH_MAX_BYTES,
        sample_rows: int = SAMPLE_ROWS,
    ) -> BundleGeometry:
        """Map the geometry of the bundle at ``bundle_dir`` that the manifest's ``record``
        describes. Always checked: the format and the points file's size (a truncated file is
        refused, naming it). With ``verify``: the table's sha256, and the points file's sha256
        when it is at most ``full_hash_max_bytes`` (and recorded), else the digests of the
        first, the last and ``sample_rows`` seeded random rows. :class:`InputError` naming the
        file for each failure."""
        path = Path(bundle_dir)
        points, table = path / record.points_file, path / record.table_file
        if (record.dtype, record.points, record.digest) != (DTYPE, SUBMAP_POINTS, DIGEST):
            raise InputError(
                f"geometry of {record.points} points as {record.dtype} ({record.digest}) is not "
                f"supported (want {SUBMAP_POINTS} as {DTYPE}, {DIGEST})",
                source=path / "manifest.json",
            )
        need = record.count * ROW_BYTES
        if not points.is_file():
            raise InputError("geometry file not found (the manifest records one)", points)
        size = points.stat().st_size
        if size < need:
            raise InputError(
                f"{points.name} is truncated: {size:,} bytes where {record.count:,} rows need "
                f"{need:,}",
                source=points,
            )
        if size != need or record.bytes != need:
            raise InputError(
                f"{points.name} has {size:,} bytes where {record.count:,} rows need {need:,} "
                f"(the manifest says {record.bytes:,})",
                source=points,
            )
        if not table.is_file():
            raise InputError("geometry table not found (the manifest records one)", table)
        if verify and sha256_file(table) != record.table_sha256:
            raise InputError(
                f"{table.name} does not match the manifest's sha256 (bundle corrupted?)", table
            )
        geo = cls(path, record, *_read_table(table, record.count))
        if verify:
            full = record.points_sha256 is not None and need <= full_hash_max_bytes
            if full and sha256_file(points) != record.points_sha256:
                bad = geo.first_bad_row(range(record.count))
                where = "" if bad is None else f" (row {bad} does not match its digest)"
                geo.close()
                raise InputError(
                    f"{points.name} does not match the manifest's sha256{where} "
                    "(bundle corrupted?)",
                    source=points,
                )
            if not full:
                bad = geo.first_bad_row(geo.sample(sample_rows))
                if bad is not None:
                    geo.close()
                    raise InputError(
                        f"{points.name} row {bad} does not match its digest (bundle corrupted?)",
                        source=points,
                    )
        return geo

    def sample(self, n: int = SAMPLE_ROWS) -> np.ndarray:
        """The rows a start-up checks when the file is too big to hash: first, last and ``n``
        random ones, seeded by the table's sha256 (the same rows at every start-up)."""
        if self.count == 0:
            return np.empty(0, dtype=np.int64)
        rng = np.random.default_rng(int(self.record.table_sha256[:16], 16))
        picks = rng.choice(self.count, size=min(n, self.count), replace=False)
        return np.unique(np.concatenate([[0, self.count - 1], picks]).astype(np.int64))

    def first_bad_row(self, rows: Iterable[int]) -> int | None:
        """The first of ``rows`` whose bytes do not match its digest, or ``None``."""
        for i in rows:
            i = int(i)
            if row_digest(self._rows[i]) != int(self.digest[i]):
                return i
        return None

    # -- the interface -------------------------------------------------------------------
    @property
    def count(self) -> int:
        """Submaps (rows); equal to the index's vector count."""
        return self.record.count

    @property
    def points(self) -> int:
        """Points per submap (4096)."""
        return self.record.points

    @property
    def file(self) -> Path:
        """The points file, ``<bundle>/geometry.f16``."""
        return self._file

    def raw(self, i: int) -> np.ndarray:
        """Row ``i`` as stored: float16 [4096, 3], normalised; checked against its digest
        (:class:`CorruptFileError` naming the file and the row when it does not match)."""
        i = self._check_id(i)
        row = np.array(self._rows[i])  # a copy: a few pages read from the mapping
        if row_digest(row) != int(self.digest[i]):
            raise CorruptFileError(
                f"row {i} does not match its digest (the bundle's geometry is corrupted)",
                source=self._file,
            )
        return row

    def metres(self, i: int) -> np.ndarray:
        """Submap ``i``'s points in metres in its local frame: float64 [4096, 3]
        (``centre + scale * row``; the float16 row is within 2**-12 of the .bin's value)."""
        row = self.raw(i)
        return self.centre[i] + self._scale[i] * row.astype(np.float64)

    def metres_many(self, ids: Iterable[int]) -> list[np.ndarray]:
        """:meth:`metres` of each of ``ids``, in order."""
        return [self.metres(int(i)) for i in ids]

    def map_pose(self, i: int) -> np.ndarray:
        """float64 [4, 4]: submap ``i``'s local frame -> UTM (easting, northing, height) as the
        map records it: axes UTM, translation the frame's origin."""
        i = self._check_id(i)
        out = np.eye(4)
        out[:3, 3] = self.origin[i]
        return out

    def scale(self, i: int) -> float:
        """Metres per normalised unit of submap ``i`` (negative where G negated the cloud)."""
        return float(self._scale[self._check_id(i)])

    def nbytes_per_submap(self) -> float:
        """Bytes the geometry takes per submap on disk (points file and table)."""
        table = (self.path / self.record.table_file).stat().st_size
        return (self.record.bytes + table) / max(self.count, 1)

    def close(self) -> None:
        """Unmap the points file (rows already returned stay valid: they are copies)."""
        self._rows = np.empty((0, SUBMAP_POINTS, 3), dtype=DTYPE)
        if self._mmap is not None:
            mm, self._mmap = self._mmap, None
            # A view of it still alive somewhere: the garbage collector unmaps it later.
            with contextlib.suppress(BufferError):
                mm.close()

    def _check_id(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < self.count:
            raise IndexError(f"geometry row {i} out of range [0, {self.count})")
        return i


def _read_table(path: Path, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(origin, centre, scale, digest) of ``geometry.npz``, checked for columns and shapes."""
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [c for c in _TABLE_COLUMNS if c not in z.files]
            if missing:
                raise InputError(f"geometry table lacks the columns {missing}", source=path)
            origin, centre, scale, digest = (z[c] for c in _TABLE_COLUMNS)
    except (ValueError, OSError) as exc:
        raise InputError(f"cannot read the geometry table: {exc}", source=path) from exc
    shapes = {"origin": (count, 3), "centre": (count, 3), "scale": (count,), "digest": (count,)}
    for name, arr in zip(_TABLE_COLUMNS, (origin, centre, scale, digest), strict=True):
        if arr.shape != shapes[name]:
            raise InputError(
                f"geometry table column {name} has shape {arr.shape}, want {shapes[name]}", path
            )
    return (
        origin.astype(np.float64, copy=False),
        centre.astype(np.float64, copy=False),
        scale.astype(np.float64, copy=False),
        digest.astype(np.uint64, copy=False),
    )


def geometry_writer(
    root: str | Path,
    records: Sequence[Submap],
    frames: Sequence[SubmapFrame],
    base: BundleGeometry | None = None,
    full_hash_max_bytes: int = FULL_HASH_MAX_BYTES,
) -> Callable[[Path], GeometryRecord]:
    """What :func:`~pnvlad_service.index.bundle.write_bundle` calls with the bundle's
    temporary directory: write ``base``'s rows (an existing bundle's, each checked), then the
    submaps ``records`` of the tree at ``root`` with their ``frames``; return the record."""

    def write(directory: Path) -> GeometryRecord:
        count = len(records) + (0 if base is None else base.count)
        writer = GeometryWriter(directory, count, full_hash_max_bytes)
        try:
            if base is not None:
                writer.append_bundle(base)
            writer.append_submaps(root, records, frames)
            return writer.finish()
        except BaseException:
            writer.abort()
            raise

    return write


def check_geometry(bundle_dir: str | Path, verify: bool = True) -> GeometryRecord | None:
    """The start-up checks of :meth:`BundleGeometry.open` on the bundle at ``bundle_dir``
    (what ``pnvlad serve`` runs before it starts the server, so a bad geometry file is a
    one-line error and exit 2); its record, or ``None`` when the bundle has no geometry."""
    from pnvlad_service.index.manifest import Manifest

    manifest = Manifest.read(bundle_dir)
    if manifest.geometry is None:
        return None
    BundleGeometry.open(bundle_dir, manifest.geometry, verify=verify).close()
    return manifest.geometry
