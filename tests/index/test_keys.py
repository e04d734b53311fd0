"""FAISS key choice at the guideline boundaries, training needs, search parameters, recall@1
against a plain loop, and IVF-PQ without polysemous training."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.index import keys


def test_auto_key_at_the_guideline_boundaries() -> None:
    big = 10**15
    assert keys.choose_index_key(1, 256, big) == "Flat"
    assert keys.choose_index_key(100_000, 256, big) == "Flat"
    assert keys.choose_index_key(100_001, 256, big) == "HNSW32"
    assert keys.choose_index_key(9_999_999, 256, big) == "HNSW32"
    assert keys.choose_index_key(10_000_000, 256, big).startswith("OPQ64,IVF")
    # HNSW32 needs n (4 d + 8 M) bytes; one byte less and IVF-Flat (n (4 d + 8)) takes over.
    n, d = 1_000_000, 256
    hnsw = n * (4 * d + 8 * 32)
    assert keys.choose_index_key(n, d, hnsw) == "HNSW32"
    assert keys.choose_index_key(n, d, hnsw - 1) == "IVF8192,Flat"
    ivf_flat = n * (4 * d + 8)
    assert keys.choose_index_key(n, d, ivf_flat) == "IVF8192,Flat"
    assert keys.choose_index_key(n, d, ivf_flat - 1) == "IVF8192,PQ64"
    assert keys.choose_index_key(n, d, n * (16 + 8)) == "IVF8192,PQ16"
    # A small map that does not fit as Flat is compressed (lists capped at n / 39 -> 1024).
    assert keys.choose_index_key(50_000, 256, 50_000 * 4 * 256 - 1) == "IVF1024,PQ64"
    with pytest.raises(InputError):
        keys.choose_index_key(0, 256)


@settings(max_examples=200, deadline=None)
@given(st.integers(min_value=1, max_value=10**9))
def test_ivf_lists_follow_the_guideline(n: int) -> None:
    k = keys.ivf_lists(n)
    assert k >= 1 and k & (k - 1) == 0  # a power of two
    if n >= 312**2:  # from here on 8√n <= n / 39: the 39-points-a-list cap does not bind
        assert 4 * n**0.5 <= k <= 16 * n**0.5
    assert k <= max(1, n // 39)


def test_min_training_vectors() -> None:
    assert keys.min_training_vectors("Flat") == 1
    assert keys.min_training_vectors("IVF1024,Flat") == 1024
    assert keys.min_training_vectors("IVF16,PQ8") == 256
    assert keys.min_training_vectors("OPQ16,IVF4096,PQ16x4") == 4096


def test_exact_keys_and_default_search_params() -> None:
    assert keys.is_exact("Flat") and keys.is_exact("IDMap, Flat")
    assert not keys.is_exact("HNSW32") and not keys.is_exact("IVF8,Flat")
    assert keys.default_search_params("Flat") == {}
    assert keys.default_search_params("HNSW32") == {"efSearch": keys.DEFAULT_EF_SEARCH}
    assert keys.default_search_params("IVF4,Flat") == {"nprobe": 4}  # capped at the lists
    assert keys.default_search_params("IVF8192,PQ16") == {"nprobe": keys.DEFAULT_NPROBE}


def test_applied_search_params_reach_the_wrapped_index() -> None:
    import faiss

    x = np.random.default_rng(2).standard_normal((400, 8)).astype(np.float32)
    index = keys.make_index(x, "IVF8,Flat")
    keys.apply_search_params(index, {"nprobe": 5})
    assert faiss.extract_index_ivf(index).nprobe == 5


def test_recall_at_1_against_a_loop() -> None:
    import faiss

    rng = np.random.default_rng(1)
    x = rng.standard_normal((200, 8)).astype(np.float32)
    y = x.copy()
    y[::3] += rng.standard_normal((len(y[::3]), 8)).astype(np.float32)  # a third of rows moved
    index = faiss.IndexFlatL2(8)
    index.add(y)
    got = keys.recall_at_1(index, x, sample=200)
    hits = 0
    for q in x:
        nearest = min(range(len(y)), key=lambda j: float(((y[j] - q) ** 2).sum()))
        hits += float(((x[nearest] - q) ** 2).sum()) <= 1e-6
    assert got == pytest.approx(hits / len(x))
    assert got < 1.0


def test_ivf_pq_skips_polysemous_training() -> None:
    import faiss

    x = np.random.default_rng(0).standard_normal((300, 16)).astype(np.float32)
    index = keys.make_index(x, "IVF2,PQ4")
    ivf = faiss.downcast_index(faiss.extract_index_ivf(index))
    assert ivf.do_polysemous_training is False
    assert index.ntotal == 300


def test_make_index_refuses_unknown_keys_and_too_few_vectors() -> None:
    x = np.zeros((10, 8), dtype=np.float32)
    with pytest.raises(InputError, match="cannot make an index"):
        keys.make_index(x, "NoSuchKey")
    with pytest.raises(InputError, match="at least 16 vectors"):
        keys.make_index(x, "IVF16,Flat")
