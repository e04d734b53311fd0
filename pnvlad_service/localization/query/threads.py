"""The process's thread counts of torch (intra-op) and FAISS (OpenMP): :func:`set_threads` once
(the server, when it loads its localiser), :func:`faiss_threads_here` in each thread that
searches (the :class:`~.localizer.Localizer` calls it before each search)."""

from __future__ import annotations

import threading

from pnvlad_service.models.runtimes import torch_installed

# FAISS's OpenMP thread count is per thread in libgomp: set in the main thread at start-up,
# it left the server's lanes, which search, on every core (measured: 1 in the main thread, 2
# in a new one). set_threads records it; each searching thread applies it once.
_faiss_threads: int | None = None
_faiss_applied = threading.local()


def set_threads(torch_threads: int | None = None, faiss_threads: int | None = None) -> None:
    """Process-wide thread counts of torch (intra-op) and FAISS (OpenMP); ``None``: as is.
    FAISS's count also reaches the threads that search later (:func:`faiss_threads_here`)."""
    global _faiss_threads
    if torch_threads and torch_installed():  # a server on ONNX Runtime may have no torch
        import torch

        torch.set_num_threads(torch_threads)
    if faiss_threads:
        _faiss_threads = faiss_threads
        faiss_threads_here()


def faiss_threads_here() -> None:
    """Give the calling thread the FAISS thread count of :func:`set_threads` (once a thread)."""
    if _faiss_threads is None or getattr(_faiss_applied, "n", None) == _faiss_threads:
        return
    import faiss

    faiss.omp_set_num_threads(_faiss_threads)
    _faiss_applied.n = _faiss_threads
