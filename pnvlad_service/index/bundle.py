"""FAISS index bundles: the map a localisation service searches.

A bundle is a directory written atomically (:func:`pnvlad_service.fileio.atomic_directory`)::

    <bundle>/index.faiss     the FAISS index, descriptors float32 [N, D], metric L2
    <bundle>/metadata.npz    one row per vector (no pickle): submap_id, dataset, run,
                             timestamp (int64 µs), northing, easting (float64, UTM metres),
                             utm_zone ("" when unknown), path (relative to the benchmark root)
    <bundle>/manifest.json   format, version, dim, metric, index key, count, model identity
                             (weights and config sha256), file sha256s, creation time, what was
                             indexed, the preprocessing config (filter G) and search parameters

Vector ``i`` of the index is row ``i`` of the metadata. Distances returned by
:meth:`IndexBundle.search` are Euclidean (not squared) descriptor distances.

``torch`` and ``faiss`` are imported inside the functions that need them.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import io
import json
import logging
import math
import os
import re
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from pnvlad_service.errors import InputError, MissingDependencyError, PnvladError
from pnvlad_service.fileio import atomic_directory, atomic_write_bytes, atomic_write_text

if TYPE_CHECKING:
    import faiss

log = logging.getLogger(__name__)

FORMAT = "pnvlad-index"
VERSION = 1
INDEX_FILE = "index.faiss"
METADATA_FILE = "metadata.npz"
MANIFEST_FILE = "manifest.json"

#: Points in one benchmark submap.
SUBMAP_POINTS = 4096

#: Exact search up to this many vectors (FAISS guidelines: Flat below about 1e5 to 1e6).
FLAT_MAX_VECTORS = 100_000
#: Above this many vectors ``auto`` picks OPQ + IVF + PQ (FAISS guidelines: 1e7 and beyond).
OPQ_MIN_VECTORS = 10_000_000
#: Neighbours per node of the HNSW graph that ``auto`` picks.
HNSW_M = 32
#: Default memory budget of ``auto``: 8 GiB.
DEFAULT_MEMORY_BUDGET = 8 * 1024**3

#: Default search-time parameters, applied on load (efSearch for HNSW, nprobe for IVF).
DEFAULT_EF_SEARCH = 128
DEFAULT_NPROBE = 32

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


class Embedder(Protocol):
    """What the index needs from an encoder (``models.inference.Encoder`` fits)."""

    dim: int

    def embed(self, points: np.ndarray) -> np.ndarray:
        """float [B, N, 3] -> float32 [B, dim], rows of unit L2 norm."""
        ...


def _faiss() -> Any:
    try:
        import faiss
    except ImportError as exc:  # pragma: no cover - faiss-cpu is a core dependency
        raise MissingDependencyError("faiss-cpu", "index", "the FAISS index") from exc
    return faiss


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# Metadata
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SubmapRecord:
    """One database submap: where it is (UTM metres) and where its file lies."""

    dataset: str
    run: str
    timestamp: int
    northing: float
    easting: float
    path: str
    utm_zone: str = ""

    @property
    def submap_id(self) -> str:
        """``dataset/run/timestamp``: unique within a benchmark tree."""
        return f"{self.dataset}/{self.run}/{self.timestamp}"


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
    def from_records(cls, records: Sequence[SubmapRecord]) -> Metadata:
        """Columns from records (order kept)."""
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
# Benchmark trees: which submaps go into the database
# --------------------------------------------------------------------------------------------


def list_database_submaps(
    root: str | Path,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
) -> list[SubmapRecord]:
    """Every submap of role ``layout`` ("test": ``pointcloud_20m`` / ``pointcloud_25m_25``;
    "train": the 10 m ones) of the benchmark tree at ``root``.

    ``datasets`` and ``runs`` restrict by folder name. Order: datasets and runs sorted, CSV
    rows in file order (:class:`pnvlad_service.data.tree.BenchmarkTree`'s order). Raises
    :class:`InputError` when nothing matches or a named run is missing.
    """
    from pnvlad_service.data.tree import BenchmarkTree

    if layout not in ("test", "train"):
        raise InputError(f"layout must be 'test' or 'train', got {layout!r}", "layout")
    tree = BenchmarkTree(root)
    wanted_runs = set(runs) if runs else None
    seen_runs: set[str] = set()
    records: list[SubmapRecord] = []
    for dataset in tree.datasets:
        if datasets and dataset not in datasets:
            continue
        for run in tree.runs(dataset):
            if wanted_runs is not None and run not in wanted_runs:
                continue
            if not tree.has(dataset, run, layout):  # type: ignore[arg-type]
                continue
            seen_runs.add(run)
            records.extend(
                SubmapRecord(s.dataset, s.run, s.timestamp, s.northing, s.easting, s.path)
                for s in tree.submaps(dataset, run, layout)  # type: ignore[arg-type]
            )
    if wanted_runs is not None and wanted_runs - seen_runs:
        raise InputError(f"runs not found: {sorted(wanted_runs - seen_runs)}", source=root)
    if not records:
        raise InputError(f"no {layout}-layout submaps found", source=root)
    return records


def read_submap(path: str | Path) -> np.ndarray:
    """A benchmark submap file: float64 [4096, 3] (``.bin``: no header, 98,304 bytes)."""
    from pnvlad_service.io.readers import read_points

    return read_points(path, "benchmark")


def embed_submaps(
    encoder: Embedder,
    root: str | Path,
    records: Sequence[SubmapRecord],
    batch_size: int = 32,
    progress: bool = True,
) -> np.ndarray:
    """Descriptors of ``records`` in order: float32 [len(records), encoder.dim]."""
    from tqdm import tqdm

    root = Path(root)
    out = np.empty((len(records), encoder.dim), dtype=np.float32)
    with tqdm(total=len(records), unit="submap", disable=not progress, desc="embedding") as bar:
        for start in range(0, len(records), batch_size):
            chunk = records[start : start + batch_size]
            pts = np.stack([read_submap(root / r.path) for r in chunk]).astype(np.float32)
            out[start : start + len(chunk)] = encoder.embed(pts)
            bar.update(len(chunk))
    return out


# --------------------------------------------------------------------------------------------
# Choosing and making a FAISS index
# --------------------------------------------------------------------------------------------


def ivf_lists(n: int) -> int:
    """Inverted lists for ``n`` vectors: the power of two nearest 8·√n (so within 4√n..16√n),
    lowered to a power of two of at most n / 39 (FAISS wants 39 training points a list)."""
    k = 2 ** round(math.log2(8.0 * math.sqrt(max(n, 1))))
    cap = max(1, n // 39)
    while k > cap:
        k //= 2
    return int(k)


def pq_subquantizers(d: int, n: int, memory_budget: int) -> int:
    """Bytes per PQ code: the largest of 64, 32, 16, 8, 4 dividing ``d`` that fits the budget
    (``n`` codes plus 8-byte ids), else the smallest that divides ``d``."""
    divisors = [m for m in (64, 32, 16, 8, 4) if m <= d and d % m == 0] or [1]
    for m in divisors:
        if n * (m + 8) <= memory_budget:
            return m
    return divisors[-1]


def choose_index_key(n: int, d: int, memory_budget: int = DEFAULT_MEMORY_BUDGET) -> str:
    """The FAISS factory key ``auto`` picks for ``n`` vectors of dimension ``d``.

    Following the FAISS guidelines: ``Flat`` (exact) up to :data:`FLAT_MAX_VECTORS` when its
    4·d bytes a vector fit the budget; below :data:`OPQ_MIN_VECTORS`, ``HNSW32`` when its
    4·d + 8·32 bytes a vector fit, else ``IVFK,Flat`` (K from :func:`ivf_lists`) when 4·d + 8
    fit, else ``IVFK,PQm``; from :data:`OPQ_MIN_VECTORS` on, ``OPQm,IVFK,PQm``.
    ``memory_budget`` is in bytes.
    """
    if n < 1 or d < 1:
        raise InputError(f"need at least one vector of dimension >= 1, got n={n}, d={d}", "n")
    flat = n * 4 * d
    hnsw = n * (4 * d + 8 * HNSW_M)
    k = ivf_lists(n)
    m = pq_subquantizers(d, n, memory_budget)
    if n <= FLAT_MAX_VECTORS and flat <= memory_budget:
        return "Flat"
    if n < OPQ_MIN_VECTORS:
        if hnsw <= memory_budget:
            return f"HNSW{HNSW_M}"
        if n * (4 * d + 8) <= memory_budget:
            return f"IVF{k},Flat"
        return f"IVF{k},PQ{m}"
    return f"OPQ{m},IVF{k},PQ{m}"


_IVF_RE = re.compile(r"IVF(\d+)")
_PQ_RE = re.compile(r"(?<!O)PQ(\d+)(?:x(\d+))?")


def min_training_vectors(key: str) -> int:
    """Fewest vectors an index of ``key`` can be trained on (K for IVF, 2^nbits for PQ)."""
    need = 1
    if m := _IVF_RE.search(key):
        need = max(need, int(m.group(1)))
    if m := _PQ_RE.search(key):
        need = max(need, 2 ** int(m.group(2) or 8))
    return need


def is_exact(key: str) -> bool:
    """Whether ``key`` is exhaustive exact search."""
    return key.replace(" ", "") in {"Flat", "IDMap,Flat"}


def make_index(
    descriptors: np.ndarray, key: str, seed: int = 0, max_train: int = 200_000
) -> faiss.Index:
    """Build (train when needed, then fill) a FAISS index of ``descriptors`` float32 [N, D].

    Raises :class:`InputError` for an unknown key or too few vectors to train it.
    """
    faiss = _faiss()
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n, d = x.shape
    try:
        index = faiss.index_factory(d, key, faiss.METRIC_L2)
    except RuntimeError as exc:
        raise InputError(f"FAISS cannot make an index from {key!r}: {exc}", "index_key") from exc
    _no_polysemous(index)
    if not index.is_trained:
        need = min_training_vectors(key)
        if n < need:
            raise InputError(
                f"{key} needs at least {need} vectors to train, the map has {n}; "
                "use Flat or fewer lists",
                "index_key",
            )
        rng = np.random.default_rng(seed)
        train = x if n <= max_train else x[np.sort(rng.choice(n, max_train, replace=False))]
        index.train(train)
    index.add(x)
    return index


def _no_polysemous(index: Any) -> None:
    """Switch off polysemous training, which index_factory turns on for IVF-PQ: it costs
    minutes of training and is only used by polysemous (Hamming) search, which we never do."""
    faiss = _faiss()
    try:
        ivf = faiss.downcast_index(faiss.extract_index_ivf(index))
    except (RuntimeError, AttributeError):
        return
    if hasattr(ivf, "do_polysemous_training"):
        ivf.do_polysemous_training = False


def default_search_params(key: str) -> dict[str, int]:
    """efSearch for HNSW, nprobe for IVF (capped at the number of lists)."""
    params: dict[str, int] = {}
    if "HNSW" in key:
        params["efSearch"] = DEFAULT_EF_SEARCH
    if m := _IVF_RE.search(key):
        params["nprobe"] = min(int(m.group(1)), DEFAULT_NPROBE)
    return params


def apply_search_params(index: faiss.Index, params: dict[str, int]) -> None:
    """Set search-time parameters (``efSearch``, ``nprobe``) on any wrapped index."""
    faiss = _faiss()
    ps = faiss.ParameterSpace()
    for name, value in params.items():
        ps.set_index_parameter(index, name, value)


def recall_at_1(
    index: faiss.Index, descriptors: np.ndarray, sample: int = 1000, seed: int = 0
) -> float:
    """Share of sampled database vectors whose top-1 under ``index`` is their exact top-1.

    A tie (same distance as the exact neighbour, e.g. a duplicate vector) counts as a hit.
    """
    faiss = _faiss()
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n = len(x)
    rng = np.random.default_rng(seed)
    q = x[np.sort(rng.choice(n, min(sample, n), replace=False))]
    exact = faiss.IndexFlatL2(x.shape[1])
    exact.add(x)
    d_ex, i_ex = exact.search(q, 1)
    _, i_ap = index.search(q, 1)
    ok = i_ap[:, 0] == i_ex[:, 0]
    # Distances of the approximate answers, computed exactly, for ties.
    valid = i_ap[:, 0] >= 0
    d_ap = np.full(len(q), np.inf, dtype=np.float32)
    d_ap[valid] = ((x[i_ap[valid, 0]] - q[valid]) ** 2).sum(1)
    ok |= d_ap <= d_ex[:, 0] + 1e-6
    return float(ok.mean())


# --------------------------------------------------------------------------------------------
# Model identity
# --------------------------------------------------------------------------------------------


def model_identity(checkpoint: str | Path) -> dict[str, Any]:
    """``{"checkpoint", "weights_sha256", "config_sha256", "config"}`` of a checkpoint dir."""
    from pnvlad_service.models import store

    checkpoint = Path(checkpoint)
    cfg, _ = store.read_model_json(checkpoint)
    return {
        "checkpoint": str(checkpoint.resolve()),
        "weights_sha256": store.weights_sha256(checkpoint),
        "config_sha256": store.config_sha256(cfg),
        "config": cfg.model_dump(mode="json"),
    }


class _ModelEmbedder:
    """Plain wrapper of ``store.load_model`` used where ``models.inference`` is absent."""

    def __init__(self, checkpoint: Path, device: str | None) -> None:
        from pnvlad_service.models import store

        self.model, self.cfg = store.load_model(checkpoint, device=device)
        self.dim = int(self.cfg.output_dim)
        self.device = device or "cpu"

    def embed(self, points: np.ndarray) -> np.ndarray:
        import torch

        x = np.asarray(points, dtype=np.float32)
        if x.ndim == 2:
            x = x[None]
        with torch.inference_mode():
            return self.model(torch.from_numpy(x).to(self.device)).cpu().numpy()


def load_encoder(checkpoint: str | Path, device: str | None = None) -> Any:
    """The encoder of a checkpoint directory (``models.inference.Encoder`` when available)."""
    checkpoint = Path(checkpoint)
    if not checkpoint.is_dir():
        raise InputError("checkpoint directory not found", source=checkpoint)
    try:
        from pnvlad_service.models.inference import Encoder
    except ImportError:
        log.debug("models.inference not available; using the plain model")
        return _ModelEmbedder(checkpoint, device)
    return Encoder.from_checkpoint(checkpoint, device=device)


def default_preprocess_config() -> dict[str, Any] | None:
    """The default filter G configuration as JSON, or ``None`` if preprocess is missing."""
    try:
        from pnvlad_service.data.preprocess import GConfig
    except ImportError:  # pragma: no cover - depends on the data engineers' module
        return None
    return GConfig().model_dump(mode="json")


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
    """A loaded bundle: the FAISS index, its metadata and manifest."""

    path: Path
    index: Any
    metadata: Metadata
    manifest: dict[str, Any]

    @property
    def dim(self) -> int:
        return int(self.manifest["dim"])

    @property
    def count(self) -> int:
        return int(self.index.ntotal)

    @property
    def key(self) -> str:
        return str(self.manifest["index_key"])

    @property
    def bundle_id(self) -> str:
        """Short identifier: the first 16 hex digits of the index file's sha256."""
        return str(self.manifest["files"][INDEX_FILE])[:16]

    @classmethod
    def load(cls, path: str | Path, verify: bool = True) -> IndexBundle:
        """Read a bundle; with ``verify`` check every file's sha256 against the manifest."""
        faiss = _faiss()
        path = Path(path)
        manifest = read_manifest(path)
        if verify:
            bad = [name for name, ok in verify_bundle(path, manifest).items() if not ok]
            if bad:
                raise InputError(
                    f"files do not match the manifest's sha256: {bad} (bundle corrupted?)",
                    source=path,
                )
        index = faiss.read_index(str(path / INDEX_FILE))
        apply_search_params(index, manifest.get("search_params", {}))
        metadata = Metadata.load(path / METADATA_FILE)
        if index.ntotal != len(metadata) or index.ntotal != manifest["count"]:
            raise InputError(
                f"index has {index.ntotal} vectors, metadata {len(metadata)} rows, "
                f"manifest says {manifest['count']}",
                source=path,
            )
        if index.d != manifest["dim"]:
            raise InputError(
                f"index dimension {index.d} != manifest's {manifest['dim']}", source=path
            )
        return cls(path, index, metadata, manifest)

    def search(self, descriptors: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Nearest ``k`` vectors of each row of ``descriptors`` float32 [Q, D].

        Returns Euclidean distances float32 [Q, k'] and ids int64 [Q, k'] with
        k' = min(k, count); id -1 marks a missing answer (approximate indexes).
        """
        q = np.ascontiguousarray(descriptors, dtype=np.float32)
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise InputError(f"expected descriptors [Q, {self.dim}], got {q.shape}", "descriptors")
        k = max(1, min(int(k), self.count))
        d2, ids = self.index.search(q, k)
        return np.sqrt(np.maximum(d2, 0.0)).astype(np.float32), ids

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


def read_manifest(path: str | Path) -> dict[str, Any]:
    """``manifest.json`` of a bundle directory, checked for format and version."""
    path = Path(path)
    mpath = path / MANIFEST_FILE
    if not path.is_dir():
        raise InputError("index bundle directory not found", source=path)
    if not mpath.is_file():
        raise InputError("not an index bundle (no manifest.json)", source=path)
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(f"manifest is not valid JSON: {exc}", source=mpath) from exc
    if manifest.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} manifest", source=mpath)
    if manifest.get("version") != VERSION:
        raise InputError(
            f"bundle format version {manifest.get('version')} is not supported (want {VERSION})",
            source=mpath,
        )
    return manifest


def verify_bundle(path: str | Path, manifest: dict[str, Any] | None = None) -> dict[str, bool]:
    """``{file name: sha256 matches}`` for every file the manifest lists."""
    path = Path(path)
    manifest = manifest or read_manifest(path)
    result: dict[str, bool] = {}
    for name, digest in manifest.get("files", {}).items():
        f = path / name
        result[name] = f.is_file() and sha256_file(f) == digest
    return result


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_bundle(
    out: str | Path,
    index: Any,
    metadata: Metadata,
    *,
    index_key: str,
    model: dict[str, Any],
    indexed: list[dict[str, Any]],
    preprocess: dict[str, Any] | None = None,
    search_params: dict[str, int] | None = None,
    recall: float | None = None,
    created: str | None = None,
    overwrite: bool = False,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write index, metadata and manifest to ``out`` atomically; return the manifest.

    ``model`` is :func:`model_identity`'s dict; ``indexed`` lists what went in (root, layout,
    datasets, runs, count); ``recall`` is recall@1 against exact search (approximate keys).
    """
    faiss = _faiss()
    if index.ntotal != len(metadata):
        raise PnvladError(f"index has {index.ntotal} vectors, metadata {len(metadata)} rows")
    with atomic_directory(out, overwrite=overwrite) as tmp:
        faiss.write_index(index, str(tmp / INDEX_FILE))
        atomic_write_bytes(tmp / METADATA_FILE, metadata.to_bytes())
        manifest: dict[str, Any] = {
            "format": FORMAT,
            "version": VERSION,
            "dim": int(index.d),
            "metric": "l2",
            "distance": "euclidean",
            "index_key": index_key,
            "count": int(index.ntotal),
            "search_params": search_params or {},
            "recall_at_1_vs_exact": recall,
            "model": model,
            "preprocess": preprocess,
            "indexed": indexed,
            "created": created or _now(),
            "modified": _now(),
            "files": {
                INDEX_FILE: sha256_file(tmp / INDEX_FILE),
                METADATA_FILE: sha256_file(tmp / METADATA_FILE),
            },
        }
        if extra:
            manifest.update(extra)
        atomic_write_text(tmp / MANIFEST_FILE, json.dumps(manifest, indent=2) + "\n")
    log.info("wrote index bundle %s: %s, %d vectors", out, index_key, manifest["count"])
    return manifest


@dataclass
class BuildReport:
    """What a build did: counts, timings (seconds), throughput (clouds/s), recall@1."""

    path: Path | None
    count: int
    index_key: str
    embed_seconds: float
    index_seconds: float
    clouds_per_second: float
    recall_at_1: float | None
    manifest: dict[str, Any] = field(default_factory=dict)


@contextlib.contextmanager
def _maybe_distributed() -> Iterator[tuple[int, int]]:
    """(rank, world size) under ``torchrun`` (gloo process group), else (0, 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        yield 0, 1
        return
    import torch.distributed as dist

    created = False
    if not dist.is_initialized():
        dist.init_process_group("gloo")
        created = True
    try:
        yield dist.get_rank(), dist.get_world_size()
    finally:
        if created:
            dist.barrier()
            dist.destroy_process_group()


def _embed_sharded(
    encoder: Embedder,
    root: Path,
    records: Sequence[SubmapRecord],
    batch_size: int,
    progress: bool,
    rank: int,
    world: int,
) -> np.ndarray | None:
    """Rank ``rank`` embeds its contiguous shard; rank 0 gets all descriptors in order."""
    if world == 1:
        return embed_submaps(encoder, root, records, batch_size, progress)
    import torch
    import torch.distributed as dist

    n = len(records)
    bounds = [n * r // world for r in range(world + 1)]
    mine = embed_submaps(
        encoder, root, records[bounds[rank] : bounds[rank + 1]], batch_size, progress and rank == 0
    )
    width = max(bounds[r + 1] - bounds[r] for r in range(world))
    padded = torch.zeros((width, encoder.dim), dtype=torch.float32)
    padded[: len(mine)] = torch.from_numpy(mine)
    gathered = [torch.zeros_like(padded) for _ in range(world)] if rank == 0 else None
    dist.gather(padded, gathered, dst=0)
    if rank != 0:
        return None
    assert gathered is not None
    return np.concatenate(
        [gathered[r][: bounds[r + 1] - bounds[r]].numpy() for r in range(world)]
    ).astype(np.float32)


def build_bundle(
    out: str | Path,
    checkpoint: str | Path,
    root: str | Path,
    *,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
    index_key: str = "Flat",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    batch_size: int = 32,
    recall_sample: int = 1000,
    overwrite: bool = False,
    progress: bool = True,
    encoder: Embedder | None = None,
    preprocess: dict[str, Any] | None = None,
) -> BuildReport:
    """Embed every ``layout`` submap of the tree at ``root`` and write a bundle to ``out``.

    ``index_key`` is a FAISS factory string or ``"auto"`` (:func:`choose_index_key`).
    Under ``torchrun`` (``WORLD_SIZE`` > 1) each rank embeds a contiguous shard, rank 0
    gathers them (gloo) and writes the same bundle a single process would; other ranks
    return a report with ``path=None``. ``encoder`` defaults to the checkpoint's.
    """
    out = Path(out)
    root = Path(root)
    if out.exists() and not overwrite:
        raise InputError("bundle already exists (use --overwrite to replace it)", source=out)
    records = list_database_submaps(root, datasets, runs, layout)
    model = model_identity(checkpoint)
    enc = encoder if encoder is not None else load_encoder(checkpoint)
    with _maybe_distributed() as (rank, world):
        t0 = time.perf_counter()
        desc = _embed_sharded(enc, root, records, batch_size, progress, rank, world)
        t_embed = time.perf_counter() - t0
        if desc is None:
            return BuildReport(None, len(records), index_key, t_embed, 0.0, 0.0, None)
        return _finish_build(
            out,
            desc,
            records,
            model=model,
            root=root,
            layout=layout,
            index_key=index_key,
            memory_budget=memory_budget,
            recall_sample=recall_sample,
            overwrite=overwrite,
            t_embed=t_embed,
            preprocess=preprocess if preprocess is not None else default_preprocess_config(),
            world=world,
        )


def _indexed_entry(root: Path, layout: str, records: Sequence[SubmapRecord]) -> dict[str, Any]:
    return {
        "root": str(root.resolve()),
        "layout": layout,
        "datasets": sorted({r.dataset for r in records}),
        "runs": sorted({r.run for r in records}),
        "count": len(records),
        "added": _now(),
    }


def _finish_build(
    out: Path,
    desc: np.ndarray,
    records: Sequence[SubmapRecord],
    *,
    model: dict[str, Any],
    root: Path,
    layout: str,
    index_key: str,
    memory_budget: int,
    recall_sample: int,
    overwrite: bool,
    t_embed: float,
    preprocess: dict[str, Any] | None,
    world: int,
) -> BuildReport:
    if index_key == "auto":
        index_key = choose_index_key(len(desc), desc.shape[1], memory_budget)
        log.info("index key auto -> %s (%d vectors, d=%d)", index_key, *desc.shape)
    t1 = time.perf_counter()
    index = make_index(desc, index_key)
    params = default_search_params(index_key)
    apply_search_params(index, params)
    t_index = time.perf_counter() - t1
    recall = None if is_exact(index_key) else recall_at_1(index, desc, recall_sample)
    if recall is not None:
        log.info("recall@1 of %s against exact search: %.4f", index_key, recall)
    rate = len(desc) / t_embed if t_embed > 0 else float("inf")
    manifest = write_bundle(
        out,
        index,
        Metadata.from_records(records),
        index_key=index_key,
        model=model,
        indexed=[_indexed_entry(root, layout, records)],
        preprocess=preprocess,
        search_params=params,
        recall=recall,
        overwrite=overwrite,
        extra={"build": {"processes": world, "embed_seconds": round(t_embed, 3)}},
    )
    return BuildReport(out, len(desc), index_key, t_embed, t_index, rate, recall, manifest)


def add_to_bundle(
    bundle_dir: str | Path,
    checkpoint: str | Path,
    root: str | Path,
    *,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
    batch_size: int = 32,
    progress: bool = True,
    encoder: Embedder | None = None,
) -> BuildReport:
    """Append the submaps of new runs to an existing bundle (rewritten atomically).

    Refuses a checkpoint whose weights differ from the bundle's, and submaps already in it.
    """
    bundle_dir = Path(bundle_dir)
    root = Path(root)
    bundle = IndexBundle.load(bundle_dir)
    model = model_identity(checkpoint)
    if model["weights_sha256"] != bundle.manifest["model"]["weights_sha256"]:
        raise InputError(
            f"the checkpoint {checkpoint} has other weights than the ones the bundle "
            f"{bundle_dir} was built with (sha256 {model['weights_sha256'][:12]}… vs "
            f"{bundle.manifest['model']['weights_sha256'][:12]}…)",
            source=checkpoint,
        )
    records = list_database_submaps(root, datasets, runs, layout)
    present = set(bundle.metadata.submap_id.tolist())
    dup = [r.submap_id for r in records if r.submap_id in present]
    if dup:
        raise InputError(
            f"{len(dup)} submaps are already in the bundle, e.g. {dup[0]}", source=bundle_dir
        )
    enc = encoder if encoder is not None else load_encoder(checkpoint)
    t0 = time.perf_counter()
    desc = embed_submaps(enc, root, records, batch_size, progress)
    t_embed = time.perf_counter() - t0
    t1 = time.perf_counter()
    bundle.index.add(np.ascontiguousarray(desc, dtype=np.float32))
    t_index = time.perf_counter() - t1
    m = bundle.manifest
    manifest = write_bundle(
        bundle_dir,
        bundle.index,
        bundle.metadata.concat(Metadata.from_records(records)),
        index_key=m["index_key"],
        model=m["model"],
        indexed=[*m.get("indexed", []), _indexed_entry(root, layout, records)],
        preprocess=m.get("preprocess"),
        search_params=m.get("search_params"),
        recall=m.get("recall_at_1_vs_exact"),
        created=m.get("created"),
        overwrite=True,
        extra={k: v for k, v in m.items() if k == "build"},
    )
    rate = len(desc) / t_embed if t_embed > 0 else float("inf")
    return BuildReport(
        bundle_dir, len(records), m["index_key"], t_embed, t_index, rate, None, manifest
    )
