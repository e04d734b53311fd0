"""Response schemas, for the OpenAPI document and for clients.

The routes write the answers themselves (``Answer.to_json``); these models document them.
The request models live in :mod:`pnvlad_service.server.contract`, where they validate.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class MatchOut(BaseModel):
    """A database submap, nearest first; distance is Euclidean in descriptor space."""

    rank: int
    submap_id: str
    dataset: str
    run: str
    timestamp: int = Field(..., description="Microseconds.")
    northing: float = Field(..., description="UTM metres.")
    easting: float = Field(..., description="UTM metres.")
    utm_zone: str | None = None
    distance: float | None


class Timings(BaseModel):
    """Milliseconds spent per stage."""

    parse: float = 0.0
    preprocess: float = 0.0
    queue: float = 0.0
    embed: float = 0.0
    search: float = 0.0
    total: float = 0.0


class ModelOut(BaseModel):
    weights_sha256: str
    config_sha256: str
    arch: str | None = None
    dim: int


class IndexOut(BaseModel):
    id: str
    key: str
    count: int


class LocalizeResponse(BaseModel):
    matches: list[MatchOut]
    timings_ms: Timings
    batch_size: int = Field(..., description="Clouds embedded together with this one.")
    model: ModelOut
    index: IndexOut


class BatchItem(BaseModel):
    matches: list[MatchOut]
    timings_ms: Timings
    batch_size: int


class BatchResponse(BaseModel):
    results: list[BatchItem]
    timings_ms: Timings
    model: ModelOut
    index: IndexOut


class Health(BaseModel):
    status: str


class Info(BaseModel):
    manifest: dict[str, Any]
    model: dict[str, Any]
    limits: dict[str, Any]
