"""A followed scan's work that needs no answer, taken one scan ahead in a worker process.

A tracked drive localises scan k (the filter G, then the registration near its prediction) and
knows nothing of scan k+1's answer before that is done; but two parts of scan k+1's work need
no answer: its refined step (:mod:`.scan_steps`), and, for a map served in this process, its
filter G (:func:`~pnvlad_service.preprocess.filter_g.apply_g` with the bundle's settings, a
fixed function of the scan). :class:`ScansAhead` takes both in a worker while this process
localises scan k. The step's registrations and most of G hold the interpreter's lock, so a
thread could not overlap them with the localisation; a process does. The results are the same
as in turn: G's to the bit (it is seeded), the steps' to the millimetres small_gicp's threads
vary them by.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.localization.drive.scan_steps import ScanStepConfig, ScanSteps
from pnvlad_service.localization.verify.verify_process import settle_child


@dataclass(frozen=True)
class Ahead:
    """What the worker made of one scan: ``step``, :meth:`ScanSteps.update`'s pose (``None``
    without steps, or where the chain breaks); ``filtered``, the filter G's
    :class:`~pnvlad_service.preprocess.filter_g.GResult` of the scan as the localiser would
    prepare it (``None`` without G's settings, or where the scan is refused: the localiser then
    prepares it itself and says why, as it would have)."""

    step: np.ndarray | None
    filtered: Any


class ScansAhead:
    """A worker process that takes, for each scan :meth:`submit` hands it, the refined step
    (``steps``: a :class:`ScanSteps` of these settings; ``None``: none) and the filter G
    (``g``: a :class:`~pnvlad_service.preprocess.filter_g.GConfig`; ``None``: none), and returns
    the future of its :class:`Ahead`. Scans are stepped in the order submitted, as in this
    process. The worker starts in about a second (a fresh interpreter: the caller may hold
    threads a fork would copy mid-work; a script that makes one must do it under
    ``if __name__ == "__main__":``, as the CLI does); :meth:`close` ends it (also as a context
    manager)."""

    def __init__(self, steps: ScanStepConfig | None = None, g: Any = None) -> None:
        self._pool = ProcessPoolExecutor(
            1,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_start_worker,
            initargs=(steps, g),
        )

    def submit(self, points: np.ndarray, recorded: np.ndarray | None) -> Future[Ahead]:
        return self._pool.submit(_worker_take, points, recorded)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> ScansAhead:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_STEPS: ScanSteps | None = None
_G: Any = None


def _start_worker(steps: ScanStepConfig | None, g: Any) -> None:
    """The worker's initialiser: it shares the cores with the process that localises, so its
    OpenMP threads sleep while they wait (small_gicp loads in its first step, after this)."""
    global _STEPS, _G
    settle_child()
    _STEPS = None if steps is None else ScanSteps(steps)
    _G = g


def _worker_take(points: np.ndarray, recorded: np.ndarray | None) -> Ahead:
    step = None if _STEPS is None else _STEPS.update(points, recorded)
    return Ahead(step, None if _G is None else filtered(points, _G))


def filtered(points: np.ndarray, g: Any) -> Any:
    """The filter G's result of a raw scan as a localiser in this process prepares it (the
    query's checks and its missing returns dropped, then G seeded 0), or ``None`` where it
    refuses the scan."""
    from pnvlad_service.localization.query.limits import Limits
    from pnvlad_service.localization.query.query import Query
    from pnvlad_service.preprocess.filter_g import apply_g

    try:
        limits = Limits(max_raw_points=max(Limits.max_raw_points, len(points)))
        query = Query.make(points, limits=limits, preprocess=True, kind="scan")
        return apply_g(query.points, g, seed=0)
    except InputError:
        return None
