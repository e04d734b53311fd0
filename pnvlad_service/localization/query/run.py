"""The one path of a query: :func:`run` takes a :class:`~.query.Query` through a localiser's
steps, given a :class:`Runner` that says how blocking work runs.

The steps, in order: the map's checks (:meth:`~.localizer.Localizer.check`), the filter G on
a raw scan (:meth:`~.localizer.Localizer.prepare`), then either the registration near the
query's prior (:meth:`~.localizer.Localizer.register_near`) or embedding and search
(:meth:`~.localizer.Localizer.submit`, queued to the micro-batcher) and the verification of
the candidates (:meth:`~.localizer.Localizer.verify`); the typed :class:`~.answers.Answer` last.

The server's routes run it on their event loop with a runner that sends blocking work to the
thread pool and awaits the batcher's futures; the library runs it inline (:data:`INLINE`,
:func:`run_inline`: no event loop; each step runs in the caller's thread). A batch of queries
is each query on this path, together (:func:`run_many`).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Coroutine, Sequence
from concurrent.futures import Future
from contextlib import AbstractContextManager
from dataclasses import replace
from typing import Any, Protocol, TypeVar

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.answers import Answer
from pnvlad_service.localization.query.batching import BatchResult
from pnvlad_service.localization.query.query import Query
from pnvlad_service.localization.verify.prior import Prior, PriorFit
from pnvlad_service.localization.verify.verify import PreparedCloud, Verification

T = TypeVar("T")


class Steps(Protocol):
    """A query's steps, one method each (:class:`~.localizer.Localizer` has them)."""

    def announce(self, count: int = 1) -> AbstractContextManager[None]: ...

    def check(self, query: Query, field: str = "kind") -> bool: ...

    def prepare(
        self, points: np.ndarray, preprocess: bool, scale: float | None = None
    ) -> PreparedCloud: ...

    def search_k(self, top_n: int, verify: bool) -> int: ...

    def submit(self, cloud: PreparedCloud, top_n: int) -> Future[BatchResult]: ...

    def verify(self, prepared: PreparedCloud, result: BatchResult) -> Verification: ...

    def register_near(self, prepared: PreparedCloud, prior: Prior) -> PriorFit: ...

    def answer(self, result: BatchResult, **times: Any) -> Answer: ...

    def answer_near(self, fit: PriorFit, **times: Any) -> Answer: ...


class Runner(Protocol):
    """How a query's blocking work runs: :meth:`blocking` calls ``fn(*args)`` (G, a
    registration, parsing a body), :meth:`wait` waits for a batcher's future."""

    async def blocking(self, fn: Callable[..., T], *args: Any) -> T: ...

    async def wait(self, future: Future[T]) -> T: ...


class Inline:
    """Blocking work in the caller's thread: a coroutine of :func:`run` never suspends."""

    async def blocking(self, fn: Callable[..., T], *args: Any) -> T:
        return fn(*args)

    async def wait(self, future: Future[T]) -> T:
        return future.result()


INLINE = Inline()


def run_inline(coro: Coroutine[Any, Any, T]) -> T:
    """The result of a coroutine that runs with :data:`INLINE` (driven here, no event loop)."""
    try:
        coro.send(None)
    except StopIteration as done:
        return done.value
    coro.close()
    raise RuntimeError("a query step suspended while running inline")


async def run(
    loc: Steps,
    query: Query | Callable[[], Query],
    runner: Runner,
    *,
    t0: float | None = None,
    field: str = "points",
    kind_field: str = "kind",
) -> Answer:
    """The :class:`Answer` of ``query`` on ``loc``; ``query`` may be a function that parses
    it (a request body: run by ``runner`` while the batcher knows a cloud is coming). ``t0``:
    when the query began (its parse included; default now); ``field`` and ``kind_field``: what
    a refusal of G or of the map's kind names."""
    t0 = time.perf_counter() if t0 is None else t0
    with loc.announce():
        if not isinstance(query, Query):
            query = await runner.blocking(query)
        verify = loc.check(query, kind_field)
        parse_s = time.perf_counter() - t0
        if query.prior is None:
            prepared = await _prepare(loc, query, runner, field)
            preprocess_s = time.perf_counter() - t0 - parse_s
            future = loc.submit(prepared, loc.search_k(query.top_n, verify))
    if query.prior is not None:
        prepared = await _prepare(loc, query, runner, field)
        preprocess_s = time.perf_counter() - t0 - parse_s
        fit = await runner.blocking(loc.register_near, prepared, query.prior)
        answer = loc.answer_near(fit, **_told(query, t0, parse_s, preprocess_s))
    else:
        result = await runner.wait(future)
        verification = await runner.blocking(loc.verify, prepared, result) if verify else None
        told = _told(query, t0, parse_s, preprocess_s)
        answer = loc.answer(result, verification=verification, **told)
    return replace(answer, no_returns=query.no_returns) if query.no_returns else answer


def _told(query: Query, t0: float, parse_s: float, preprocess_s: float) -> dict[str, Any]:
    """What an answer tells of its query besides the search: its ``top_n`` and kind, and the
    stages' times (``total_s``: from ``t0`` until now)."""
    return {
        "parse_s": parse_s,
        "preprocess_s": preprocess_s,
        "total_s": time.perf_counter() - t0,
        "top_n": query.top_n,
        "query_kind": query.kind,
    }


async def run_many(
    loc: Steps, queries: Sequence[Query], runner: Runner, *, t0: float | None = None
) -> list[Answer]:
    """The answers of a batch: every query's map checks first (the first refusal names its
    ``queries[i]``), then each on :func:`run`, together, so that their clouds are embedded as
    one batch; the first query's refusal in order is raised."""
    for i, q in enumerate(queries):
        loc.check(q, f"queries[{i}].kind")
    runs = (
        run(loc, q, runner, t0=t0, field=f"queries[{i}].points", kind_field=f"queries[{i}].kind")
        for i, q in enumerate(queries)
    )
    answers = await asyncio.gather(*runs, return_exceptions=True)
    for a in answers:
        if isinstance(a, BaseException):
            raise a
    return list(answers)  # type: ignore[arg-type]


async def _prepare(loc: Steps, query: Query, runner: Runner, field: str) -> PreparedCloud:
    """The encoder's input of ``query``: a raw scan through the filter G (blocking work; its
    refusal names ``field``), a preprocessed cloud as it is."""
    if not query.raw:
        return loc.prepare(query.points, False, query.scale)
    try:
        return await runner.blocking(loc.prepare, query.points, True)
    except InputError as exc:
        raise InputError(f"filter G: {exc.detail}", field) from None
