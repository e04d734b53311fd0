"""Server settings: environment variables with the prefix ``PNVLAD_`` (e.g. ``PNVLAD_INDEX``).

``pnvlad serve`` turns its options into these variables, so a container or a process manager
configures the service the same way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict

from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.localization.query.batching import Batching
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.localization.verify.prior import PriorConfig
from pnvlad_service.localization.verify.verify import DEFAULT_CANDIDATES, VerifyConfig


class ServerSettings(BaseSettings):
    """Everything the HTTP service reads at start-up."""

    model_config = SettingsConfigDict(env_prefix="PNVLAD_", extra="ignore")

    index: Path | None = Field(None, description="Index bundle directory (pnvlad index build).")
    checkpoint: Path | None = Field(
        None,
        description="Model checkpoint directory; default: the one recorded in the bundle. "
        "Its weights must be the ones the bundle was built with.",
    )
    host: str = Field("127.0.0.1", description="Interface to bind (loopback unless told).")
    port: int = Field(8000, ge=0, le=65535)
    workers: int = Field(1, ge=1, description="Server processes (each loads model and index).")
    api_key: SecretStr | None = Field(
        None, description="When set, /localize* and /info need 'Authorization: Bearer <key>'."
    )
    admin_key: SecretStr | None = Field(
        None,
        description="Bearer token of POST /admin/reload; default: the API key. With neither "
        "set, the admin route answers 403 (SIGHUP still reloads).",
    )
    reload_drain_s: float = Field(
        30.0,
        gt=0,
        description="How long a reload waits for the queries on the old bundle before closing "
        "it (seconds).",
    )
    max_body_bytes: int = Field(
        32 * 1024 * 1024, ge=1024, description="Largest request body accepted (bytes)."
    )
    max_raw_points: int = Field(
        Limits.max_raw_points,
        ge=SUBMAP_POINTS,
        description="Most points of a raw scan sent with preprocess=true.",
    )
    max_top_n: int = Field(
        Limits.max_top_n, ge=1, description="Largest top_n a request may ask for."
    )
    max_batch_queries: int = Field(
        Limits.max_batch_queries, ge=1, description="Most queries in /localize/batch."
    )
    batch_max_size: int = Field(
        Batching.max_size, ge=1, description="Most clouds embedded in one batch."
    )
    batch_wait_ms: float = Field(
        Batching.wait_ms,
        ge=0.0,
        le=100.0,
        description="How long the batcher waits for requests already being parsed (ms).",
    )
    batch_lanes: int = Field(
        Batching.lanes,
        ge=1,
        le=16,
        description="Batches in flight at once: with 2 the next batch is embedded while the "
        "previous one finishes its head, search and answers.",
    )
    warm_up: int = Field(
        8,
        ge=0,
        le=256,
        description="Batch sizes 1..this embedded once at start-up, so that no request pays "
        "for the first forward pass of its batch size (0: none).",
    )
    runtime: Literal["auto", "torch", "onnx"] = Field(
        "auto",
        description="What embeds: torch, or ONNX Runtime on the model directory's model.onnx "
        "(pnvlad model export); auto: torch when it is installed, else ONNX Runtime.",
    )
    threads: int | None = Field(
        None,
        ge=1,
        description="Encoder threads: ONNX Runtime's, or torch's intra-op threads (default: "
        "the CPUs of the process for ONNX Runtime, torch's own default).",
    )
    torch_threads: int | None = Field(
        None, ge=1, description="torch intra-op threads (PNVLAD_THREADS sets both runtimes')."
    )
    faiss_threads: int | None = Field(
        1,
        ge=1,
        description="FAISS OpenMP threads. 1 by default: searches are small batches, which gain "
        "nothing from threads and stall when the cores are busy (docs/SERVICE.md).",
    )
    device: str | None = Field(None, description="torch device for the encoder (default cpu).")
    verify_bundle: bool = Field(True, description="Check the bundle's sha256s at start-up.")
    rerank: int = Field(
        DEFAULT_CANDIDATES,
        ge=1,
        le=100,
        description="Candidates registered to each query and re-ranked (bundles with geometry).",
    )
    verify_threshold: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="Confidence a best match needs to count as verified. Default: the one "
        "chosen for the model's weights on training-layout submaps (MODEL/verification.json, "
        "written by pnvlad eval --rerank K --save-threshold), else "
        f"{VerifyConfig.threshold} (docs/VERIFY.md).",
    )

    verify_stop_score: float | None = Field(
        VerifyConfig.stop_score,
        ge=0.0,
        le=1.0,
        description="Candidates are registered in retrieval order, one at a time; the rest are "
        "skipped once one scores this within the place radius (1: register all).",
    )
    verify_alone_score: float = Field(
        VerifyConfig.alone_score if VerifyConfig.alone_score is not None else 1.0,
        ge=0.0,
        le=1.0,
        description="The cascade always registers a second candidate (the rival the "
        "confidence weighs), unless the first scores this within the place radius and pins "
        "the translation (1: always a second).",
    )
    verify_cache: int = Field(
        VerifyConfig.cache_entries,
        ge=0,
        description="Prepared candidate clouds kept in memory (about 1 MB each; 0: none).",
    )

    verify_crowded_threads: int = Field(
        VerifyConfig.crowded_threads or 0,
        ge=0,
        le=64,
        description="small_gicp threads a registration gets while other queries are being "
        "embedded or verified (the cores are taken; 2 otherwise). 0: always 2.",
    )

    verify_process: bool = Field(
        True,
        description="Register in a child process: small_gicp holds the GIL, so in the "
        "server's process a registration stops the threads that embed and answer.",
    )

    max_prior_radius: float = Field(
        Limits.max_prior_radius_m,
        gt=0.0,
        le=1000.0,
        description="Largest radius (metres) a request with a prior pose may ask the map to "
        "be searched within.",
    )
    prior_radius: float = Field(
        Limits.default_prior_radius_m,
        gt=0.0,
        le=1000.0,
        description="Radius (metres) of a prior pose that gives none (docs/TRACKING.md).",
    )
    prior_min_fitness: float = Field(
        PriorConfig.min_fitness,
        ge=0.0,
        le=1.0,
        description="Share of a scan's points on the map after registration near a prior at "
        "or above which its pose is verified (docs/TRACKING.md).",
    )
    prior_max_sigma: float = Field(
        PriorConfig.max_sigma_m or 0.0,
        ge=0.0,
        description="Largest horizontal standard deviation (metres) of a pose registered near "
        "a prior that is still verified (0: not checked).",
    )
    prior_max_submaps: int = Field(
        PriorConfig.max_submaps,
        ge=1,
        le=64,
        description="Map entries near a prior (of one drive) laid together and registered to.",
    )

    def prior_config(self) -> PriorConfig:
        """How a scan is registered near a prior pose."""
        return PriorConfig(
            max_submaps=self.prior_max_submaps,
            min_fitness=self.prior_min_fitness,
            max_sigma_m=self.prior_max_sigma or None,
        )

    def verify_config(self) -> VerifyConfig:
        """How candidates are verified, but for the threshold: ``Localizer.load`` takes
        ``verify_threshold``, else the model's calibration (see :func:`..app.load_localizer`)."""
        return VerifyConfig(
            candidates=self.rerank,
            stop_score=self.verify_stop_score,
            alone_score=self.verify_alone_score if self.verify_alone_score < 1.0 else None,
            cache_entries=self.verify_cache,
            crowded_threads=self.verify_crowded_threads or None,
        )

    def limits(self) -> Limits:
        """The request limits these settings configure (the rest are the format's)."""
        return Limits(
            max_raw_points=self.max_raw_points,
            max_top_n=self.max_top_n,
            max_batch_queries=self.max_batch_queries,
            max_prior_radius_m=self.max_prior_radius,
            default_prior_radius_m=min(self.prior_radius, self.max_prior_radius),
        )

    def batching(self) -> Batching:
        """The micro-batcher's configuration."""
        return Batching(
            max_size=self.batch_max_size, wait_ms=self.batch_wait_ms, lanes=self.batch_lanes
        )
