"""Localisation as a library: a bundle and its model loaded together, a cloud in, typed
matches out. No HTTP here; the server (``pnvlad_service.server``) and ``pnvlad localize``
are two callers of the same path.

A :class:`Localizer` holds the steps of a query, one method each: :meth:`Localizer.check`
(what this map can answer), :meth:`Localizer.prepare` (the filter G on a raw scan, with the
bundle's G config, keeping its centre and scale for the pose), :meth:`Localizer.submit` (embed
and search, queued to the micro-batcher when loaded with one), :meth:`Localizer.verify` (the
candidates registered and re-ranked by the verifier chosen at load,
:mod:`pnvlad_service.localization.verify.verifier`) or :meth:`Localizer.register_near` (a
scan with a prior), and the :class:`Answer`. :func:`~.run.run` takes a
:class:`~.query.Query` through them, whoever drives it; :meth:`Localizer.localize` is that
path run inline (the CLI, scripts). Errors are the library's own: ``InputError`` (bad cloud,
a bundle built with other weights, verification asked of a bundle without geometry),
``NotReadyError`` (used after :meth:`Localizer.close`).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pnvlad_service.errors import InputError, NotReadyError
from pnvlad_service.index.bundle import IndexBundle, Match
from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.localization.query.answers import (
    Answer,
    IndexInfo,
    LocalizerInfo,
    ModelInfo,
    Timings,
)
from pnvlad_service.localization.query.batching import Batching, BatchResult, MicroBatcher
from pnvlad_service.localization.query.calibration import CALIBRATION_FILE, read_calibration
from pnvlad_service.localization.query.compatibility import checked_model
from pnvlad_service.localization.query.config import LocalizerConfig
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.localization.query.query import Query
from pnvlad_service.localization.query.run import INLINE, run, run_inline
from pnvlad_service.localization.query.threads import faiss_threads_here, set_threads
from pnvlad_service.localization.verify.prior import (
    MapPositions,
    Once,
    Prior,
    PriorConfig,
    PriorFit,
    no_map_near,
)
from pnvlad_service.localization.verify.scale import DriveTracks, map_tracks, track_scales
from pnvlad_service.localization.verify.verifier import open_verifier
from pnvlad_service.localization.verify.verify import PreparedCloud, Verification, VerifyConfig
from pnvlad_service.models.embedding import Embedder
from pnvlad_service.models.runtimes import describe as describe_runtime
from pnvlad_service.models.runtimes import load_encoder
from pnvlad_service.models.store import ModelIdentity

log = logging.getLogger(__name__)

__all__ = [
    "Batching",
    "Localizer",
    "LocalizerConfig",
    "Match",
    "Prior",
    "PriorConfig",
    "Query",
    "VerifyConfig",
    "checked_model",
    "set_threads",
]


class QueryEncoder(Embedder, Protocol):
    """The encoder a localiser embeds with (``models.inference.Encoder`` and
    ``models.onnx_encoder.OnnxEncoder`` are ones): an :class:`Embedder` that names its
    weights, can be told when other work holds the cores, and closes its threads."""

    crowded_by: Callable[[], bool] | None

    @property
    def weights_sha256(self) -> str: ...

    def close(self) -> None: ...


class Localizer:
    """A bundle and the encoder it was built with, loaded once; answers queries.

    With ``config.batching``, concurrent callers (threads, or an event loop's requests) share
    forward passes through a :class:`MicroBatcher`; without, each query runs in its caller's
    thread. ``threshold``: the verification's (default: ``config.verify``'s)."""

    def __init__(
        self,
        bundle: IndexBundle,
        encoder: QueryEncoder,
        identity: ModelIdentity,
        config: LocalizerConfig | None = None,
        *,
        on_batch: Callable[[int], None] | None = None,
        threshold: float | None = None,
    ) -> None:
        if encoder.dim != bundle.dim:
            raise InputError(
                f"encoder output dimension {encoder.dim} != index dimension {bundle.dim}",
                bundle.path,
            )
        from pnvlad_service.preprocess.filter_g import GConfig

        config = config or LocalizerConfig()
        self.config = config
        self.bundle = bundle
        self.encoder = encoder
        # Fixed once loaded; asked now so that /readyz and /info never wait on the thread that
        # embeds (describe asks it for torch's thread count).
        self._runtime = describe_runtime(encoder)
        self.identity = identity
        self.verify_config = config.verify.config(threshold)
        #: Whether the map's drives are taken as aligned (``pnvlad map align``; as the bundle
        #: records unless the config says): a prior's rules the config leaves unset follow it
        #: (docs/TRACKING.md).
        self.aligned_map = config.prior.aligned(bundle.manifest.map_record.aligned)
        self.prior_config = config.prior.config(aligned=self.aligned_map)
        # The map's positions for a prior's range search, made on the first prior.
        self._positions = Once(lambda: MapPositions.of_metadata(bundle.metadata))
        # The map's drives, for the scale of a query without one (verify_ids).
        self._tracks: Once[DriveTracks | None] = Once(self._map_tracks)
        # Verifications in flight: with another one, or the encoder busy, small_gicp runs on
        # VerifyConfig.crowded_threads (the cores are taken).
        self._verifying = 0
        self._verifying_lock = threading.Lock()
        # Registration here, or in a child process (small_gicp holds the GIL: there it does
        # not stop the threads that embed and answer; verify_process.py), chosen once.
        self.verifier = open_verifier(
            bundle.path, bundle.geometry, config.verify.cache, config.verify.process
        )
        if bundle.geometry is not None:
            # A verification in flight holds a core (the child's, or this process's): a batch
            # then runs on the single-threaded cloud workers, not on both cores' team.
            encoder.crowded_by = self._verification_in_flight
        recorded = bundle.manifest.preprocess
        self._gconfig = GConfig.model_validate(dict(recorded)) if recorded else GConfig()
        self.info = LocalizerInfo(
            model=ModelInfo(
                weights_sha256=identity.weights_sha256,
                config_sha256=identity.config_sha256,
                arch=identity.config.get("arch"),
                dim=bundle.dim,
            ),
            index=IndexInfo(id=bundle.bundle_id, key=bundle.key, count=bundle.count),
        )
        self._closed = False
        #: Whether :meth:`close` closes the encoder too (a reload that hands the encoder on
        #: to the next localiser clears it: ``serving.py``).
        self.owns_encoder = True
        batching = config.batching
        self._batcher = (
            None
            if batching is None
            else MicroBatcher(
                self._embed_and_search,
                max_size=batching.max_size,
                wait_ms=batching.wait_ms,
                on_batch=on_batch,
                lanes=batching.lanes,
            )
        )

    @classmethod
    def load(
        cls,
        index: str | Path,
        model: str | Path | None = None,
        config: LocalizerConfig | None = None,
        *,
        encoder: QueryEncoder | None = None,
        on_batch: Callable[[int], None] | None = None,
    ) -> Localizer:
        """Load the bundle at ``index`` and ``model`` (default: the one the bundle records),
        after checking that the bundle was built with these weights (:func:`checked_model`),
        as ``config`` says (:class:`LocalizerConfig`: the encoder, the verification and where
        it runs, the prior, the batcher, the bundle's checks). The verification threshold is
        the config's, else the one chosen for these weights when the model directory records
        it (:mod:`.calibration`), else :class:`VerifyConfig`'s. ``encoder``: one already
        loaded, reused when it holds these weights (a reload of the bundle with the same
        model: ``serving.py``); ``on_batch``: told the size of each batch embedded."""
        config = config or LocalizerConfig()
        ident = checked_model(index, model)
        threshold, source = config.verify.threshold, "given"
        if threshold is None:
            cal = read_calibration(ident.checkpoint, ident.weights_sha256)
            threshold = VerifyConfig.threshold if cal is None else cal.threshold
            source = "the verify config" if cal is None else CALIBRATION_FILE
        log.info("verification threshold %.2f (%s)", threshold, source)
        t0 = time.perf_counter()
        bundle = IndexBundle.load(index, verify=config.check_bundle)
        if encoder is None or encoder.weights_sha256 != ident.weights_sha256:
            e = config.encoder
            encoder = load_encoder(
                ident.checkpoint,
                device=e.device,
                identity=ident,
                runtime=e.runtime,
                threads=e.threads,
            )
        loc = cls(bundle, encoder, ident, config, on_batch=on_batch, threshold=threshold)
        log.info(
            "loaded %s (%s, %d vectors) and model %s in %.2f s; embedding with %s",
            index,
            bundle.key,
            bundle.count,
            ident.checkpoint,
            time.perf_counter() - t0,
            loc.runtime,
        )
        return loc

    def close(self) -> None:
        """Finish queued batches, then stop the verifier and the encoder's threads."""
        if self._closed:
            return
        self._closed = True
        if self._batcher is not None:
            self._batcher.close()
        if self.verifier is not None:
            self.verifier.close()
        if self.encoder.crowded_by == self._verification_in_flight:
            self.encoder.crowded_by = None  # a caller's encoder outlives this localizer
        if self.owns_encoder:
            self.encoder.close()

    def __enter__(self) -> Localizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def runtime(self) -> str:
        """What embeds, in one line: ``onnxruntime 1.22.0, 2 threads`` or ``torch 2.8.0, ...``."""
        return self._runtime

    def _verification_in_flight(self) -> bool:
        return self._verifying > 0

    def warm_up(self, largest: int) -> float:
        """Embed throw-away clouds 1, 2, ... ``largest`` at a time, once each, so that no
        request pays for the first forward pass of its batch size: that pass sets up the
        backend's kernels for the shape (oneDNN's convolutions for bev-netvlad: the demo's
        first two queries embedded in 52 ms, later ones in 3-7 ms). The clouds are seeded
        noise in the encoder's [-1, 1] cube; their descriptors are dropped. Seconds taken."""
        t0 = time.perf_counter()
        rng = np.random.default_rng(0)
        for b in range(1, max(0, largest) + 1):  # the server embeds whole submaps
            self.encoder.embed(rng.uniform(-1.0, 1.0, (b, SUBMAP_POINTS, 3)).astype(np.float32))
        seconds = time.perf_counter() - t0
        if largest > 0:
            log.info("warmed up batches of 1-%d clouds in %.2f s", largest, seconds)
        return seconds

    def manifest_json(self) -> dict[str, Any]:
        """The bundle's manifest as JSON (``manifest.json``'s content)."""
        return self.bundle.manifest.to_json()

    @functools.cached_property
    def utm_zone(self) -> str | None:
        """The UTM zone of the map's coordinates (its entries'), ``None`` when unknown; read
        once (the bundle does not change under a localiser: a reload makes a new one)."""
        zones = [str(z) for z in np.unique(self.bundle.metadata.utm_zone) if str(z)]
        return ", ".join(zones) or None

    # the steps of a query ---------------------------------------------------------------
    @contextlib.contextmanager
    def announce(self, count: int = 1) -> Iterator[None]:
        """Tell the batcher that ``count`` clouds are being parsed (it waits for them)."""
        if self._batcher is None:
            yield
            return
        with self._batcher.announce(count):
            yield

    @property
    def can_verify(self) -> bool:
        """Whether the bundle carries the geometry verification needs."""
        return self.bundle.geometry is not None

    def wants_verify(self, verify: bool | None, field: str = "verify") -> bool:
        """Whether a query runs verification: ``None`` means "when the bundle can". Asking for
        it of a bundle without geometry is an :class:`InputError` naming ``field``."""
        if verify is None:
            return self.can_verify
        if verify and not self.can_verify:
            raise InputError(
                f"the index {self.bundle.path} carries no geometry to verify against: build it "
                "from a tree with frame sidecars (pnvlad synth / pnvlad data prepare write them), "
                "or send verify=false",
                field,
            )
        return bool(verify)

    @property
    def map_kind(self) -> str:
        """What the bundle's entries are: ``submap`` or ``keyframe`` (single scans)."""
        return self.bundle.manifest.map_record.kind

    def check_kind(self, kind: str, field: str = "kind") -> None:
        """:class:`InputError` naming ``field`` when a query of ``kind`` does not meet its own
        kind in this bundle (an accumulated window against a map of single scans)."""
        if not self.bundle.manifest.map_record.accepts(kind):
            raise InputError(
                f"the index {self.bundle.path} holds {self.map_kind}s (single scans, cropped "
                f"as a scan is), which a {kind} query does not match: send single scans (kind "
                "scan), or ask a map of submaps (pnvlad index build --layout test)",
                field,
            )

    def check(self, query: Query, field: str = "kind") -> bool:
        """What this map makes of ``query``: :class:`InputError` when its kind does not meet
        the map's (naming ``field``), or it asks for verification or a prior of a bundle
        without geometry; whether it runs verification (a query without a prior)."""
        self.check_kind(query.kind, field)
        if query.prior is not None:
            self.check_prior()
            return False
        return self.wants_verify(query.verify)

    def search_k(self, top_n: int, verify: bool) -> int:
        """How many neighbours to search for: ``top_n``, or the candidates to verify."""
        return max(top_n, self.verify_config.candidates) if verify else top_n

    def prepare(
        self, points: np.ndarray, preprocess: bool, scale: float | None = None
    ) -> PreparedCloud:
        """The encoder's input: ``points`` as they are (``scale``: metres per unit, when the
        caller knows it), or a raw scan float [N, 3] metres through the bundle's filter G ->
        float32 [4096, 3], with G's centre and scale (sensor frame)."""
        if not preprocess:
            return PreparedCloud(points, None, scale, False)
        from pnvlad_service.preprocess.filter_g import apply_g

        g = apply_g(points, self._gconfig, seed=0)
        cloud = np.ascontiguousarray(g.points, dtype=np.float32)
        return PreparedCloud(cloud, g.centre, g.scale if self._gconfig.normalize else None, True)

    def submit(self, cloud: np.ndarray | PreparedCloud, top_n: int) -> Future[BatchResult]:
        """Embed and search one prepared cloud float32 [4096, 3] for its ``top_n`` neighbours
        (:meth:`search_k` when it is to be verified); the future resolves to its
        :class:`BatchResult` (already resolved without batching)."""
        if isinstance(cloud, PreparedCloud):
            cloud = cloud.cloud
        if self._closed:
            raise NotReadyError("the localizer is closed")
        if self._batcher is not None:
            return self._batcher.submit(cloud, top_n)
        fut: Future[BatchResult] = Future()
        distances, ids, embed_s, search_s = self._embed_and_search(cloud[None], top_n)
        fut.set_result(BatchResult(distances[0], ids[0], 0.0, embed_s, search_s, 1))
        return fut

    @contextlib.contextmanager
    def _registering(self) -> Iterator[bool]:
        """Count a registration in flight while the block runs; whether the cores are taken
        (another registration, or the encoder busy): small_gicp gets fewer threads then."""
        with self._verifying_lock:
            crowded = self._verifying > 0 or (self._batcher is not None and self._batcher.busy)
            self._verifying += 1
        try:
            yield crowded
        finally:
            with self._verifying_lock:
                self._verifying -= 1

    def verify(self, prepared: PreparedCloud, result: BatchResult) -> Verification:
        """Register the query to its nearest ``verify_config.candidates`` and re-rank them."""
        k = self.verify_config.candidates
        return self.verify_ids(prepared, [int(i) for i in result.ids[:k] if i >= 0])

    def _map_tracks(self) -> DriveTracks | None:
        geometry = self.bundle.geometry
        if geometry is None:
            return None
        tracks = map_tracks(self.bundle.metadata, geometry.metres)
        steady = self.verify_config.scale.takes_tracks(tracks)
        log.info(
            "queries without a scale start from %s (the submaps' extents along their drives: "
            "90th percentile %.2f times the 10th; track_spread %s)",
            "the extent along the candidates' drives" if steady else "the candidates' median scale",
            tracks.spread,
            self.verify_config.scale.track_spread,
        )
        return tracks

    def verify_ids(self, prepared: PreparedCloud, ids: list[int]) -> Verification:
        """Register the query to the map entries ``ids`` (best first) and re-rank them. A
        query without a scale starts from the metres per unit its extent along the
        candidates' drives gives (:func:`~..verify.scale.track_scales`), its factor then held
        to ``ScaleConfig.track_bounds``, on a map whose submaps span alike along their drives
        (:func:`~..verify.scale.map_tracks`); else from the candidates' median scale."""
        geometry = self.bundle.geometry
        if geometry is None or self.verifier is None:
            raise InputError("the bundle carries no geometry", "verify")
        scales = [geometry.scale(i) for i in ids]
        config = self.verify_config
        tracks = self._tracks.get() if prepared.scale is None and ids else None
        if tracks is not None and config.scale.takes_tracks(tracks):
            tracked = track_scales(
                prepared.cloud,
                scales,
                [functools.partial(geometry.metres, i) for i in ids],
                tracks.directions[ids],
            )
            if tracked is not None:
                scales, config = tracked, replace(config, scale=config.scale.tracked())
        query = prepared.query(scales)
        with self._registering() as crowded:
            return self.verifier.verify(query, ids, config.crowded() if crowded else config)

    # a query with a prior pose ---------------------------------------------------------
    def check_prior(self, field: str = "prior") -> None:
        """:class:`InputError` naming ``field`` when a scan cannot be registered near a prior
        here: the bundle has no geometry (the rest of a prior's rules are the query's own:
        :meth:`Query.make`)."""
        if not self.can_verify:
            raise InputError(
                f"the index {self.bundle.path} carries no geometry to register a scan near its "
                "prior against: build it from a tree with frame sidecars",
                field,
            )

    def positions(self) -> MapPositions:
        """The range search over the map's positions (built on first use)."""
        return self._positions.get()

    def register_near(self, prepared: PreparedCloud, prior: Prior) -> PriorFit:
        """Register a prepared raw scan to the map entries within ``prior.radius_m`` of the
        prior (:func:`~..verify.prior.register_near`, by the verifier): its
        :class:`~..verify.prior.PriorFit`; a prior with no entry near says so (not verified)."""
        if self.verifier is None:
            raise InputError("the bundle carries no geometry", "prior")
        config = self.prior_config
        positions = self.positions()
        nearby = positions.near(prior, config.max_submaps, config.same_run)
        if nearby is None:
            nearest = positions.nearest_m(prior.northing, prior.easting)
            return no_map_near(prior, nearest, config.min_fitness)
        query = prepared.query([])
        with self._registering() as crowded:
            if crowded and self.verify_config.crowded_threads is not None:
                reg_config = replace(
                    config.registration, threads=self.verify_config.crowded_threads
                )
                config = replace(config, registration=reg_config)
            fit = self.verifier.register_near(query, nearby, prior, config)
            if not config.retry_submaps or fit.pose is None or fit.fitness >= config.min_fitness:
                return fit
            # Under the threshold: once more against a wider stretch of the map.
            wider = positions.near(prior, config.retry_submaps, config.same_run)
            if wider is None or len(wider.rows) <= len(nearby.rows):
                return fit
            at = min(1.0, config.min_fitness + config.retry_margin)
            again = replace(config, min_fitness=at)
            retried = self.verifier.register_near(query, wider, prior, again)
            moved = retried.correction_m
            near = moved is not None and moved <= config.retry_max_correction_m
            return retried if retried.verified and near else fit

    def answer_near(
        self,
        fit: PriorFit,
        *,
        parse_s: float,
        preprocess_s: float,
        total_s: float,
        top_n: int | None = None,
        query_kind: str = "scan",
    ) -> Answer:
        """The :class:`Answer` of a query registered near its prior: the entries registered
        to as its matches (nearest the prior first, at most ``top_n``), no embedding."""
        rows = fit.rows[: top_n or len(fit.rows)]
        nan = np.full((1, len(rows)), np.nan, dtype=np.float32)
        ids = np.asarray([rows], dtype=np.int64).reshape(1, -1)
        (matches,) = self.bundle.matches(nan, ids)
        timings = Timings(
            parse=parse_s,
            preprocess=preprocess_s,
            verify=fit.seconds,
            total=total_s,
        )
        return Answer(
            tuple(matches), 1, timings, None, tuple(m.rank for m in matches), query_kind,
            self.map_kind, fit,
        )  # fmt: skip

    def answer(
        self,
        result: BatchResult,
        *,
        parse_s: float,
        preprocess_s: float,
        total_s: float,
        top_n: int | None = None,
        verification: Verification | None = None,
        query_kind: str = "submap",
    ) -> Answer:
        """One cloud's :class:`Answer` from its batch result, its verification (re-ranked) and
        its earlier stage times; ``top_n``: matches to keep (default: all searched)."""
        (matches,) = self.bundle.matches(result.distances[None], result.ids[None])
        ranks = [m.rank for m in matches]
        if verification is not None:
            head = [r for r in verification.order if r <= len(matches)]
            ranks = head + [r for r in ranks if r not in set(head)]
        ranks = ranks[: top_n or len(ranks)]
        ordered = tuple(replace(matches[r - 1], rank=k) for k, r in enumerate(ranks, 1))
        timings = Timings(
            parse=parse_s,
            preprocess=preprocess_s,
            queue=result.queue_s,
            embed=result.embed_s,
            search=result.search_s,
            verify=0.0 if verification is None else verification.seconds,
            total=total_s,
        )
        return Answer(
            ordered,
            result.batch_size,
            timings,
            verification,
            tuple(ranks),
            query_kind,
            self.map_kind,
        )

    def localize(
        self,
        points: np.ndarray,
        *,
        preprocess: bool | None = None,
        top_n: int = 5,
        limits: Limits | None = None,
        verify: bool | None = None,
        scale: float | None = None,
        kind: str | None = None,
        prior: Prior | None = None,
    ) -> Answer:
        """The ``top_n`` map places nearest to one cloud: exactly 4096 points in [-1, 1]
        float [4096, 3], or with ``preprocess`` a raw scan float [N, 3] in metres, as a
        :class:`Query` checked against ``limits`` (default :class:`Limits`) and run inline
        (:func:`~.run.run`). ``kind``: ``submap``, ``scan`` or ``window`` (told by
        ``preprocess`` when absent). ``verify``: register the top candidates and re-rank them
        (default: when the bundle carries geometry); ``scale``: metres per unit of a
        preprocessed cloud, for a metric pose (estimated when not given). ``prior``: where
        the raw scan's sensor is thought to be (:class:`~..verify.prior.Prior`): the scan is
        registered to the map entries near it instead of searched for (:meth:`register_near`)."""
        t0 = time.perf_counter()
        if prior is not None and kind is None and preprocess is None:
            preprocess = True  # a prior is a sensor's pose: the cloud is its raw scan
        query = Query.make(
            points,
            limits=limits,
            preprocess=preprocess,
            kind=kind,
            top_n=top_n,
            verify=verify,
            scale=scale,
            prior=prior,
        )
        return run_inline(run(self, query, INLINE, t0=t0))

    def _embed_and_search(
        self, clouds: np.ndarray, k: int
    ) -> tuple[np.ndarray, np.ndarray, float, float]:
        """float32 [B, 4096, 3] -> (distances [B, k], ids [B, k], embed s, search s)."""
        t0 = time.perf_counter()
        desc = np.asarray(self.encoder.embed(clouds), dtype=np.float32)
        t1 = time.perf_counter()
        faiss_threads_here()
        distances, ids = self.bundle.search(desc, k)
        return distances, ids, t1 - t0, time.perf_counter() - t1
