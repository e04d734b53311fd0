"""The localisation service behind the HTTP layer: model, index, parsing and batching.

:func:`parse_json_query`, :func:`parse_binary_points` and :func:`parse_npy` turn request bodies
into point arrays and raise :class:`~pnvlad_service.errors.InputError` naming the field;
:class:`Localizer` loads the checkpoint and the bundle once, checks that the bundle was built
with these weights, runs the filter G on raw scans and answers queries via a
:class:`~pnvlad_service.localization.batching.MicroBatcher`.
"""

from __future__ import annotations

import io
import json
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.index.build import load_encoder
from pnvlad_service.index.bundle import IndexBundle
from pnvlad_service.index.manifest import Manifest
from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.localization.batching import BatchResult, MicroBatcher
from pnvlad_service.server.settings import ServerSettings

log = logging.getLogger(__name__)

#: Slack on the [-1, 1] bound of preprocessed points.
_BOUND = 1.0 + 1e-4
#: Largest |coordinate| of a raw scan, metres (sensor frame): far beyond any LiDAR's range,
#: and it keeps overflowing values (1e308) away from the filter G's plane fits.
MAX_RAW_COORD = 100_000.0


class MalformedJSON(InputError):
    """The body is not JSON at all (400 rather than 422)."""

    problem_kind = "malformed-json"


# --------------------------------------------------------------------------------------------
# Parsing request bodies
# --------------------------------------------------------------------------------------------


