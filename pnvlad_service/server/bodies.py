"""Request bodies of the localisation routes, by content type, to the one query type.

JSON goes through the request models (:mod:`pnvlad_service.server.contract`); the binary
bodies (``application/octet-stream``: little-endian xyz of float32 or float64, and
``application/x-npy``) are read as arrays without a copy and made a
:class:`~pnvlad_service.localization.query.query.Query` with the query parameters
(:class:`BinaryParams`), which checks the same rules. Every function raises
:class:`~pnvlad_service.errors.InputError` naming the field.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from starlette.requests import Request

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.query import Query, Where
from pnvlad_service.server.contract import Contract
from pnvlad_service.server.problems import Problem

JSON = "application/json"
OCTET = "application/octet-stream"
NPY = "application/x-npy"

_DTYPES = {"float32": "<f4", "float64": "<f8", "f4": "<f4", "f8": "<f8"}


def content_type(request: Request, allowed: tuple[str, ...]) -> str:
    """The request's media type, one of ``allowed``; 415 else."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype not in allowed:
        *first, last = allowed
        send = f"{', '.join(first)} or {last}" if first else last
        raise Problem(
            "unsupported-media-type",
            f"content type {ctype or '(none)'!r} is not supported; send {send}",
            field="Content-Type",
        )
    return ctype


def parse_binary_points(body: bytes, dtype: str) -> np.ndarray:
    """Interleaved little-endian xyz of ``dtype`` (float32 or float64) -> [N, 3] (a view)."""
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


@dataclass(frozen=True)
class BinaryParams:
    """The query parameters of a binary body (a JSON body says these in itself): the query's
    ``top_n``, ``preprocess``, ``verify``, ``scale`` and ``kind``, the ``dtype`` of raw xyz,
    and the prior's values by name (the query parameters ``prior_<name>``)."""

    top_n: int | None = None
    preprocess: bool | None = None
    verify: bool | None = None
    scale: float | None = None
    kind: str | None = None
    dtype: str | None = None
    prior: dict[str, Any] = field(default_factory=dict)


def read_query(contract: Contract, ctype: str, body: bytes, params: BinaryParams) -> Query:
    """The query of a ``/localize`` body of content type ``ctype`` (JSON, raw xyz or .npy);
    ``params`` are a binary body's (a ``scan`` or ``window`` is raw without saying
    ``preprocess``; a prior needs a raw scan)."""
    prior = {k: v for k, v in params.prior.items() if v is not None}
    if ctype == JSON:
        if prior:
            raise InputError("with a JSON body the prior is its 'prior' object", "prior_northing")
        return contract.parse_query(body)
    dtype = params.dtype or "float32"
    raw = parse_npy(body, 2) if ctype == NPY else parse_binary_points(body, dtype)
    return Query.make(
        raw,
        limits=contract.limits,
        preprocess=params.preprocess,
        kind=params.kind,
        top_n=params.top_n,
        verify=params.verify,
        scale=params.scale,
        prior=prior,
        where=Where(points="body", sep="_"),
    )


def read_batch(contract: Contract, ctype: str, body: bytes, params: BinaryParams) -> list[Query]:
    """The queries of a ``/localize/batch`` body: JSON, or .npy [B, N, 3] with ``params``'
    ``top_n``, ``preprocess`` and ``verify``."""
    if ctype == JSON:
        return list(contract.parse_batch(body))
    arr = parse_npy(body, 3)
    contract.limits.check_count(len(arr), "body")
    return [
        Query.make(
            a,
            limits=contract.limits,
            preprocess=bool(params.preprocess),
            top_n=params.top_n,
            verify=params.verify,
            where=Where(points=f"body[{i}]"),
        )
        for i, a in enumerate(arr)
    ]
