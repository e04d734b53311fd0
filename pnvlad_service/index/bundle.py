"""FAISS index bundles: the map a localisation service searches.

A bundle is a directory written atomically (:func:`pnvlad_service.fileio.atomic_directory`)::

    <bundle>/index.faiss     the FAISS index, descriptors float32 [N, D], metric L2
    <bundle>/metadata.npz    one row per vector (no pickle): submap_id, dataset, run,
                             timestamp (int64 µs), northing, easting (float64, UTM metres),
                             utm_zone ("" when unknown), path (relative to the benchmark root)
    <bundle>/manifest.json   :class:`pnvlad_service.index.manifest.Manifest`
    <bundle>/geometry.f16    optional: the submaps' points, float16 [N, 4096, 3], and
    <bundle>/geometry.npz    their origin, centre, scale and row digests
                             (:mod:`pnvlad_service.index.geometry`; the manifest's ``geometry``)

Vector ``i`` of the index is row ``i`` of the metadata (and of the geometry). Distances
returned by :meth:`IndexBundle.search` are Euclidean (not squared) descriptor distances.

``faiss`` is imported inside the functions that need it.
"""

from __future__ import annotations

import datetime as _dt
import io
import json
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError, PnvladError
from pnvlad_service.fileio import (
    atomic_directory,
    atomic_write_bytes,
    atomic_write_text,
    sha256_file,
)
from pnvlad_service.index.geometry import FULL_HASH_MAX_BYTES, SAMPLE_ROWS, BundleGeometry
from pnvlad_service.index.keys import apply_search_params, import_faiss
from pnvlad_service.index.manifest import (
    FORMAT,
    INDEX_FILE,
    MANIFEST_FILE,
    METADATA_FILE,
    GeometryRecord,
    Manifest,
    MapRecord,
    ModelRecord,
    format_version,
)

if TYPE_CHECKING:
    from pnvlad_service.data.tree import Submap

log = logging.getLogger(__name__)

METADATA_FIELDS = (
    "submap_id",
    "dataset",
    "run",
    "timestamp",
    "northing",
    "easting",
    "utm_zone",
    "path",
)


# --------------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------------


