"""Server settings: environment variables with the prefix ``PNVLAD_`` (e.g. ``PNVLAD_INDEX``).

``pnvlad serve`` turns its options into these variables, so a container or a process manager
configures the service the same way. The settings of the localiser are the fields of its
config's sections (:mod:`pnvlad_service.localization.query.config`), each under the name the
server reads (``PNVLAD_VERIFY_THRESHOLD`` is ``VerifySection.threshold``);
:meth:`ServerSettings.localizer_config` puts them back together.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, SecretStr
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, SettingsConfigDict

from pnvlad_service.io.submap import SUBMAP_POINTS
from pnvlad_service.localization.query.batching import Batching
from pnvlad_service.localization.query.config import (
    BatchSection,
    EncoderSection,
    LocalizerConfig,
    PriorSection,
    VerifySection,
)
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.localization.verify.prior import PriorConfig
from pnvlad_service.localization.verify.verify import VerifyConfig


def section_field(section: type[BaseModel], name: str, **overrides: Any) -> Any:
    """The field ``name`` of a localiser config's ``section`` (its type's bounds, default and
    description), as a setting of its own (``overrides``: e.g. another default)."""
    field = section.model_fields[name]
    return FieldInfo.merge_field_infos(field, **overrides) if overrides else field


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
    foxglove: str | None = Field(
        None,
        description="HOST:PORT: stream each answered query live to Foxglove (the 'view' "
        "extra; docs/TRACKING.md).",
    )
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
    batch_max_size: int = section_field(BatchSection, "max_size")
    batch_wait_ms: float = section_field(BatchSection, "wait_ms")
    batch_lanes: int = section_field(BatchSection, "lanes")
    warm_up: int = Field(
        8,
        ge=0,
        le=256,
        description="Batch sizes 1..this embedded once at start-up, so that no request pays "
        "for the first forward pass of its batch size (0: none).",
    )
    runtime: Literal["auto", "torch", "onnx"] = section_field(EncoderSection, "runtime")
    threads: int | None = section_field(EncoderSection, "threads")
    torch_threads: int | None = Field(
        None, ge=1, description="torch intra-op threads (PNVLAD_THREADS sets both runtimes')."
    )
    faiss_threads: int | None = Field(
        1,
        ge=1,
        description="FAISS OpenMP threads. 1 by default: searches are small batches, which gain "
        "nothing from threads and stall when the cores are busy (docs/SERVICE.md).",
    )
    device: str | None = section_field(EncoderSection, "device")
    verify_bundle: bool = section_field(LocalizerConfig, "check_bundle")
    rerank: int = section_field(VerifySection, "candidates")
    verify_threshold: float | None = section_field(VerifySection, "threshold")
    verify_stop_score: float | None = section_field(VerifySection, "stop_score")
    verify_alone_score: float = section_field(VerifySection, "alone_score")
    verify_cache: int = section_field(VerifySection, "cache")
    verify_crowded_threads: int = section_field(VerifySection, "crowded_threads")
    verify_process: bool = section_field(VerifySection, "process", default=True)

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
    prior_min_fitness: float = section_field(PriorSection, "min_fitness")
    prior_max_sigma: float = section_field(PriorSection, "max_sigma")
    prior_max_submaps: int | None = section_field(PriorSection, "max_submaps")
    prior_same_run: bool | None = section_field(PriorSection, "same_run")
    prior_retry_submaps: int | None = section_field(PriorSection, "retry_submaps")
    prior_aligned_map: bool | None = section_field(PriorSection, "aligned_map")

    def localizer_config(self) -> LocalizerConfig:
        """How the localiser is loaded: these settings' sections (``index`` and the model
        aside)."""
        return LocalizerConfig(
            encoder=EncoderSection(
                runtime=self.runtime,
                threads=self.threads or self.torch_threads,
                device=self.device,
            ),
            verify=VerifySection(
                candidates=self.rerank,
                threshold=self.verify_threshold,
                stop_score=self.verify_stop_score,
                alone_score=self.verify_alone_score,
                cache=self.verify_cache,
                crowded_threads=self.verify_crowded_threads,
                process=self.verify_process,
            ),
            prior=PriorSection(
                min_fitness=self.prior_min_fitness,
                max_sigma=self.prior_max_sigma,
                max_submaps=self.prior_max_submaps,
                same_run=self.prior_same_run,
                retry_submaps=self.prior_retry_submaps,
                aligned_map=self.prior_aligned_map,
            ),
            batching=BatchSection(
                max_size=self.batch_max_size, wait_ms=self.batch_wait_ms, lanes=self.batch_lanes
            ),
            check_bundle=self.verify_bundle,
        )

    def prior_config(self, aligned: bool = False) -> PriorConfig:
        """How a scan is registered near a prior pose on a map whose bundle records it as
        ``aligned`` or not (what the settings leave unset follows it)."""
        return self.localizer_config().prior.config(aligned)

    def verify_config(self) -> VerifyConfig:
        """How candidates are verified, but for the threshold: ``Localizer.load`` takes
        ``verify_threshold``, else the model's calibration (see :func:`..app.load_localizer`)."""
        return self.localizer_config().verify.config()

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
        return self.localizer_config().batching.config()  # type: ignore[union-attr]
