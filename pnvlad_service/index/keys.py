"""Choosing and making a FAISS index: the factory key by map size and memory budget, search
parameters, and recall@1 of an approximate index against exact search.

Descriptors are float32 [N, D] under the L2 metric. ``faiss`` is imported inside the functions
that need it (:func:`import_faiss`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError, MissingDependencyError

if TYPE_CHECKING:
    import faiss

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

_IVF_RE = re.compile(r"IVF(\d+)")
_PQ_RE = re.compile(r"(?<!O)PQ(\d+)(?:x(\d+))?")


def import_faiss() -> Any:
    """The ``faiss`` module, or :class:`MissingDependencyError` saying what to install."""
    try:
        import faiss
    except ImportError as exc:  # pragma: no cover - faiss-cpu is a core dependency
        raise MissingDependencyError("faiss-cpu", "index", "the FAISS index") from exc
    return faiss


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

    Trains on at most ``max_train`` vectors (a seeded sample). Raises :class:`InputError` for
    an unknown key or too few vectors to train it.
    """
    faiss = import_faiss()
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
    faiss = import_faiss()
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


def apply_search_params(index: faiss.Index, params: Mapping[str, int]) -> None:
    """Set search-time parameters (``efSearch``, ``nprobe``) on any wrapped index."""
    faiss = import_faiss()
    ps = faiss.ParameterSpace()
    for name, value in params.items():
        ps.set_index_parameter(index, name, value)


def recall_at_1(
    index: faiss.Index, descriptors: np.ndarray, sample: int = 1000, seed: int = 0
) -> float:
    """Share of sampled database vectors whose top-1 under ``index`` is their exact top-1.

    ``descriptors`` float32 [N, D] are the vectors in ``index``; ``sample`` of them (seeded)
    are the queries. A tie (same distance as the exact neighbour, e.g. a duplicate vector)
    counts as a hit.
    """
    faiss = import_faiss()
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
