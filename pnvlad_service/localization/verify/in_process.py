"""Registration in this process: :class:`InProcess`, a bundle's geometry and the caches of the
clouds it prepared, the :class:`~.verifier.Verifier` a localiser uses without a child, and the
one a child process (:mod:`.verify_process`) runs for its parent."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pnvlad_service.localization.verify.prior import (
    NEAR_CACHE_ENTRIES,
    Nearby,
    Prior,
    PriorConfig,
    PriorFit,
    register_near,
)
from pnvlad_service.localization.verify.verify import (
    PreparedCache,
    QueryCloud,
    Verification,
    VerifyConfig,
    bundle_candidates,
    verify,
)


class InProcess:
    """Registration in the caller's thread against ``geometry`` (a bundle's
    :class:`~pnvlad_service.index.geometry.BundleGeometry`), with a cache of ``cache_entries``
    prepared candidates (consecutive queries share candidates) and a few targets near priors."""

    def __init__(self, geometry: Any, cache_entries: int) -> None:
        self.geometry = geometry
        self._prepared = PreparedCache(cache_entries)
        self._near = PreparedCache(NEAR_CACHE_ENTRIES if cache_entries else 0)

    def verify(self, query: QueryCloud, ids: Sequence[int], config: VerifyConfig) -> Verification:
        candidates = bundle_candidates(self.geometry, [int(i) for i in ids])
        return verify(query, candidates, config, cache=self._prepared)

    def register_near(
        self, query: QueryCloud, nearby: Nearby, prior: Prior, config: PriorConfig
    ) -> PriorFit:
        return register_near(query, self.geometry, nearby, prior, config, cache=self._near)

    def close(self) -> None:
        pass
