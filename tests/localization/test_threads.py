"""The process's thread counts (localization/query/threads.py)."""

from __future__ import annotations

import threading

import pytest

from pnvlad_service.localization.query import threads


def test_the_faiss_thread_count_reaches_the_threads_that_search() -> None:
    """libgomp keeps the count per thread: set in one thread, a new thread still had every
    core. set_threads' count is applied in each searching thread (as the lanes search)."""
    faiss = pytest.importorskip("faiss")

    before = threads._faiss_threads
    try:
        threads.set_threads(faiss_threads=1)
        seen: list[int] = []

        def search_like_a_lane() -> None:
            fresh = faiss.omp_get_max_threads()  # what the thread starts with
            threads.faiss_threads_here()
            seen.extend([fresh, faiss.omp_get_max_threads()])

        t = threading.Thread(target=search_like_a_lane)
        t.start()
        t.join()
        default = seen[0]
        assert seen[1] == 1
        if default == 1:
            pytest.skip("one CPU: a new thread has one FAISS thread anyway")
    finally:
        threads._faiss_threads = before


def test_the_localizer_module_still_names_set_threads() -> None:
    from pnvlad_service.localization.query import localizer

    assert localizer.set_threads is threads.set_threads
