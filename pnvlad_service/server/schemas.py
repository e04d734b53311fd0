"""Response schemas, for the OpenAPI document and for clients.

The routes write the answers themselves (``Answer.to_json``); these models document them.
``Timings``, ``ModelOut`` and ``IndexOut`` are made from the localiser's dataclasses
(:mod:`pnvlad_service.localization.localizer`), so the answer and its schema have one list of
fields. The request models live in :mod:`pnvlad_service.server.contract`, where they validate.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from pydantic import BaseModel, Field, create_model

from pnvlad_service.localization import localizer


def _json_model(dc: type, name: str, doc: str | None = None, **defaults: Any) -> type[BaseModel]:
    """A response model named ``name`` with the fields of the dataclass ``dc`` as its JSON has
    them: the same names in the same order, the same types and defaults (``defaults``: a
    default the JSON form has and the dataclass does not)."""
    hints = typing.get_type_hints(dc)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(dc):
        default = f.default if f.default is not dataclasses.MISSING else ...
        fields[f.name] = (hints[f.name], defaults.get(f.name, default))
    return create_model(name, __doc__=doc, __module__=__name__, **fields)


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


#: ``Timings.to_json``: milliseconds per stage.
Timings = _json_model(localizer.Timings, "Timings", "Milliseconds spent per stage.")
ModelOut = _json_model(localizer.ModelInfo, "ModelOut", arch=None)
IndexOut = _json_model(localizer.IndexInfo, "IndexOut")


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
