"""Request bodies of the localisation routes, by content type, to validated clouds.

JSON goes through the request models (:mod:`pnvlad_service.server.contract`); the binary
bodies (``application/octet-stream``: little-endian xyz of float32 or float64, and
``application/x-npy``) are read as arrays without a copy and checked by the same
``Limits.check_points``; with them ``top_n`` and ``preprocess`` are query parameters.
Every function raises :class:`~pnvlad_service.errors.InputError` naming the field.
"""

from __future__ import annotations

import io

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.limits import query_kind
from pnvlad_service.server.contract import PRIOR_RAW, SCALE_RAW, BatchQueries, Contract, Query

JSON = "application/json"
OCTET = "application/octet-stream"
NPY = "application/x-npy"

_DTYPES = {"float32": "<f4", "float64": "<f8", "f4": "<f4", "f8": "<f8"}


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


def read_query(
    contract: Contract,
    ctype: str,
    body: bytes,
    top_n: int | None,
    preprocess: bool | None,
    dtype: str,
    verify: bool | None = None,
    scale: float | None = None,
    kind: str | None = None,
    prior: dict[str, float | None] | None = None,
) -> Query:
    """The cloud of a ``/localize`` body of content type ``ctype`` (JSON, raw xyz or .npy);
    ``top_n``, ``preprocess``, ``dtype``, ``verify``, ``scale``, ``kind`` and the ``prior``'s
    values (``northing``, ``easting``, ``yaw_deg``, ``height``, ``radius_m``: the query
    parameters ``prior_<name>``) are the query's, for binary bodies (a ``scan`` or ``window``
    is raw without saying ``preprocess``)."""
    if ctype == JSON:
        if prior and any(v is not None for v in prior.values()):
            raise InputError("with a JSON body the prior is its 'prior' object", "prior_northing")
        return contract.parse_query(body)
    limits = contract.limits
    kind, pre = query_kind(kind, preprocess)
    given = {k: v for k, v in (prior or {}).items() if v is not None}
    pose = None
    if given:
        if not pre:
            raise InputError(PRIOR_RAW, "prior_northing")
        if verify is False:
            raise InputError("a query with a prior is registered to the map: no verify=false",
                             "verify")  # fmt: skip
        pose = limits.check_prior(**given, field="prior", sep="_")
    raw = parse_npy(body, 2) if ctype == NPY else parse_binary_points(body, dtype)
    points = limits.check_points(raw, pre, "body")
    scale = limits.check_scale(scale)
    if pre and scale is not None:
        raise InputError(SCALE_RAW, "scale")
    n = top_n if top_n is not None else limits.default_top_n
    return Query(points, pre, n, verify, scale, kind, pose)


def read_batch(
    contract: Contract,
    ctype: str,
    body: bytes,
    top_n: int | None,
    preprocess: bool | None,
    verify: bool | None = None,
) -> BatchQueries:
    """The clouds of a ``/localize/batch`` body: JSON, or .npy [B, N, 3] with the query's
    ``top_n``, ``preprocess`` and ``verify``."""
    if ctype == JSON:
        return contract.parse_batch(body)
    limits = contract.limits
    pre = bool(preprocess)
    n = top_n if top_n is not None else limits.default_top_n
    arr = parse_npy(body, 3)
    limits.check_count(len(arr), "body")
    kind = "scan" if pre else "submap"
    queries = tuple(
        Query(limits.check_points(a, pre, f"body[{i}]"), pre, n, verify, None, kind)
        for i, a in enumerate(arr)
    )
    return BatchQueries(queries, n, verify)
