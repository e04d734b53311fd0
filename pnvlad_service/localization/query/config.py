"""How a :class:`~.localizer.Localizer` is loaded: one :class:`LocalizerConfig` with sections.

- :class:`EncoderSection`: what embeds (runtime, threads, device);
- :class:`VerifySection`: how candidates are verified, and where (in a child process or not);
- :class:`PriorSection`: how a scan is registered near a prior pose;
- :class:`BatchSection`: the micro-batcher (``None``: each query embedded in its caller).

The server's settings (``pnvlad_service.server.settings.ServerSettings``) are made of the same
sections: each of their fields is one of a section's, under the environment name the server
has always read (``PNVLAD_VERIFY_THRESHOLD`` is :attr:`VerifySection.threshold`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from pnvlad_service.localization.query.batching import Batching
from pnvlad_service.localization.verify.prior import (
    ALIGNED_ENTRIES,
    ALIGNED_RETRY_ENTRIES,
    RETRY_MARGIN,
    RETRY_MAX_CORRECTION_M,
    PriorConfig,
)
from pnvlad_service.localization.verify.verify import DEFAULT_CANDIDATES, VerifyConfig

_FROZEN = ConfigDict(frozen=True, extra="forbid")


class EncoderSection(BaseModel):
    """What embeds the clouds."""

    model_config = _FROZEN

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
    device: str | None = Field(None, description="torch device for the encoder (default cpu).")


class VerifySection(BaseModel):
    """How the retrieved candidates are verified (bundles with geometry), and where."""

    model_config = _FROZEN

    candidates: int = Field(
        DEFAULT_CANDIDATES,
        ge=1,
        le=100,
        description="Candidates registered to each query and re-ranked (bundles with geometry).",
    )
    threshold: float | None = Field(
        None,
        ge=0.0,
        le=1.0,
        description="Confidence a best match needs to count as verified. Default: the one "
        "chosen for the model's weights on training-layout submaps (MODEL/verification.json, "
        "written by pnvlad eval --rerank K --save-threshold), else "
        f"{VerifyConfig.threshold} (docs/VERIFY.md).",
    )
    stop_score: float | None = Field(
        VerifyConfig.stop_score,
        ge=0.0,
        le=1.0,
        description="Candidates are registered in retrieval order, one at a time; the rest are "
        "skipped once one scores this within the place radius (1: register all).",
    )
    alone_score: float = Field(
        VerifyConfig.alone_score if VerifyConfig.alone_score is not None else 1.0,
        ge=0.0,
        le=1.0,
        description="The cascade always registers a second candidate (the rival the "
        "confidence weighs), unless the first scores this within the place radius and pins "
        "the translation (1: always a second).",
    )
    cache: int = Field(
        VerifyConfig.cache_entries,
        ge=0,
        description="Prepared candidate clouds kept in memory (about 1 MB each; 0: none).",
    )
    crowded_threads: int = Field(
        VerifyConfig.crowded_threads or 0,
        ge=0,
        le=64,
        description="small_gicp threads a registration gets while other queries are being "
        "embedded or verified (the cores are taken; 2 otherwise). 0: always 2.",
    )
    process: bool = Field(
        False,
        description="Register in a child process: small_gicp holds the GIL, so in the "
        "server's process a registration stops the threads that embed and answer.",
    )

    def config(self, threshold: float | None = None) -> VerifyConfig:
        """The verification's :class:`VerifyConfig`, with ``threshold`` (default: this
        section's, else the config's default)."""
        threshold = self.threshold if threshold is None else threshold
        return VerifyConfig(
            candidates=self.candidates,
            threshold=VerifyConfig.threshold if threshold is None else threshold,
            stop_score=self.stop_score,
            alone_score=self.alone_score if self.alone_score < 1.0 else None,
            cache_entries=self.cache,
            crowded_threads=self.crowded_threads or None,
        )

    @classmethod
    def of(cls, config: VerifyConfig, **rest: object) -> VerifySection:
        """The section of a :class:`VerifyConfig` (its tunable fields) and ``rest``."""
        return cls(
            candidates=config.candidates,
            threshold=config.threshold,
            stop_score=config.stop_score,
            alone_score=1.0 if config.alone_score is None else config.alone_score,
            cache=config.cache_entries,
            crowded_threads=config.crowded_threads or 0,
            **rest,  # type: ignore[arg-type]
        )


class PriorSection(BaseModel):
    """How a raw scan is registered near a prior pose (docs/TRACKING.md)."""

    model_config = _FROZEN

    min_fitness: float = Field(
        PriorConfig.min_fitness,
        ge=0.0,
        le=1.0,
        description="Share of a scan's points on the map after registration near a prior at "
        "or above which its pose is verified (docs/TRACKING.md).",
    )
    max_sigma: float = Field(
        PriorConfig.max_sigma_m or 0.0,
        ge=0.0,
        description="Largest horizontal standard deviation (metres) of a pose registered near "
        "a prior that is still verified (0: not checked).",
    )
    max_submaps: int | None = Field(
        None,
        ge=1,
        le=64,
        description="Map entries near a prior laid together and registered to. Default: "
        f"{ALIGNED_ENTRIES} of any drive on a map the bundle records as aligned (pnvlad map "
        f"align), {PriorConfig.max_submaps} of one drive on another.",
    )
    same_run: bool | None = Field(
        None,
        description="Register to the entries of one drive of the map only (false: of any "
        "drive, for a map whose drives agree). Default: false on a map the bundle records as "
        "aligned (pnvlad map align), true on another (docs/TRACKING.md).",
    )
    aligned_map: bool | None = Field(
        None,
        description="Whether the map's drives agree (pnvlad map align), which sets what the "
        "other prior fields leave unset. Default: as the bundle records.",
    )
    retry_submaps: int | None = Field(
        None,
        ge=0,
        le=64,
        description="A registration near a prior that fits under min_fitness is tried once "
        "more against this many nearest entries, a wider stretch of the map, and verified when "
        f"it fits at min_fitness{f' + {RETRY_MARGIN:g}' if RETRY_MARGIN else ''} within "
        f"{RETRY_MAX_CORRECTION_M:g} m of the prior (0: never). "
        f"Default: {ALIGNED_RETRY_ENTRIES} on a map the bundle records as aligned, 0 on another.",
    )

    def aligned(self, recorded: bool) -> bool:
        """Whether the map is taken as aligned: ``aligned_map``, else what the bundle
        ``recorded``."""
        return recorded if self.aligned_map is None else self.aligned_map

    def config(self, aligned: bool = False) -> PriorConfig:
        """The registration's :class:`PriorConfig`; what the section leaves unset follows
        ``aligned``, whether the bundle records its map's drives as agreeing (its
        ``map.alignment``), or ``aligned_map`` when set."""
        aligned = self.aligned(aligned)
        max_submaps = self.max_submaps or (ALIGNED_ENTRIES if aligned else PriorConfig.max_submaps)
        retry = self.retry_submaps
        if retry is None:
            retry = ALIGNED_RETRY_ENTRIES if aligned and max_submaps < ALIGNED_RETRY_ENTRIES else 0
        return PriorConfig(
            max_submaps=max_submaps,
            same_run=(not aligned) if self.same_run is None else self.same_run,
            min_fitness=self.min_fitness,
            max_sigma_m=self.max_sigma or None,
            retry_submaps=retry,
        )


class BatchSection(BaseModel):
    """The micro-batcher: concurrent callers' clouds embedded together."""

    model_config = _FROZEN

    max_size: int = Field(Batching.max_size, ge=1, description="Most clouds embedded in one batch.")
    wait_ms: float = Field(
        Batching.wait_ms,
        ge=0.0,
        le=100.0,
        description="How long the batcher waits for requests already being parsed (ms).",
    )
    lanes: int = Field(
        Batching.lanes,
        ge=1,
        le=16,
        description="Batches in flight at once: with 2 the next batch is embedded while the "
        "previous one finishes its head, search and answers.",
    )

    def config(self) -> Batching:
        return Batching(max_size=self.max_size, wait_ms=self.wait_ms, lanes=self.lanes)


class LocalizerConfig(BaseModel):
    """Everything :meth:`~.localizer.Localizer.load` reads, by section; ``check_bundle``:
    check the bundle's files against their sha256 at load."""

    model_config = _FROZEN

    encoder: EncoderSection = EncoderSection()
    verify: VerifySection = VerifySection()
    prior: PriorSection = PriorSection()
    batching: BatchSection | None = None
    check_bundle: bool = Field(True, description="Check the bundle's sha256s at start-up.")
