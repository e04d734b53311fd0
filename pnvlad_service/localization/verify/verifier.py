"""One verifier interface, in this process or in a child process, chosen once at load.

A :class:`Verifier` registers a query's metres to bundle rows: to its retrieved candidates
(:meth:`Verifier.verify`, the cascade of :func:`~.verify.verify`) or to the map entries near
a prior pose (:meth:`Verifier.register_near`, :func:`~.prior.register_near`). Two kinds:

- :class:`~.in_process.InProcess` registers in the caller's thread, with its own caches of
  prepared clouds;
- :class:`InChild` sends the work to a :class:`~.verify_process.VerifyProcess` (small_gicp
  holds the GIL: a server's threads that embed and answer keep running meanwhile); a child
  that died has its query registered in this process, and the next one starts a new child.

:func:`open_verifier` picks one for a bundle (none for a bundle without geometry).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from pnvlad_service.localization.verify.in_process import InProcess
from pnvlad_service.localization.verify.prior import Nearby, Prior, PriorConfig, PriorFit
from pnvlad_service.localization.verify.verify import QueryCloud, Verification, VerifyConfig
from pnvlad_service.localization.verify.verify_process import VerifyProcess

log = logging.getLogger(__name__)


class Verifier(Protocol):
    """Registers queries to the rows of one bundle's geometry."""

    def verify(self, query: QueryCloud, ids: Sequence[int], config: VerifyConfig) -> Verification:
        """The cascade of ``query`` against the rows ``ids`` (retrieval order)."""
        ...

    def register_near(
        self, query: QueryCloud, nearby: Nearby, prior: Prior, config: PriorConfig
    ) -> PriorFit:
        """``query`` registered to the rows ``nearby`` laid together around ``prior``."""
        ...

    def close(self) -> None:
        """Release what it holds (a child process)."""
        ...


class InChild:
    """Registration in a child process (:class:`VerifyProcess` of the bundle at
    ``bundle_dir``); ``here``: the :class:`InProcess` verifier that takes a query whose child
    died."""

    def __init__(self, bundle_dir: Any, cache_entries: int, here: InProcess) -> None:
        self.process = VerifyProcess(bundle_dir, cache_entries)
        self.here = here

    def verify(self, query: QueryCloud, ids: Sequence[int], config: VerifyConfig) -> Verification:
        try:
            return self.process.verify(query, ids, config)
        except BrokenProcessPool:
            log.error(
                "the verification process died; this query is verified in the server's "
                "process, the next one starts a new child"
            )
        return self.here.verify(query, ids, config)

    def register_near(
        self, query: QueryCloud, nearby: Nearby, prior: Prior, config: PriorConfig
    ) -> PriorFit:
        try:
            return self.process.register_near(query, nearby, prior, config)
        except BrokenProcessPool:
            log.error(
                "the verification process died; this query is registered in the server's "
                "process, the next one starts a new child"
            )
        return self.here.register_near(query, nearby, prior, config)

    def close(self) -> None:
        self.process.close()


def open_verifier(
    bundle_dir: Any, geometry: Any, cache_entries: int, in_child: bool
) -> Verifier | None:
    """The verifier of a bundle (``None`` without ``geometry``): :class:`InChild` when
    ``in_child``, else :class:`InProcess`."""
    if geometry is None:
        return None
    here = InProcess(geometry, cache_entries)
    return InChild(bundle_dir, cache_entries, here) if in_child else here
