"""``OnnxEncoder``: the encoder on ONNX Runtime, without torch.

A model directory with ``model.onnx`` (``pnvlad model export``, :mod:`.onnx_export`) embeds
with ONNX Runtime: ``OnnxEncoder.from_checkpoint(dir).embed(points [B, N, 3]) -> float32
[B, D]``, the same interface as :class:`~.inference.Encoder` (``dim``, ``weights_sha256``,
``crowded_by``, ``close``), so the ``Localizer``, the micro-batcher and the index build take
either. This module imports numpy, pydantic and (when an encoder is made) onnxruntime: never
torch.

At load the file is checked against the directory it sits in: the sha256 of the
``model.safetensors`` and of the configuration it was exported from (recorded in the ONNX
file's metadata) must be those of the directory, else :class:`InputError` naming both files;
and the check clouds recorded at export (seeded, rebuilt here with numpy) must embed within
cosine 0.9999 of torch's descriptors of them.

Threads, as the torch encoder uses them (docs/SERVICE.md, "How a request runs"): two sessions
of the same file, a *wide* one on ``threads`` intra-op threads for a lone cloud on idle
cores, and a *narrow* one on one thread that ``threads`` worker threads run side by side, each
on its own share of a batch's clouds (ONNX Runtime releases the GIL while it runs). A batch of
several clouds, or any batch while ``crowded_by()`` says other work holds the cores (a
verification in flight) or while another batch is being embedded, goes to the workers; a lone
cloud on idle cores, and the last ones of a batch that would leave most workers idle, to the
wide session.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.extras import require
from pnvlad_service.models.config import ModelConfig, config_sha256
from pnvlad_service.models.embedding import over_scales, unit_rows
from pnvlad_service.models.store import ONNX_FILE

log = logging.getLogger(__name__)

#: ``metadata_props`` keys of an exported file.
FORMAT = "pnvlad-onnx"
FORMAT_VERSION = "1"
#: Cosine every check cloud's descriptor must keep against torch's (export and load).
MIN_COSINE = 0.9999


# --------------------------------------------------------------------------------------------
# Check clouds: seeded, made with numpy alone, so a server without torch rebuilds them
# --------------------------------------------------------------------------------------------


def check_clouds(seed: int, count: int, points: int) -> np.ndarray:
    """float32 [count, points, 3] in [-1, 1]: street-like clouds (ground, two facades along a
    direction, poles, scattered points), each turned to its own heading; cloud i from
    ``default_rng(seed + i)``."""
    out = np.empty((count, points, 3), dtype=np.float32)
    for i in range(count):
        rng = np.random.default_rng(seed + i)
        n_ground, n_wall, n_pole = int(0.4 * points), int(0.4 * points), int(0.1 * points)
        n_rest = points - n_ground - n_wall - n_pole
        ground = np.column_stack(
            [rng.uniform(-0.9, 0.9, (n_ground, 2)), rng.normal(-0.03, 0.003, n_ground)]
        )
        side = rng.choice([-0.3, 0.35], n_wall) + rng.normal(0, 0.005, n_wall)
        wall = np.column_stack(
            [rng.uniform(-0.9, 0.9, n_wall), side, rng.uniform(-0.03, 0.05, n_wall)]
        )
        poles = rng.uniform(-0.7, 0.7, (6, 2))[rng.integers(0, 6, n_pole)]
        pole = np.column_stack(
            [poles + rng.normal(0, 0.004, (n_pole, 2)), rng.uniform(-0.03, 0.04, n_pole)]
        )
        rest = rng.uniform(-0.9, 0.9, (n_rest, 3)) * [1, 1, 0.05]
        cloud = np.concatenate([ground, wall, pole, rest])
        a = rng.uniform(-np.pi, np.pi)
        turn = np.array([[np.cos(a), np.sin(a), 0], [-np.sin(a), np.cos(a), 0], [0, 0, 1]])
        out[i] = np.clip(cloud @ turn, -1, 1)
    return out


def encode_array(a: np.ndarray) -> dict[str, Any]:
    """A float32 array as JSON: shape and base64 of its little-endian bytes."""
    a = np.ascontiguousarray(a, dtype="<f4")
    return {"shape": list(a.shape), "f32le": base64.b64encode(a.tobytes()).decode("ascii")}


def decode_array(doc: dict[str, Any]) -> np.ndarray:
    """:func:`encode_array` read back."""
    raw = base64.b64decode(doc["f32le"])
    return np.frombuffer(raw, dtype="<f4").reshape(doc["shape"]).astype(np.float32)


def cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """float64 [M]: the cosine of each row of ``a`` with the same row of ``b`` (float [M, D])."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    den = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return (a * b).sum(1) / np.maximum(den, 1e-30)


