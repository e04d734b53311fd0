"""Verification in a child process, away from the GIL of the process that embeds.

small_gicp's Python binding holds the GIL for the whole of each call (measured by
benchmarks/gil_hold.py: a Python thread spinning beside ``preprocess_points`` ran at 2.1-2.4 %
of its idle rate). In the server's process a registration therefore stops every other Python
thread for milliseconds at a time: the micro-batcher's lanes between the encoder's operators,
the event loop parsing the next requests. Under load the cores then wait on the lock rather
than work. A child process has a GIL of its own: it registers while the parent embeds and
answers (docs/VERIFY.md, "In the server").

:class:`VerifyProcess` starts one child (``spawn``: nothing of the parent's torch or OpenMP
state is inherited) that maps the bundle's geometry itself, read-only, and registers there as
this process would (an :class:`~.in_process.InProcess` verifier with caches of its own). A
query crosses as its metres (about 100 KB) and the candidates' bundle rows; the
:class:`~.verify.Verification` comes back. Verifications queue for the one child, as they
queued for the GIL before.

The pipe carries pickles between this process and the child it started: both ends are this
code, nothing else can write to it.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from pnvlad_service.localization.verify.in_process import InProcess
from pnvlad_service.localization.verify.prior import Nearby, Prior, PriorConfig, PriorFit
from pnvlad_service.localization.verify.verify import QueryCloud, Verification, VerifyConfig

log = logging.getLogger(__name__)

#: Set by `pnvlad serve` beside the GOMP_SPINCOUNT it chose for the server's process.
SPINCOUNT_MARK = "PNVLAD_SERVE_SET_GOMP_SPINCOUNT"

# The child's state, set by _start (one bundle per child): the geometry and its caches.
_HERE: InProcess | None = None
_GOMP_BEFORE: bool | None = None


def _start(bundle_dir: str, cache_entries: int) -> None:
    """The child's initialiser: map the geometry of ``bundle_dir`` (the parent checked the
    bundle's files at its own start-up; the size check runs again)."""
    global _HERE, _GOMP_BEFORE
    # The tests check, through _runtime, that no libgomp at all was mapped here before.
    _GOMP_BEFORE = _gomp_loaded()
    settle_child()
    from pnvlad_service.index.geometry import BundleGeometry
    from pnvlad_service.index.manifest import Manifest

    manifest = Manifest.read(Path(bundle_dir))
    if manifest.geometry is None:
        raise RuntimeError(f"{bundle_dir} carries no geometry")
    geometry = BundleGeometry.open(bundle_dir, manifest.geometry, verify=False)
    _HERE = InProcess(geometry, cache_entries)


def settle_child() -> None:
    """What a registering child process of ours sets first, before it loads small_gicp.

    small_gicp's OpenMP runtime (libgomp) lets a thread that reaches a barrier first spin
    there. While the parent works on the other core, the thread it waits for has no core, and
    each call stalls for scheduler slices: preparing a query on 2 threads took 40-61 ms with a
    core busy, 6.6 ms with the threads sleeping at barriers instead, and 4.4-5.5 ms either way
    on idle cores (docs/VERIFY.md). libgomp reads the wait policy when it loads, so the child
    must load small_gicp only after this. A value the user set is kept; the GOMP_SPINCOUNT
    `pnvlad serve` sets for the server's encoder would override PASSIVE, so that one (not a
    user's) is dropped. Ctrl-C reaches the whole process group: the parent stops the child, so
    the child ignores it rather than die mid-call with a traceback of its own."""
    if os.environ.pop(SPINCOUNT_MARK, None):
        os.environ.pop("GOMP_SPINCOUNT", None)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _gomp_loaded() -> bool:
    """Whether an OpenMP runtime (libgomp) is mapped into this process (Linux; else False)."""
    try:
        with open("/proc/self/maps") as fh:
            return any("libgomp" in line for line in fh)
    except OSError:
        return False


def _runtime() -> dict[str, Any]:
    """The child's OpenMP wait policy, and whether any libgomp (torch's own, or the copy that
    faiss and small_gicp share) was mapped before it was set: a main script that imports
    torch or faiss at its top loads one in the child too (spawn imports it again); only the
    small_gicp one matters here."""
    return {
        "OMP_WAIT_POLICY": os.environ.get("OMP_WAIT_POLICY"),
        "GOMP_SPINCOUNT": os.environ.get("GOMP_SPINCOUNT"),
        "gomp_before": _GOMP_BEFORE,
    }


def _ready() -> int:
    """The rows the child mapped (its first call: the parent waits for it)."""
    assert _HERE is not None
    return int(_HERE.geometry.count)


def _verify(query: QueryCloud, ids: list[int], config: VerifyConfig) -> Verification:
    assert _HERE is not None
    return _HERE.verify(query, ids, config)


def _register_near(
    query: QueryCloud, nearby: Nearby, prior: Prior, config: PriorConfig
) -> PriorFit:
    assert _HERE is not None
    return _HERE.register_near(query, nearby, prior, config)


class VerifyProcess:
    """One child process that verifies queries against the geometry of the bundle at
    ``bundle_dir`` (see the module doc). :meth:`verify` blocks its caller until the answer is
    back; callers from many threads queue. If the child dies, the call that saw it raises
    :class:`BrokenProcessPool` and the next call starts a new child.

    The child is started with ``spawn``, which imports the parent's main script again: a
    script that makes one must do it under ``if __name__ == "__main__":`` (servers, the CLI
    and pytest do)."""

    def __init__(self, bundle_dir: str | Path, cache_entries: int = 0) -> None:
        self.bundle_dir = str(bundle_dir)
        self.cache_entries = cache_entries
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = None
        self._closed = False
        self._started()  # start now: the first query should not wait for an interpreter

    def _started(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._closed:
                raise RuntimeError("the verification process is closed")
            if self._pool is None:
                pool = ProcessPoolExecutor(
                    max_workers=1,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_start,
                    initargs=(self.bundle_dir, self.cache_entries),
                )
                try:
                    count = pool.submit(_ready).result()
                except (BrokenProcessPool, RuntimeError) as exc:
                    pool.shutdown(wait=False, cancel_futures=True)
                    raise RuntimeError(
                        f"the verification process for {self.bundle_dir} did not start ({exc}); "
                        "a script that loads a Localizer with verify_process=True must do it "
                        "under `if __name__ == '__main__':` (multiprocessing's spawn imports "
                        "the script again in the child)"
                    ) from exc
                log.info("verification process started (%d submaps mapped)", count)
                self._pool = pool
            return self._pool

    def verify(self, query: QueryCloud, ids: Sequence[int], config: VerifyConfig) -> Verification:
        """:func:`~.verify.verify` of ``query`` against the bundle rows ``ids`` (retrieval
        order), run in the child."""
        return self._call(_verify, query, [int(i) for i in ids], config)

    def register_near(
        self, query: QueryCloud, nearby: Nearby, prior: Prior, config: PriorConfig
    ) -> PriorFit:
        """:func:`~.prior.register_near` of ``query`` to the bundle rows ``nearby`` from
        ``prior``, run in the child."""
        return self._call(_register_near, query, nearby, prior, config)

    def _call(self, fn: Any, *args: Any) -> Any:
        pool = self._started()
        try:
            return pool.submit(fn, *args).result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            raise

    def close(self) -> None:
        """Stop the child (waits for the verification in flight)."""
        with self._lock:
            self._closed = True
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
