"""The micro-batcher: every request gets its own answer, concurrent ones share a batch, a lone
one does not wait, failures reach the callers and leave the worker alive."""

from __future__ import annotations

import threading
import time
from contextlib import closing

import numpy as np
import pytest

from pnvlad_service.localization.query.batching import MicroBatcher


def echo(sizes: list[int], delay: float = 0.0):
    """A batch function whose 'ids' are each cloud's first value: answers must not mix up."""

    def fn(clouds: np.ndarray, k: int):
        sizes.append(len(clouds))
        time.sleep(delay)
        ids = np.repeat(clouds[:, 0, 0].astype(np.int64)[:, None], k, axis=1) + np.arange(k)
        return np.zeros(ids.shape, np.float32), ids, 0.001, 0.0001

    return fn


def test_each_request_gets_its_own_answer_and_batches_form() -> None:
    sizes: list[int] = []
    with closing(MicroBatcher(echo(sizes, delay=0.05), max_size=8, wait_ms=1.0)) as b:
        first = b.submit(np.full((4, 3), 1000.0, np.float32), 2)  # occupies the worker
        futures = {i: b.submit(np.full((4, 3), float(i), np.float32), 1 + i % 3) for i in range(20)}
        assert first.result(10).ids.tolist() == [1000, 1001]
        for i, f in futures.items():
            r = f.result(10)
            assert r.ids.tolist() == list(range(i, i + 1 + i % 3))  # own cloud, own top_n
        assert max(sizes) == 8 and sum(sizes) == 21 and len(sizes) >= 3


def test_a_lone_request_does_not_wait() -> None:
    sizes: list[int] = []
    with closing(MicroBatcher(echo(sizes), max_size=32, wait_ms=50.0)) as b:
        t0 = time.perf_counter()
        b.submit(np.zeros((4, 3), np.float32), 1).result(5)
        assert time.perf_counter() - t0 < 0.04  # no announced request: no 50 ms wait


def test_announced_requests_are_waited_for() -> None:
    sizes: list[int] = []
    with closing(MicroBatcher(echo(sizes), max_size=32, wait_ms=300.0)) as b:
        with b.announce():
            late: list = []

            def later() -> None:
                time.sleep(0.05)
                late.append(b.submit(np.ones((4, 3), np.float32), 1))

            t = threading.Thread(target=later)
            t.start()
            early = b.submit(np.zeros((4, 3), np.float32), 1)
            t.join()
        assert early.result(5).batch_size == 2 and late[0].result(5).batch_size == 2
        assert sizes == [2]


def test_two_lanes_start_the_next_batch_while_one_is_busy() -> None:
    """A slow batch does not hold back a request that arrives after it with two lanes; with
    one lane the second request waits for the first batch to finish."""
    for lanes, ends_after in ((2, 0.15), (1, 0.3)):
        sizes: list[int] = []
        batcher = MicroBatcher(echo(sizes, delay=0.15), max_size=8, wait_ms=0.0, lanes=lanes)
        with closing(batcher) as b:
            t0 = time.perf_counter()
            a = b.submit(np.zeros((4, 3), np.float32), 1)
            while not sizes:  # the first batch has started (not a fixed sleep: loaded CI)
                time.sleep(0.001)
            c = b.submit(np.ones((4, 3), np.float32), 1)
            assert c.result(5).ids.tolist() == [1] and a.result(5).ids.tolist() == [0]
            took = time.perf_counter() - t0
            assert sizes == [1, 1]
            assert (took < 0.27) if lanes == 2 else (took >= ends_after)
    with pytest.raises(ValueError, match="lanes"):
        MicroBatcher(echo([]), lanes=0)


def test_a_failing_batch_reaches_its_callers_and_the_worker_lives_on() -> None:
    calls = {"n": 0}

    def flaky(clouds: np.ndarray, k: int):
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("boom")
        return np.zeros((len(clouds), k), np.float32), np.zeros((len(clouds), k), np.int64), 0, 0

    with closing(MicroBatcher(flaky, max_size=4, wait_ms=0.0)) as b:
        with pytest.raises(RuntimeError, match="boom"):
            b.submit(np.zeros((4, 3), np.float32), 1).result(5)
        assert b.submit(np.zeros((4, 3), np.float32), 1).result(5).ids.tolist() == [0]
    with pytest.raises(RuntimeError, match="closed"):
        b.submit(np.zeros((4, 3), np.float32), 1)


def test_busy_while_announced_queued_or_embedding() -> None:
    """``busy`` (what Localizer.verify reads to give small_gicp one thread) is true exactly
    while a cloud is announced, waiting or in a batch."""
    entered, release = threading.Event(), threading.Event()

    def held(clouds: np.ndarray, k: int):
        entered.set()
        release.wait(5)
        return echo([])(clouds, k)

    with closing(MicroBatcher(held, max_size=8, wait_ms=0.0, lanes=1)) as b:
        assert not b.busy
        with b.announce():
            assert b.busy
        assert not b.busy
        fut = b.submit(np.zeros((4, 3), np.float32), 1)
        assert entered.wait(5) and b.busy  # in the batch function
        release.set()
        fut.result(5)
        deadline = time.monotonic() + 5
        while b.busy and time.monotonic() < deadline:  # the lane leaves _process after
            time.sleep(0.001)  # resolving the future
        assert not b.busy
