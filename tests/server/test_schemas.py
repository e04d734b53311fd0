"""server.schemas: the response models made from the localiser's dataclasses document what the
routes write (``Answer.to_json`` with ``LocalizerInfo.to_json``), field for field."""

from __future__ import annotations

import dataclasses

from pnvlad_service.index.bundle import Match
from pnvlad_service.localization.query.answers import (
    Answer,
    IndexInfo,
    LocalizerInfo,
    ModelInfo,
    Timings,
)
from pnvlad_service.server import schemas


def test_the_models_have_the_dataclasses_fields_in_order() -> None:
    for model, dc in (
        (schemas.Timings, Timings),
        (schemas.ModelOut, ModelInfo),
        (schemas.IndexOut, IndexInfo),
    ):
        assert list(model.model_fields) == [f.name for f in dataclasses.fields(dc)]


def test_the_schemas_as_the_openapi_document_has_them() -> None:
    timings = schemas.Timings.model_json_schema()
    assert timings["title"] == "Timings"
    assert timings["description"] == "Milliseconds spent per stage."
    stages = ["parse", "preprocess", "queue", "embed", "search", "verify", "total"]
    assert list(timings["properties"]) == stages
    assert all(
        timings["properties"][s] == {"default": 0.0, "title": s.title(), "type": "number"}
        for s in stages
    )
    assert "required" not in timings
    model = schemas.ModelOut.model_json_schema()
    assert "description" not in model
    assert model["required"] == ["weights_sha256", "config_sha256", "dim"]
    assert model["properties"]["arch"]["default"] is None
    assert model["properties"]["dim"]["type"] == "integer"
    index = schemas.IndexOut.model_json_schema()
    assert index["required"] == ["id", "key", "count"]
    assert [p["type"] for p in index["properties"].values()] == ["string", "string", "integer"]


def test_an_answer_validates_against_the_response_model_and_round_trips() -> None:
    match = Match(1, 7, "oxford/r/1", "oxford", "r", 1, 5.0, 6.0, "", "r/1.bin", 0.25)
    answer = Answer((match,), 3, Timings(parse=0.001, embed=0.0025, total=0.004))
    info = LocalizerInfo(ModelInfo("a" * 64, "b" * 64, None, 16), IndexInfo("c" * 16, "Flat", 32))
    doc = {**answer.to_json(), **info.to_json()}
    parsed = schemas.LocalizeResponse.model_validate(doc)
    assert parsed.model_dump() == doc
    assert doc["timings_ms"] == {
        "parse": 1.0,
        "preprocess": 0.0,
        "queue": 0.0,
        "embed": 2.5,
        "search": 0.0,
        "verify": 0.0,
        "total": 4.0,
    }
    assert doc["model"] == {
        "weights_sha256": "a" * 64,
        "config_sha256": "b" * 64,
        "arch": None,
        "dim": 16,
    }