@dataclass
class Metadata:
    """Column arrays, one row per index vector; see the module docstring for the fields."""

    submap_id: np.ndarray
    dataset: np.ndarray
    run: np.ndarray
    timestamp: np.ndarray
    northing: np.ndarray
    easting: np.ndarray
    utm_zone: np.ndarray
    path: np.ndarray

    @classmethod
    def from_records(cls, records: Sequence[Submap]) -> Metadata:
        """Columns from submap records (order kept)."""
        return cls(
            submap_id=np.array([r.submap_id for r in records], dtype=np.str_),
            dataset=np.array([r.dataset for r in records], dtype=np.str_),
            run=np.array([r.run for r in records], dtype=np.str_),
            timestamp=np.array([r.timestamp for r in records], dtype=np.int64),
            northing=np.array([r.northing for r in records], dtype=np.float64),
            easting=np.array([r.easting for r in records], dtype=np.float64),
            utm_zone=np.array([r.utm_zone for r in records], dtype=np.str_),
            path=np.array([r.path for r in records], dtype=np.str_),
        )

    def __len__(self) -> int:
        return len(self.timestamp)

    def concat(self, other: Metadata) -> Metadata:
        """This metadata followed by ``other``."""
        return Metadata(
            **{f: np.concatenate([getattr(self, f), getattr(other, f)]) for f in METADATA_FIELDS}
        )

    def row(self, i: int) -> dict[str, Any]:
        """Row ``i`` as plain Python values."""
        return {
            "submap_id": str(self.submap_id[i]),
            "dataset": str(self.dataset[i]),
            "run": str(self.run[i]),
            "timestamp": int(self.timestamp[i]),
            "northing": float(self.northing[i]),
            "easting": float(self.easting[i]),
            "utm_zone": str(self.utm_zone[i]),
            "path": str(self.path[i]),
        }

    def to_bytes(self) -> bytes:
        """Serialise as an ``.npz`` of plain (non-object) arrays: loadable without pickle."""
        buf = io.BytesIO()
        arrays = {f: getattr(self, f) for f in METADATA_FIELDS}
        for name, arr in arrays.items():
            if arr.dtype == object:  # pragma: no cover - from_records never makes these
                raise PnvladError(f"metadata column {name} has dtype object")
        np.savez(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def load(cls, path: str | Path) -> Metadata:
        """Read ``metadata.npz`` (``allow_pickle=False``)."""
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [f for f in METADATA_FIELDS if f not in z.files]
                if missing:
                    raise InputError(f"metadata lacks the columns {missing}", source=path)
                cols = {f: z[f] for f in METADATA_FIELDS}
        except (ValueError, OSError) as exc:
            raise InputError(f"cannot read the metadata: {exc}", source=path) from exc
        n = {len(v) for v in cols.values()}
        if len(n) != 1:
            raise InputError("metadata columns differ in length", source=path)
        return cls(**cols)


# --------------------------------------------------------------------------------------------
# The bundle
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Match:
    """One search result: rank 1 is the nearest; distance is Euclidean in descriptor space."""

    rank: int
    id: int
    submap_id: str
    dataset: str
    run: str
    timestamp: int
    northing: float
    easting: float
    utm_zone: str
    path: str
    distance: float


@dataclass
class IndexBundle:
    """A loaded bundle: the FAISS index, its metadata and manifest, and the submaps' points
    (``geometry``, memory-mapped; ``None`` for a bundle built without them)."""

    path: Path
    index: Any
    metadata: Metadata
    manifest: Manifest
    geometry: BundleGeometry | None = None

    @property
    def dim(self) -> int:
        """Descriptor dimension D."""
        return self.manifest.dim

    @property
    def turns(self) -> int:
        """Vectors an entry has in the index (its headings; see ``MapRecord.turns``)."""
        return self.manifest.map_record.turns

    @property
    def count(self) -> int:
        """Entries (submaps or keyframes) in the map: the index's vectors over ``turns``."""
        return int(self.index.ntotal) // self.turns

    @property
    def key(self) -> str:
        """The FAISS factory key."""
        return self.manifest.index_key

    @property
    def bundle_id(self) -> str:
        """Short identifier: the first 16 hex digits of the index file's sha256."""
        return str(self.manifest.files[INDEX_FILE])[:16]

    @classmethod
    def load(
        cls,
        path: str | Path,
        verify: bool = True,
        *,
        geometry_hash_max_bytes: int = FULL_HASH_MAX_BYTES,
        geometry_sample_rows: int = SAMPLE_ROWS,
    ) -> IndexBundle:
        """Read a bundle; with ``verify`` check every file's sha256 against the manifest.

        The geometry, when the bundle has it, is mapped, not read
        (:meth:`BundleGeometry.open`): its size is always checked, and with ``verify`` its
        table's sha256 and the points file's sha256 when that is at most
        ``geometry_hash_max_bytes``, else ``geometry_sample_rows`` rows' digests."""
        faiss = import_faiss()
        path = Path(path)
        manifest = Manifest.read(path)
        if verify:
            bad = [name for name, ok in manifest.verify_files(path).items() if not ok]
            if bad:
                raise InputError(
                    f"files do not match the manifest's sha256: {bad} (bundle corrupted?)",
                    source=path,
                )
        index = faiss.read_index(str(path / INDEX_FILE))
        apply_search_params(index, manifest.search_params)
        metadata = Metadata.load(path / METADATA_FILE)
        turns = manifest.map_record.turns
        if index.ntotal != len(metadata) * turns or len(metadata) != manifest.count:
            raise InputError(
                f"index has {index.ntotal} vectors ({turns} an entry), metadata "
                f"{len(metadata)} rows, manifest says {manifest.count}",
                source=path,
            )
        if index.d != manifest.dim:
            raise InputError(f"index dimension {index.d} != manifest's {manifest.dim}", path)
        geometry = None
        if manifest.geometry is not None:
            if manifest.geometry.count != manifest.count:
                raise InputError(
                    f"the geometry has {manifest.geometry.count} rows where the index has "
                    f"{manifest.count} vectors",
                    source=path / MANIFEST_FILE,
                )
            geometry = BundleGeometry.open(
                path,
                manifest.geometry,
                verify=verify,
                full_hash_max_bytes=geometry_hash_max_bytes,
                sample_rows=geometry_sample_rows,
            )
        return cls(path, index, metadata, manifest, geometry)

    def search(self, descriptors: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Nearest ``k`` vectors of each row of ``descriptors`` float32 [Q, D].

        Returns Euclidean distances float32 [Q, k'] and entry ids int64 [Q, k'] with
        k' = min(k, count); id -1 marks a missing answer (approximate indexes). An entry
        embedded at several headings (``turns``) counts once, at its nearest.
        """
        q = np.ascontiguousarray(descriptors, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise InputError(f"expected descriptors [Q, {self.dim}], got {q.shape}", "descriptors")
        k = max(1, min(int(k), self.count))
        turns = self.turns
        d2, ids = self.index.search(q, min(k * turns, int(self.index.ntotal)))
        dist = np.sqrt(np.maximum(d2, 0.0)).astype(np.float32)
        if turns == 1:
            return dist, ids
        out_d = np.full((len(q), k), np.inf, dtype=np.float32)
        out_i = np.full((len(q), k), -1, dtype=np.int64)
        for r in range(len(q)):
            seen: set[int] = set()
            n = 0
            for dv, iv in zip(dist[r], ids[r], strict=True):
                entry = int(iv) // turns if iv >= 0 else -1
                if entry < 0 or entry in seen:
                    continue
                seen.add(entry)
                out_d[r, n], out_i[r, n] = dv, entry
                n += 1
                if n == k:
                    break
        return out_d, out_i

    def matches(self, distances: np.ndarray, ids: np.ndarray) -> list[list[Match]]:
        """Search results [Q, k] as :class:`Match` lists, ranks from 1, missing ids dropped."""
        out: list[list[Match]] = []
        for drow, irow in zip(distances, ids, strict=True):
            row: list[Match] = []
            for dist, i in zip(drow, irow, strict=True):
                if i < 0:
                    continue
                row.append(
                    Match(
                        rank=len(row) + 1, id=int(i), distance=float(dist), **self.metadata.row(i)
                    )
                )
            out.append(row)
        return out


def now() -> str:
    """The current UTC time, ISO 8601 to the second (``...+00:00``)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_bundle(
    out: str | Path,
    index: Any,
    metadata: Metadata,
    *,
    index_key: str,
    model: ModelRecord,
    indexed: Sequence[Mapping[str, Any]],
    preprocess: Mapping[str, Any] | None = None,
    search_params: Mapping[str, int] | None = None,
    recall: float | None = None,
    created: str | None = None,
    overwrite: bool = False,
    build: Mapping[str, Any] | None = None,
    extra: Mapping[str, Any] | None = None,
    geometry: Callable[[Path], GeometryRecord] | None = None,
    map_record: MapRecord | None = None,
) -> Manifest:
    """Write index, metadata and manifest to ``out`` atomically; return the manifest.

    ``indexed`` lists what went in (root, layout, datasets, runs, count, added); ``recall``
    is recall@1 against exact search (approximate keys); ``build`` how it was built;
    ``extra`` keys of a manifest read back and kept (see :attr:`Manifest.extra`).
    ``geometry``, when given, writes the geometry files into the temporary bundle directory
    it is passed and returns their record (:class:`~pnvlad_service.index.geometry.GeometryWriter`).
    """
    faiss = import_faiss()
    turns = 1 if map_record is None else map_record.turns
    if index.ntotal != len(metadata) * turns:
        raise PnvladError(
            f"index has {index.ntotal} vectors, metadata {len(metadata)} rows ({turns} an entry)"
        )
    with atomic_directory(out, overwrite=overwrite) as tmp:
        faiss.write_index(index, str(tmp / INDEX_FILE))
        atomic_write_bytes(tmp / METADATA_FILE, metadata.to_bytes())
        geo = None if geometry is None else geometry(tmp)
        if geo is not None and geo.count != len(metadata):
            raise PnvladError(f"geometry has {geo.count} rows, the metadata {len(metadata)}")
        manifest = Manifest(
            format=FORMAT,
            version=format_version(map_record),
            dim=int(index.d),
            metric="l2",
            distance="euclidean",
            index_key=index_key,
            count=len(metadata),
            search_params=search_params or {},
            recall_at_1_vs_exact=recall,
            model=model,
            preprocess=preprocess,
            indexed=tuple(indexed),
            created=created or now(),
            modified=now(),
            files={
                INDEX_FILE: sha256_file(tmp / INDEX_FILE),
                METADATA_FILE: sha256_file(tmp / METADATA_FILE),
            },
            build=build,
            geometry=geo,
            map=map_record,
            extra=extra or {},
            path=Path(out),
        )
        text = json.dumps(manifest.to_json(), indent=2) + "\n"
        atomic_write_text(tmp / MANIFEST_FILE, text)
    log.info("wrote index bundle %s: %s, %d vectors", out, index_key, manifest.count)
    if manifest.geometry is not None:
        g = manifest.geometry
        log.info("geometry: %d submaps, %.1f KB each", g.count, g.bytes / max(g.count, 1) / 1e3)
    return manifest