@dataclass(frozen=True)
class OnnxRecord:
    """What an exported file says of itself (its ``metadata_props``): the sha256 of the weights
    and of the configuration it was exported from, and its check: torch's descriptors float32
    [M, D] of M seeded clouds of ``check_points`` points (:func:`check_clouds`)."""

    weights_sha256: str
    config_sha256: str
    check_seed: int
    check_points: int
    check_descriptors: np.ndarray
    point_tile: int
    exported: str

    def clouds(self) -> np.ndarray:
        """The check clouds float32 [M, N, 3] the descriptors are of."""
        return check_clouds(self.check_seed, len(self.check_descriptors), self.check_points)

    @classmethod
    def from_metadata(cls, meta: dict[str, str], path: Path) -> OnnxRecord:
        if meta.get("pnvlad.format") != FORMAT:
            raise InputError(
                f"not an ONNX file that pnvlad exported (metadata pnvlad.format is "
                f"{meta.get('pnvlad.format')!r}): write it with `pnvlad model export`",
                path,
            )
        if meta.get("pnvlad.version") != FORMAT_VERSION:
            raise InputError(
                f"ONNX export version {meta.get('pnvlad.version')!r}, this pnvlad reads "
                f"{FORMAT_VERSION}: export the model again (pnvlad model export)",
                path,
            )
        try:
            check = json.loads(meta["pnvlad.check"])
            return cls(
                weights_sha256=meta["pnvlad.weights_sha256"],
                config_sha256=meta["pnvlad.config_sha256"],
                check_seed=int(check["seed"]),
                check_points=int(check["points"]),
                check_descriptors=decode_array(check["descriptors"]),
                point_tile=int(meta.get("pnvlad.point_tile", "0")),
                exported=meta.get("pnvlad.exported", ""),
            )
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"unreadable pnvlad metadata in the ONNX file ({exc})", path) from None

    def metadata(self) -> dict[str, str]:
        """The ``metadata_props`` to write."""
        check = {
            "seed": self.check_seed,
            "points": self.check_points,
            "descriptors": encode_array(self.check_descriptors),
        }
        return {
            "pnvlad.format": FORMAT,
            "pnvlad.version": FORMAT_VERSION,
            "pnvlad.weights_sha256": self.weights_sha256,
            "pnvlad.config_sha256": self.config_sha256,
            "pnvlad.check": json.dumps(check),
            "pnvlad.point_tile": str(self.point_tile),
            "pnvlad.exported": self.exported,
        }

    def check_identity(self, path: Path, directory: Path, weights_sha256: str, cfg: Any) -> None:
        """:class:`InputError` naming both files unless the file at ``path`` was exported
        from the weights (sha256 ``weights_sha256``) and configuration ``cfg`` of
        ``directory``."""
        from pnvlad_service.models.store import CONFIG_FILE, WEIGHTS_FILE

        if self.weights_sha256 != weights_sha256:
            raise InputError(
                f"{path} was exported from other weights (sha256 {self.weights_sha256[:16]}…) "
                f"than {directory / WEIGHTS_FILE} (sha256 {weights_sha256[:16]}…): export it "
                f"again, pnvlad model export {directory}",
                path,
            )
        if self.config_sha256 != config_sha256(cfg):
            raise InputError(
                f"{path} was exported from another configuration (sha256 "
                f"{self.config_sha256[:16]}…) than {directory / CONFIG_FILE} (sha256 "
                f"{config_sha256(cfg)[:16]}…): export it again, pnvlad model export {directory}",
                path,
            )


def read_onnx_metadata(path: str | Path) -> dict[str, str]:
    """The ``metadata_props`` of the ONNX file at ``path`` without loading it: the file's
    top-level protobuf fields are walked and every one but ``metadata_props`` (field 14 of
    ``ModelProto``: ``StringStringEntryProto`` key 1, value 2) skipped by its length, so the
    graph and its weights are never read. :class:`InputError` naming the file when it is not
    a protobuf message."""
    path = Path(path)
    out: dict[str, str] = {}
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            while fh.tell() < size:
                field, wire = divmod(_read_varint(fh), 8)
                if wire == 0:
                    _read_varint(fh)
                    continue
                if wire in (1, 5):
                    fh.seek(8 if wire == 1 else 4, 1)
                    continue
                if wire != 2:
                    raise ValueError(f"wire type {wire}")
                n = _read_varint(fh)
                if fh.tell() + n > size:
                    raise ValueError("truncated")
                if field != 14:
                    fh.seek(n, 1)
                    continue
                entry = io.BytesIO(fh.read(n))
                kv: dict[int, bytes] = {}
                while entry.tell() < n:
                    f, w = divmod(_read_varint(entry), 8)
                    if w != 2:
                        raise ValueError(f"wire type {w} in a metadata entry")
                    kv[f] = entry.read(_read_varint(entry))
                out[kv.get(1, b"").decode("utf-8")] = kv.get(2, b"").decode("utf-8")
    except (ValueError, UnicodeDecodeError, EOFError):
        raise InputError("not an ONNX file (unreadable protobuf)", path) from None
    return out