def check_points(
    points: np.ndarray, preprocess: bool, field: str, max_raw_points: int
) -> np.ndarray:
    """Validate a query cloud; return float32 [4096, 3] (or float64 [N, 3] when raw).

    Preprocessed clouds must hold exactly 4096 finite points inside [-1, 1]; raw scans
    (``preprocess``) between 1 and ``max_raw_points`` finite points.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"expected an array of [x, y, z] points, got shape {points.shape}", field)
    n = len(points)
    if not np.isfinite(points).all():
        bad = int(np.argwhere(~np.isfinite(points))[0][0])
        raise InputError(f"point {bad} has a NaN or infinite coordinate", f"{field}[{bad}]")
    if preprocess:
        if n < 1 or n > max_raw_points:
            raise InputError(
                f"a raw scan needs between 1 and {max_raw_points} points, got {n}", field
            )
        out64 = np.ascontiguousarray(points, dtype=np.float64)
        far = np.abs(out64).max(axis=1) > MAX_RAW_COORD
        if far.any():
            bad = int(np.argmax(far))
            raise InputError(
                f"point {bad} is more than {MAX_RAW_COORD:,.0f} m from the sensor: raw scans are "
                "in the sensor frame, metres",
                f"{field}[{bad}]",
            )
        return out64
    if n != SUBMAP_POINTS:
        raise InputError(
            f"expected exactly {SUBMAP_POINTS} preprocessed points, got {n} "
            "(send a raw scan with preprocess=true)",
            field,
        )
    out = np.ascontiguousarray(points, dtype=np.float32)
    if np.abs(out).max() > _BOUND:
        bad = int(np.argwhere(np.abs(out) > _BOUND)[0][0])
        raise InputError(
            f"point {bad} lies outside [-1, 1]: preprocessed points are in the benchmark's "
            "normalised frame (send a raw scan with preprocess=true)",
            f"{field}[{bad}]",
        )
    return out


def _points_from_json(value: Any, field: str) -> np.ndarray:
    if not isinstance(value, list):
        raise InputError(f"expected a list of [x, y, z] points, got {type(value).__name__}", field)
    if not value:
        raise InputError("expected at least one point, got an empty list", field)
    for i, p in enumerate(value):
        if not isinstance(p, list) or len(p) != 3:
            what = f"{len(p)} values" if isinstance(p, list) else type(p).__name__
            raise InputError(f"point {i} must be [x, y, z], got {what}", f"{field}[{i}]")
        for c in p:
            if isinstance(c, bool) or not isinstance(c, (int, float)):
                raise InputError(f"point {i} has a non-numeric coordinate {c!r}", f"{field}[{i}]")
    try:
        return np.asarray(value, dtype=np.float64)
    except OverflowError as exc:
        raise InputError(f"a coordinate is out of range: {exc}", field) from None


def _int_field(obj: dict[str, Any], name: str, default: int, lo: int, hi: int) -> int:
    v = obj.get(name, default)
    if isinstance(v, bool) or not isinstance(v, int):
        raise InputError(f"expected an integer, got {json.dumps(v)[:40]}", name)
    if not lo <= v <= hi:
        raise InputError(f"must be between {lo} and {hi}, got {v}", name)
    return v


def _bool_field(obj: dict[str, Any], name: str, default: bool) -> bool:
    v = obj.get(name, default)
    if not isinstance(v, bool):
        raise InputError(f"expected true or false, got {json.dumps(v)[:40]}", name)
    return v


def _loads(body: bytes) -> Any:
    try:
        return json.loads(body)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise MalformedJSON(f"body is not valid JSON: {exc}", "body") from None


def _check_keys(obj: Any, allowed: set[str], where: str) -> dict[str, Any]:
    if not isinstance(obj, dict):
        raise InputError(f"expected a JSON object, got {type(obj).__name__}", where)
    extra = sorted(set(obj) - allowed)
    if extra:
        raise InputError(f"unknown fields {extra}; allowed: {sorted(allowed)}", where)
    return obj


def parse_json_query(
    body: bytes, max_top_n: int, max_raw_points: int
) -> tuple[np.ndarray, int, bool]:
    """``{"points": [[x, y, z], ...], "top_n": 5, "preprocess": false}`` -> (points, top_n,
    preprocess); points as :func:`check_points` returns them."""
    obj = _check_keys(_loads(body), {"points", "top_n", "preprocess"}, "body")
    if "points" not in obj:
        raise InputError("field required", "points")
    top_n = _int_field(obj, "top_n", 5, 1, max_top_n)
    preprocess = _bool_field(obj, "preprocess", False)
    pts = check_points(
        _points_from_json(obj["points"], "points"), preprocess, "points", max_raw_points
    )
    return pts, top_n, preprocess


def parse_json_batch(
    body: bytes, max_top_n: int, max_raw_points: int, max_queries: int
) -> tuple[list[tuple[np.ndarray, bool]], int]:
    """``{"queries": [{"points": ..., "preprocess": false}, ...], "top_n": 5}``."""
    obj = _check_keys(_loads(body), {"queries", "top_n"}, "body")
    if "queries" not in obj:
        raise InputError("field required", "queries")
    top_n = _int_field(obj, "top_n", 5, 1, max_top_n)
    queries = obj["queries"]
    if not isinstance(queries, list) or not 1 <= len(queries) <= max_queries:
        n = len(queries) if isinstance(queries, list) else type(queries).__name__
        raise InputError(f"expected a list of 1 to {max_queries} queries, got {n}", "queries")
    out = []
    for i, q in enumerate(queries):
        q = _check_keys(q, {"points", "preprocess"}, f"queries[{i}]")
        if "points" not in q:
            raise InputError("field required", f"queries[{i}].points")
        pre = _bool_field(q, "preprocess", False)
        field = f"queries[{i}].points"
        out.append(
            (check_points(_points_from_json(q["points"], field), pre, field, max_raw_points), pre)
        )
    return out, top_n


_DTYPES = {"float32": "<f4", "float64": "<f8", "f4": "<f4", "f8": "<f8"}


def parse_binary_points(body: bytes, dtype: str) -> np.ndarray:
    """Interleaved little-endian xyz of ``dtype`` (float32 or float64) -> [N, 3]."""
    if dtype not in _DTYPES:
        raise InputError(f"dtype must be float32 or float64, got {dtype!r}", "dtype")
    dt = np.dtype(_DTYPES[dtype])
    step = 3 * dt.itemsize
    if not body or len(body) % step:
        raise InputError(
            f"{len(body)} bytes is not a whole, non-zero number of {dtype} xyz triples "
            f"({step} bytes each)",
            "body",
        )
    return np.frombuffer(body, dtype=dt).reshape(-1, 3)


def parse_npy(body: bytes, ndim: int) -> np.ndarray:
    """An ``.npy`` file (float32/float64, no pickle) of ``ndim`` dimensions, last of size 3."""
    try:
        arr = np.load(io.BytesIO(body), allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"not a readable .npy array: {exc}", "body") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f":
        raise InputError(
            f"expected a float32 or float64 array, got {getattr(arr, 'dtype', '?')}", "body"
        )
    if arr.ndim != ndim or arr.shape[-1] != 3:
        want = "[N, 3]" if ndim == 2 else "[B, N, 3]"
        raise InputError(f"expected an array of shape {want}, got {arr.shape}", "body")
    return arr


# --------------------------------------------------------------------------------------------
# The service
# --------------------------------------------------------------------------------------------


def resolve_checkpoint(settings: ServerSettings) -> Path:
    """The checkpoint to load: the one given, else the one the bundle records."""
    if settings.index is None:
        raise InputError("no index bundle given (--index or PNVLAD_INDEX)", "index")
    if settings.checkpoint is not None:
        return Path(settings.checkpoint)
    recorded = Manifest.read(settings.index).model.checkpoint
    if not recorded:
        raise InputError("the bundle records no checkpoint; pass --checkpoint", settings.index)
    return Path(recorded)


def check_compatible(index_dir: Path, checkpoint: Path) -> dict[str, Any]:
    """Raise :class:`InputError` naming both when the bundle was built with other weights."""
    from pnvlad_service.models.store import model_identity

    ident = model_identity(checkpoint)
    Manifest.read(index_dir).check_model(ident)
    return ident.to_json()


class Localizer:
    """Model and index, loaded once; answers queries through a micro-batcher."""

    def __init__(
        self,
        bundle: IndexBundle,
        encoder: Any,
        model: dict[str, Any],
        settings: ServerSettings,
        on_batch: Any = None,
    ) -> None:
        self.bundle = bundle
        self.encoder = encoder
        self.model = model
        self.settings = settings
        if getattr(encoder, "dim", bundle.dim) != bundle.dim:
            raise InputError(
                f"encoder output dimension {encoder.dim} != index dimension {bundle.dim}",
                bundle.path,
            )
        self._gconfig: Any = None
        self.batcher = MicroBatcher(
            self._embed_and_search,
            max_size=settings.batch_max_size,
            wait_ms=settings.batch_wait_ms,
            on_batch=on_batch,
            lanes=settings.batch_lanes,
        )

    @classmethod
    def load(cls, settings: ServerSettings, on_batch: Any = None) -> Localizer:
        """Load the checkpoint and the bundle named by ``settings``; check they belong together."""
        if settings.torch_threads:
            import torch

            torch.set_num_threads(settings.torch_threads)
        if settings.faiss_threads:
            import faiss

            faiss.omp_set_num_threads(settings.faiss_threads)
        if settings.index is None:
            raise InputError("no index bundle given (--index or PNVLAD_INDEX)", "index")
        checkpoint = resolve_checkpoint(settings)
        ident = check_compatible(Path(settings.index), checkpoint)
        t0 = time.perf_counter()
        bundle = IndexBundle.load(settings.index, verify=settings.verify_bundle)
        encoder = load_encoder(checkpoint, device=settings.device)
        log.info(
            "loaded %s (%s, %d vectors) and model %s in %.2f s",
            settings.index,
            bundle.key,
            bundle.count,
            checkpoint,
            time.perf_counter() - t0,
        )
        return cls(bundle, encoder, ident, settings, on_batch=on_batch)

    def close(self) -> None:
        """Finish queued batches, then stop the encoder's cloud worker threads."""
        self.batcher.close()
        close = getattr(self.encoder, "close", None)
        if close is not None:
            close()

    # identity ---------------------------------------------------------------------------
    def model_info(self) -> dict[str, Any]:
        return {
            "weights_sha256": self.model["weights_sha256"],
            "config_sha256": self.model["config_sha256"],
            "arch": self.model.get("config", {}).get("arch"),
            "dim": self.bundle.dim,
        }

    def index_info(self) -> dict[str, Any]:
        return {"id": self.bundle.bundle_id, "key": self.bundle.key, "count": self.bundle.count}

    # work -------------------------------------------------------------------------------
    def preprocess(self, points: np.ndarray) -> np.ndarray:
        """Raw scan float64 [N, 3] -> float32 [4096, 3] through the bundle's filter G."""
        try:
            from pnvlad_service.data.preprocess import GConfig, filter_g
        except ImportError as exc:
            from pnvlad_service.server.problems import Problem

            raise Problem("unavailable", f"preprocessing is not available: {exc}") from None
        if self._gconfig is None:
            recorded = self.bundle.manifest.preprocess
            self._gconfig = GConfig.model_validate(recorded) if recorded else GConfig()
        out = filter_g(points, self._gconfig, seed=0)
        return np.ascontiguousarray(out, dtype=np.float32)

    def _embed_and_search(
        self, clouds: np.ndarray, k: int
    ) -> tuple[np.ndarray, np.ndarray, float, float]:
        t0 = time.perf_counter()
        desc = np.asarray(self.encoder.embed(clouds), dtype=np.float32)
        t1 = time.perf_counter()
        distances, ids = self.bundle.search(desc, k)
        return distances, ids, t1 - t0, time.perf_counter() - t1

    def localize(self, points: np.ndarray, preprocess: bool, top_n: int) -> dict[str, Any]:
        """Answer one query synchronously (the same path as the server): ``points`` float
        [N, 3]; returns the JSON answer (matches, timings_ms, model, index)."""
        t0 = time.perf_counter()
        pts = check_points(
            np.asarray(points), preprocess, "points", max(self.settings.max_raw_points, len(points))
        )
        top_n = max(1, min(int(top_n), self.settings.max_top_n))
        timings = {"parse": time.perf_counter() - t0}
        t1 = time.perf_counter()
        cloud = self.preprocess(pts) if preprocess else pts
        timings["preprocess"] = time.perf_counter() - t1
        result = self.batcher.submit(cloud, top_n).result()
        answer = self.answer(result, timings)
        timings["total"] = time.perf_counter() - t0
        answer["timings_ms"] = {k: round(v * 1000.0, 3) for k, v in timings.items()}
        answer["model"] = self.model_info()
        answer["index"] = self.index_info()
        return answer

    def answer(self, result: BatchResult, timings: dict[str, float]) -> dict[str, Any]:
        """One query's JSON answer; ``timings`` (seconds) gains queue, embed and search."""
        timings.update(queue=result.queue_s, embed=result.embed_s, search=result.search_s)
        (matches,) = self.bundle.matches(result.distances[None], result.ids[None])
        return {
            "matches": [
                {
                    "rank": m.rank,
                    "submap_id": m.submap_id,
                    "dataset": m.dataset,
                    "run": m.run,
                    "timestamp": m.timestamp,
                    "northing": m.northing,
                    "easting": m.easting,
                    "utm_zone": m.utm_zone or None,
                    "distance": m.distance if math.isfinite(m.distance) else None,
                }
                for m in matches
            ],
            "batch_size": result.batch_size,
        }
