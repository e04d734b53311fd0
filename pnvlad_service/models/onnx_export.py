"""``pnvlad model export``: a model directory's encoder written as ``model.onnx`` beside its
weights, and checked against torch before it is.

The graph (:mod:`.onnx_graph`) is the fast inference path of :class:`~.inference.Encoder` with
the batch norms folded the same way (``folding.py``); bev-netvlad's with its convolutions'
batch norms folded. Before the file is written, ONNX Runtime embeds the check clouds (seeded
street-like clouds, :func:`~.onnx_encoder.check_clouds`, and any given ``points``) as one batch
and one cloud at a time, and every descriptor must be within cosine 0.9999 of the torch
encoder's; the torch descriptors of the seeded clouds go into the file's metadata, with the
sha256 of the weights and the configuration, for the checks at load
(:class:`~.onnx_encoder.OnnxEncoder`). Needs torch and the ``onnx`` package (the ``torch``
extra).
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError, PnvladError
from pnvlad_service.extras import require
from pnvlad_service.fileio import atomic_write_bytes
from pnvlad_service.models.onnx_encoder import (
    MIN_COSINE,
    ONNX_FILE,
    OnnxEncoder,
    OnnxRecord,
    check_clouds,
    cosines,
)
from pnvlad_service.models.pretrained import refuse_pretrained

log = logging.getLogger(__name__)

#: The seeded check clouds an export records (their torch descriptors go into the file).
CHECK_SEED = 20240901
CHECK_CLOUDS = 4


@dataclass(frozen=True)
class OnnxExport:
    """What :func:`export_onnx` wrote: the file, its size, the smallest cosine against torch
    over the clouds checked, how many, and the seconds the export took."""

    path: Path
    bytes: int
    min_cosine: float
    clouds: int
    seconds: float


def folded_params(model: Any) -> dict[str, Any]:
    """The parameters :func:`~.onnx_graph.build_graph` takes, from a model in eval mode."""
    from pnvlad_service.models.folding import fold_model
    from pnvlad_service.models.onnx_graph import bev_params

    if model.cfg.arch == "bev-netvlad":
        return bev_params(model)
    return fold_model(model)


def export_onnx(
    directory: str | Path,
    *,
    point_tile: int = 512,
    points: np.ndarray | None = None,
    threads: int | None = None,
    float16: bool = False,
) -> OnnxExport:
    """Write ``model.onnx`` into the model directory ``directory`` (atomically, replacing an
    older one) after checking it against the torch encoder on the seeded check clouds and on
    ``points`` float [M, N, 3] when given (real clouds); :class:`PnvladError` naming the worst
    cloud when a descriptor is below cosine 0.9999, and nothing is written.

    ``point_tile``: points a tile of the widest per-point layers (0: whole clouds);
    ``threads``: ONNX Runtime's threads for the check; ``float16``: store the graph's weight
    matrices as float16 (:func:`store_float16`; the check then runs on that graph)."""
    require("torch", "torch", "torch", "pnvlad model export")
    onnx = require("onnx", "onnx", "torch", "pnvlad model export")
    import torch

    from pnvlad_service.models import store
    from pnvlad_service.models.config import config_sha256
    from pnvlad_service.models.inference import Encoder
    from pnvlad_service.models.onnx_graph import build_graph

    refuse_pretrained(directory)
    t0 = time.perf_counter()
    directory = store.resolve_model_dir(directory)
    model, cfg = store.load_model(directory)
    model.eval()
    sha = store.weights_sha256(directory)
    encoder = Encoder(model, cfg, weights_sha256=sha)
    seeded = check_clouds(CHECK_SEED, CHECK_CLOUDS, cfg.num_points)
    with torch.inference_mode():
        reference = encoder.embed(seeded)
    record = OnnxRecord(
        weights_sha256=sha,
        config_sha256=config_sha256(cfg),
        check_seed=CHECK_SEED,
        check_points=cfg.num_points,
        check_descriptors=reference,
        point_tile=point_tile,
        exported=f"{_dt.datetime.now(_dt.timezone.utc).isoformat(timespec='seconds')} "
        f"torch {torch.__version__}, onnx {onnx.__version__}",
    )
    with torch.no_grad():
        proto = build_graph(
            cfg, folded_params(model), point_tile=point_tile, metadata=record.metadata()
        )
    if float16:
        store_float16(proto)
    data = proto.SerializeToString()

    # The check, on the bytes about to be written.
    path = directory / ONNX_FILE
    ort = OnnxEncoder(path, cfg, sha, threads=threads, check=False, data=data)
    clouds = [seeded] + ([] if points is None else [np.asarray(points, dtype=np.float32)])
    try:
        worst, count = _check_against_torch(encoder, ort, clouds, directory)
    finally:
        ort.close()
        encoder.close()
    try:
        atomic_write_bytes(path, data)
    except OSError as exc:
        raise InputError(f"cannot write {ONNX_FILE} here ({exc.strerror})", directory) from None
    seconds = time.perf_counter() - t0
    log.debug(
        "wrote %s (%.1f MB): %d clouds within cosine %.6f of torch, in %.1f s",
        path,
        len(data) / 1e6,
        count,
        worst,
        seconds,
    )
    return OnnxExport(path, len(data), worst, count, seconds)


def _check_against_torch(
    encoder: Any, ort: OnnxEncoder, clouds: list[np.ndarray], directory: Path
) -> tuple[float, int]:
    """The smallest cosine of ONNX Runtime's descriptors (each batch whole and one cloud at a
    time) to torch's over ``clouds`` and how many clouds; :class:`PnvladError` naming the
    first cloud below :data:`MIN_COSINE`."""
    import torch

    worst, count = 1.0, 0
    for batch in clouds:
        with torch.inference_mode():
            want = encoder.embed(batch)
        for got in (ort.embed(batch), np.concatenate([ort.embed(c) for c in batch])):
            cos = cosines(got, want)
            i = int(np.argmin(cos))
            if not cos[i] >= MIN_COSINE:
                raise PnvladError(
                    f"{directory}: the ONNX graph's descriptor of check cloud {count + i} "
                    f"is at cosine {cos[i]:.6f} of torch's (< {MIN_COSINE}); nothing written"
                )
            worst = min(worst, float(cos[i]))
        count += len(batch)
    return worst, count


def store_float16(proto: Any) -> int:
    """Store ``proto``'s float32 initializers of two or more dimensions (weight matrices,
    convolution kernels) as float16, each followed by a ``Cast`` back to float32 at the top of
    the graph under its old name; ONNX Runtime folds the casts when it loads the file, so it
    computes in float32 from the rounded weights. Vectors, and matrices with a value outside
    float16's range, stay float32. Returns the initializers converted."""
    from onnx import TensorProto, helper, numpy_helper

    graph = proto.graph
    kept, casts = [], []
    for init in graph.initializer:
        if init.data_type == TensorProto.FLOAT and len(init.dims) >= 2:
            arr = numpy_helper.to_array(init)
            if np.all(np.abs(arr) <= np.finfo(np.float16).max):
                half = numpy_helper.from_array(arr.astype(np.float16), f"{init.name}__f16")
                kept.append(half)
                casts.append(
                    helper.make_node("Cast", [half.name], [init.name], to=TensorProto.FLOAT)
                )
                continue
        kept.append(init)
    nodes = [*casts, *graph.node]
    del graph.initializer[:]
    graph.initializer.extend(kept)
    del graph.node[:]
    graph.node.extend(nodes)
    return len(casts)