def _read_varint(fh: Any) -> int:
    """One protobuf varint from the binary stream ``fh``."""
    value = shift = 0
    while True:
        b = fh.read(1)
        if not b:
            raise EOFError
        value |= (b[0] & 0x7F) << shift
        if not b[0] & 0x80:
            return value
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def check_onnx_file(directory: str | Path, weights_sha256: str) -> Path:
    """``model.onnx`` of the model directory ``directory``, checked without loading it: it was
    exported by pnvlad from this directory's weights (sha256 ``weights_sha256``) and
    configuration (:meth:`OnnxRecord.check_identity`; ``pnvlad serve`` runs this before it
    starts). :class:`InputError` naming both files otherwise."""
    from pnvlad_service.models.store import read_model_json

    directory = Path(directory)
    path = directory / ONNX_FILE
    if not path.is_file():
        raise InputError(f"no {ONNX_FILE} in this model directory", directory)
    cfg, _ = read_model_json(directory)
    record = OnnxRecord.from_metadata(read_onnx_metadata(path), path)
    record.check_identity(path, directory, weights_sha256, cfg)
    return path


def default_threads() -> int:
    """The CPUs this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def runtime_version() -> str:
    """``onnxruntime X.Y.Z`` (the installed package), for logs and /readyz."""
    ort = require("onnxruntime", "onnxruntime", None, "the ONNX encoder")
    return f"onnxruntime {ort.__version__}"


class OnnxEncoder:
    """The encoder of ``model.onnx`` on ONNX Runtime (see the module doc).

    ``OnnxEncoder.from_checkpoint(dir)``; ``embed(points)`` with points float [B, N, 3] or
    [N, 3] (coordinates as the model was trained on) -> numpy float32 [B, dim], unit rows.
    ``threads``: intra-op threads of the wide session and worker threads of the narrow one
    (default: the CPUs of this process); ``batch_size``: clouds a forward pass at most;
    ``check``: embed the check clouds at load (:meth:`self_check`); ``directory``: the model
    directory whose weights and configuration the file must come from
    (:meth:`OnnxRecord.check_identity`); ``data``: the file's bytes when they are not (yet)
    at ``path`` (the export's check).
    """

    runtime = "onnx"

    def __init__(
        self,
        path: str | Path,
        cfg: ModelConfig,
        weights_sha256: str,
        *,
        threads: int | None = None,
        batch_size: int = 32,
        check: bool = True,
        directory: str | Path | None = None,
        data: bytes | None = None,
    ) -> None:
        ort = require("onnxruntime", "onnxruntime", None, "the ONNX encoder")
        if batch_size < 1:
            raise InputError(f"batch_size must be >= 1, got {batch_size}", "batch_size")
        self.path = Path(path)
        self.cfg = cfg
        self.batch_size = batch_size
        self.threads = threads or default_threads()
        self._sha = weights_sha256
        #: Whether other work holds the cores right now (as ``Encoder.crowded_by``).
        self.crowded_by: Callable[[], bool] | None = None
        self._embedding = 0
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        record = None
        if data is None:  # checked before anything is loaded
            record = OnnxRecord.from_metadata(read_onnx_metadata(self.path), self.path)
            if directory is not None:
                record.check_identity(self.path, Path(directory), weights_sha256, cfg)
            data = self.path.read_bytes()
        self._wide = ort.InferenceSession(
            data, self._options(ort, self.threads), providers=["CPUExecutionProvider"]
        )
        self.record = record or OnnxRecord.from_metadata(
            self._wide.get_modelmeta().custom_metadata_map, self.path
        )
        self._narrow = (
            ort.InferenceSession(data, self._options(ort, 1), providers=["CPUExecutionProvider"])
            if self.threads > 1
            else self._wide
        )
        del data
        self.version = ort.__version__
        if check:
            self.self_check()

    @staticmethod
    def _options(ort: Any, threads: int) -> Any:
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.log_severity_level = 3  # warnings of the optimiser are not the user's business
        return so

    @classmethod
    def from_checkpoint(
        cls,
        directory: str | Path,
        *,
        weights_sha256: str | None = None,
        **kwargs: Any,
    ) -> OnnxEncoder:
        """The encoder of a model directory's ``model.onnx``, after checking that it was
        exported from the directory's own weights and configuration (:class:`InputError`
        naming both files otherwise). ``weights_sha256``: the weights' hash when the caller
        has it (a ``ModelIdentity``)."""
        from pnvlad_service.models.store import read_model_json, resolve_model_dir
        from pnvlad_service.models.store import weights_sha256 as sha_of

        directory = resolve_model_dir(directory)
        path = directory / ONNX_FILE
        if not path.is_file():
            raise InputError(
                f"no {ONNX_FILE} in this model directory: write it with `pnvlad model export "
                f"{directory}` (needs torch: pip install 'pnvlad[torch]')",
                directory,
            )
        cfg, _ = read_model_json(directory)
        sha = weights_sha256 or sha_of(directory)
        return cls(path, cfg, sha, directory=directory, **kwargs)

    # -- properties ---------------------------------------------------------------------------

    @property
    def dim(self) -> int:
        return self.cfg.output_dim

    @property
    def weights_sha256(self) -> str:
        """SHA-256 of the ``model.safetensors`` the file was exported from."""
        return self._sha

    def describe(self) -> str:
        """One line for logs and /readyz: runtime, version, threads."""
        return f"onnxruntime {self.version}, {self.threads} threads"

    # -- inference ----------------------------------------------------------------------------

    def self_check(self) -> float:
        """Embed the check clouds recorded at export and compare with torch's descriptors of
        them; :class:`InputError` naming the file below cosine :data:`MIN_COSINE`. Returns
        the smallest cosine."""
        rec = self.record
        got = self.embed(rec.clouds())
        worst = float(cosines(got, rec.check_descriptors).min())
        if not worst >= MIN_COSINE:
            raise InputError(
                f"ONNX Runtime {self.version}'s descriptors of the check clouds differ from "
                f"torch's recorded at export (cosine {worst:.6f} < {MIN_COSINE}): export the "
                "model again with this version, or serve it with torch",
                self.path,
            )
        return worst

    def embed(self, points: Any) -> np.ndarray:
        """Descriptors float32 [B, dim] (unit rows) of points float [B, N, 3] or [N, 3]."""
        x = self._as_array(points)
        out = np.empty((x.shape[0], self.dim), dtype=np.float32)
        for s in range(0, x.shape[0], self.batch_size):
            chunk = x[s : s + self.batch_size]
            out[s : s + chunk.shape[0]] = over_scales(
                self._forward, chunk, self.cfg.embed_scales, unit_rows
            )
        return out

    def _as_array(self, points: Any) -> np.ndarray:
        if hasattr(points, "detach"):  # a torch tensor, from a caller that has torch
            points = points.detach().cpu().numpy()
        x = np.asarray(points)
        if x.ndim == 2:
            x = x[None]
        if x.ndim != 3 or x.shape[-1] != 3 or x.shape[1] < 1:
            raise InputError(
                f"expected points of shape [B, N, 3] or [N, 3], got {list(x.shape)}", "points"
            )
        if not (np.issubdtype(x.dtype, np.floating) or x.dtype in (np.int32, np.int64)):
            raise InputError(f"expected float coordinates, got {x.dtype}", "points")
        x = np.ascontiguousarray(x, dtype=np.float32)
        if not np.isfinite(x).all():
            raise InputError("points contain NaN or infinite coordinates", "points")
        return x

    def _run(self, session: Any, x: np.ndarray) -> np.ndarray:
        return session.run(["descriptor"], {"points": x})[0]

    def _forward(self, x: np.ndarray) -> np.ndarray:
        """Descriptors of one batch x float32 [b, n, 3] (see the module doc for which session
        runs which clouds)."""
        with self._lock:
            self._embedding += 1
            alone = self._embedding == 1
        try:
            if alone and self.crowded_by is not None and self.crowded_by():
                alone = False
            b = x.shape[0]
            workers = self.threads
            pool = self._worker_pool()
            if pool is None or (b == 1 and alone):
                return self._run(self._wide, x)
            rest = b % workers
            side = b if (rest > workers / 2 or not alone) else b - rest
            parts = [p for p in np.array_split(np.arange(side), workers) if len(p)]
            futures = [pool.submit(self._run, self._narrow, x[p[0] : p[-1] + 1]) for p in parts]
            tail = [self._run(self._wide, x[side:])] if side < b else []
            return np.concatenate([f.result() for f in futures] + tail)
        finally:
            with self._lock:
                self._embedding -= 1

    def _worker_pool(self) -> ThreadPoolExecutor | None:
        """The worker threads that run the narrow session (made on first use), or None for a
        single thread."""
        with self._lock:
            if self._pool is None and self.threads > 1:
                self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="pnvlad-onnx")
            return self._pool

    def close(self) -> None:
        """Stop the worker threads (a later batch starts them again)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True)
