"""Request and response schemas, for the OpenAPI document and for clients.

The handlers parse bodies themselves (JSON, raw float arrays and ``.npy`` share one endpoint),
so these models describe the JSON forms; :mod:`pnvlad_service.server.service` enforces them.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

Point = Annotated[list[float], Field(min_length=3, max_length=3)]


class LocalizeRequest(BaseModel):
    """One query cloud."""

    model_config = ConfigDict(extra="forbid")

    points: list[Point] = Field(
        ...,
        min_length=1,
        description="Exactly 4096 preprocessed points in the benchmark's normalised frame "
        "([-1, 1]), or with preprocess=true a raw scan (sensor frame, metres) of any size up "
        "to the server's limit.",
    )
    top_n: int = Field(5, ge=1, description="Matches to return (at most the server's max_top_n).")
    preprocess: bool = Field(False, description="Run the filter G on a raw scan first.")


class BatchQuery(BaseModel):
    """One cloud of a batch."""

    model_config = ConfigDict(extra="forbid")

    points: list[Point] = Field(..., min_length=1)
    preprocess: bool = False


class BatchRequest(BaseModel):
    """Several clouds, embedded as one batch."""

    model_config = ConfigDict(extra="forbid")

    queries: list[BatchQuery] = Field(..., min_length=1)
    top_n: int = Field(5, ge=1)


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


#: Fewest raw points the filter G accepts by default (``GConfig.min_points``); a scan can still
#: be refused (422) when, e.g., ground removal leaves too few.
RAW_MIN_POINTS = 16
#: Largest |coordinate| of a raw scan, metres (``service.MAX_RAW_COORD``).
RAW_MAX_COORD = 100_000.0


def _points_schema(min_items: int, max_items: int, bound: float | None) -> dict[str, Any]:
    coord: dict[str, Any] = {"type": "number"}
    if bound is not None:
        coord.update(minimum=-bound, maximum=bound)
    return {
        "type": "array",
        "minItems": min_items,
        "maxItems": max_items,
        "items": {"type": "array", "minItems": 3, "maxItems": 3, "items": coord},
    }


def cloud_schema(max_raw_points: int, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """JSON Schema of one cloud: exactly 4096 points in [-1, 1] (``preprocess`` false or
    absent) or a raw scan of 16 to ``max_raw_points`` points with ``preprocess: true``."""
    extra = extra or {}
    pre = {
        "type": "object",
        "additionalProperties": False,
        "required": ["points"],
        "properties": {
            "points": _points_schema(4096, 4096, 1.0),
            "preprocess": {"type": "boolean", "enum": [False]},
            **extra,
        },
    }
    raw = {
        "type": "object",
        "additionalProperties": False,
        "required": ["points", "preprocess"],
        "properties": {
            "points": _points_schema(RAW_MIN_POINTS, max_raw_points, RAW_MAX_COORD),
            "preprocess": {"type": "boolean", "enum": [True]},
            **extra,
        },
    }
    return {"oneOf": [pre, raw]}


def localize_request_schema(max_top_n: int, max_raw_points: int) -> dict[str, Any]:
    """The JSON body of ``POST /localize`` (see :class:`LocalizeRequest`)."""
    top_n = {"type": "integer", "minimum": 1, "maximum": max_top_n, "default": 5}
    doc = cloud_schema(max_raw_points, {"top_n": top_n})
    doc["description"] = LocalizeRequest.model_fields["points"].description
    return doc


def batch_request_schema(max_top_n: int, max_raw_points: int, max_queries: int) -> dict[str, Any]:
    """The JSON body of ``POST /localize/batch`` (see :class:`BatchRequest`)."""
    return {
        "type": "object",
        "additionalProperties": False,
        "required": ["queries"],
        "properties": {
            "queries": {
                "type": "array",
                "minItems": 1,
                "maxItems": max_queries,
                "items": cloud_schema(max_raw_points),
            },
            "top_n": {"type": "integer", "minimum": 1, "maximum": max_top_n, "default": 5},
        },
    }
