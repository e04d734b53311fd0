"""The request contract: the OpenAPI request schema states exactly what validation accepts.

Bodies at and just past every limit (points per cloud, raw points, coordinate bounds, top_n,
queries per batch) and of every wrong shape are checked two ways: against the JSON Schema the
server publishes in /openapi.json, and by the server (or the parser) itself; a body must be
schema-valid exactly when it is accepted. The schema is read with a small validator of the
keywords it uses (any other keyword fails the test, so the validator cannot silently fall
behind the schema); "integer" means a JSON integer literal (JSON Schema draft 4), as the
server has always read ``top_n``.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.limits import Limits
from pnvlad_service.server.contract import Contract
from tests.index.helpers import make_world

IGNORED = {"title", "description", "default", "format"}
TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "boolean": lambda v: isinstance(v, bool),
    "string": lambda v: isinstance(v, str),
    "null": lambda v: v is None,
}


def valid(schema: dict[str, Any], v: Any) -> bool:
    """Whether ``v`` (a ``json.loads`` value) is valid against ``schema``."""
    unknown = set(schema) - IGNORED - {
        "type", "properties", "required", "additionalProperties", "items", "minItems",
        "maxItems", "minimum", "maximum", "enum", "oneOf", "anyOf", "exclusiveMinimum",
        "minLength", "maxLength",
    }  # fmt: skip
    assert not unknown, f"the test's validator does not know {unknown}"
    if "oneOf" in schema and sum(valid(s, v) for s in schema["oneOf"]) != 1:
        return False
    if "anyOf" in schema and not any(valid(s, v) for s in schema["anyOf"]):
        return False
    if "type" in schema and not TYPES[schema["type"]](v):
        return False
    if "enum" in schema and not any(
        v is e or (v == e and type(v) is type(e)) for e in schema["enum"]
    ):
        return False
    number = isinstance(v, (int, float)) and not isinstance(v, bool)
    lo, hi = schema.get("minimum", -math.inf), schema.get("maximum", math.inf)
    if number and (math.isnan(v) or not lo <= v <= hi):
        return False
    if number and "exclusiveMinimum" in schema and not v > schema["exclusiveMinimum"]:
        return False
    if isinstance(v, str) and not schema.get("minLength", 0) <= len(v) <= schema.get(
        "maxLength", math.inf
    ):
        return False
    if isinstance(v, list):
        if not schema.get("minItems", 0) <= len(v) <= schema.get("maxItems", math.inf):
            return False
        if "items" in schema and not all(valid(schema["items"], x) for x in v):
            return False
    if isinstance(v, dict):
        props = schema.get("properties", {})
        if any(k not in v for k in schema.get("required", [])):
            return False
        if schema.get("additionalProperties") is False and set(v) - set(props):
            return False
        return all(valid(props[k], x) for k, x in v.items() if k in props)
    return True


# -- through the server, at the real limits ---------------------------------------------------

TOP, RAW, QUERIES = 3, 4096, 2


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    """(test client, /localize JSON schema, /localize/batch JSON schema) of a real app."""
    from fastapi.testclient import TestClient

    from pnvlad_service.server.app import create_app
    from pnvlad_service.server.settings import ServerSettings

    bundle = make_world(tmp_path_factory.mktemp("contract"))["bundle"]
    s = ServerSettings(index=bundle, max_raw_points=RAW, max_top_n=TOP, max_batch_queries=QUERIES)
    with TestClient(create_app(s)) as c:
        paths = c.get("/openapi.json").json()["paths"]
        schemas = [
            paths[p]["post"]["requestBody"]["content"]["application/json"]["schema"]
            for p in ("/localize", "/localize/batch")
        ]
        yield c, *schemas


def accepted(client, path: str, doc: Any) -> bool:
    """The server took the body: 200, or refused only by the filter G after validation (a
    raw scan that ground removal leaves too small: the one rule a schema cannot state)."""
    r = client.post(path, content=json.dumps(doc), headers={"content-type": "application/json"})
    assert r.status_code in (200, 422), r.text
    return r.status_code == 200 or "filter G:" in r.json()["detail"]


def pre_cloud(n: int = 4096, value: float = 0.5) -> list[list[float]]:
    pts = np.random.default_rng(n).uniform(-0.9, 0.9, (n, 3))
    if n:
        pts[n // 2, 1] = value
    return pts.tolist()


def raw_cloud(n: int, value: float = 3.0) -> list[list[float]]:
    """A raw scan of ``n`` points: walls on a ground plane, metres."""
    rng = np.random.default_rng(n)
    pts = np.c_[
        rng.uniform(-20, 20, (n, 2)), np.where(np.arange(n) % 2, 0.0, rng.uniform(0.5, 3, n))
    ]
    if n:
        pts[n - 1, 0] = value
    return pts.tolist()


BODIES = [
    {"points": pre_cloud()},
    {"points": pre_cloud(4095)},
    {"points": pre_cloud(4097)},
    {"points": pre_cloud(value=1.0001)},
    {"points": pre_cloud(value=-1.0001)},
    {"points": pre_cloud(value=1.00011)},
    {"points": pre_cloud(value=-1.0002)},
    {"points": pre_cloud(), "preprocess": False},
    {"points": pre_cloud(), "preprocess": True},  # a raw scan of 4096 points in [-1, 1]: fine
    {"points": raw_cloud(RAW), "preprocess": True},
    {"points": raw_cloud(RAW + 1), "preprocess": True},
    {"points": raw_cloud(1), "preprocess": True},
    {"points": [], "preprocess": True},
    {"points": raw_cloud(500, 100_000.0), "preprocess": True},
    {"points": raw_cloud(500, -100_000.0), "preprocess": True},
    {"points": raw_cloud(500, 100_000.5), "preprocess": True},
    {"points": raw_cloud(500)},
    *({"points": pre_cloud(), "top_n": n} for n in (0, 1, TOP, TOP + 1, 2.5, True, "2")),
    {"points": pre_cloud(), "preprocess": "yes"},
    {"points": pre_cloud(), "preprocess": None},
    {"points": pre_cloud(), "extra": 1},
    {"points": [[0.1, 0.2]] * 4096},
    {"points": [[0.1, 0.2, 0.3, 0.4]] * 4096},
    {"points": [[0.1, 0.2, "x"]] * 4096},
    {"points": [[0.1, 0.2, True]] * 4096},
    {"top_n": 1},
    [1, 2, 3],
]


@pytest.mark.parametrize("doc", BODIES, ids=range(len(BODIES)))
def test_localize_schema_valid_iff_accepted(served, doc) -> None:
    client, schema, _ = served
    assert valid(schema, doc) == accepted(client, "/localize", doc), json.dumps(doc)[:200]


def _batch(n: int, **kw: Any) -> dict[str, Any]:
    return {"queries": [{"points": pre_cloud()} for _ in range(n)], **kw}


BATCHES = [
    _batch(1),
    _batch(QUERIES),
    _batch(QUERIES + 1),
    _batch(0),
    *(_batch(1, top_n=n) for n in (0, TOP, TOP + 1)),
    {"queries": [{"points": pre_cloud()}, {"points": raw_cloud(RAW), "preprocess": True}]},
    {"queries": [{"points": pre_cloud()}, {"points": raw_cloud(RAW + 1), "preprocess": True}]},
    {"queries": [{"points": pre_cloud(value=1.00011)}]},
    {"queries": [{"points": pre_cloud(), "top_n": 1}]},
    {"queries": [{"points": pre_cloud()}], "extra": 1},
    {"queries": {"points": pre_cloud()}},
    {"top_n": 2},
]


@pytest.mark.parametrize("doc", BATCHES, ids=range(len(BATCHES)))
def test_batch_schema_valid_iff_accepted(served, doc) -> None:
    client, _, schema = served
    assert valid(schema, doc) == accepted(client, "/localize/batch", doc), json.dumps(doc)[:200]


def test_the_schema_states_each_limit_of_the_settings(served) -> None:
    _, one, batch = served
    pre, raw = one["oneOf"]
    assert (
        pre["properties"]["points"]["minItems"] == pre["properties"]["points"]["maxItems"] == 4096
    )
    assert (raw["properties"]["points"]["minItems"], raw["properties"]["points"]["maxItems"]) == (
        16,  # the filter G's fewest: a scan of fewer is refused before G, as the schema says
        RAW,
    )
    assert pre["properties"]["points"]["items"]["items"]["maximum"] == Limits().bound
    assert raw["properties"]["points"]["items"]["items"]["maximum"] == Limits().max_raw_coord
    assert pre["properties"]["top_n"]["maximum"] == TOP and raw["required"] == [
        "points",
        "preprocess",
    ]
    assert batch["properties"]["queries"]["maxItems"] == QUERIES
    assert "top_n" not in batch["properties"]["queries"]["items"]["oneOf"][0]["properties"]


# -- against the parser, at small limits, with generated bodies --------------------------------

SMALL = Limits(max_raw_points=20, max_top_n=4, max_batch_queries=3, points_per_cloud=8)
CONTRACT = Contract(SMALL)
NEAR = [0.0, 0.5, SMALL.bound, -SMALL.bound, 1.0002, -1.0002, SMALL.max_raw_coord, 100_000.5]
ODD = [True, None, "1", [1.0]]


@st.composite
def clouds(draw: st.DrawFn, top: bool) -> Any:
    """A cloud near the limits: point counts around both, coordinates around both bounds, odd
    values, odd ``preprocess`` and ``top_n``, extra keys; sometimes not an object at all."""
    if draw(st.integers(0, 30)) == 0:
        return draw(st.sampled_from([[], "x", 3, None]))
    pre = draw(st.sampled_from(["absent", "absent", False, True, True, "yes", None, 1]))
    raw = pre is True
    n = draw(st.sampled_from([0, 1, 15, 16, 16, 20, 20, 21] if raw else [7, 8, 8, 8, 9]))
    pts = [[0.25, -0.25, 0.5] for _ in range(n)]
    for _ in range(draw(st.integers(0, 2)) if n else 0):
        i, j = draw(st.integers(0, n - 1)), draw(st.integers(0, 2))
        pts[i][j] = draw(st.sampled_from(NEAR + ODD) | st.floats(-2, 2))
    if n and draw(st.integers(0, 9)) == 0:
        pts[draw(st.integers(0, n - 1))] = draw(st.sampled_from([[0.1, 0.2], [0.1] * 4, 5]))
    doc: dict[str, Any] = {"points": pts}
    if pre != "absent":
        doc["preprocess"] = pre
    if top and draw(st.integers(0, 3)) == 0:
        doc["prior"] = draw(priors())
    if top and draw(st.booleans()):
        doc["top_n"] = draw(
            st.integers(-1, SMALL.max_top_n + 1) | st.sampled_from([2.0, True, "3"])
        )
    if draw(st.integers(0, 9)) == 0:
        doc[draw(st.sampled_from(["extra", "top_n" if not top else "queries"]))] = 1
    return doc


@st.composite
def priors(draw: st.DrawFn) -> Any:
    """A prior pose near its limits: values at and past each bound, odd types, a field
    missing, an extra one; sometimes not an object."""
    if draw(st.integers(0, 15)) == 0:
        return draw(st.sampled_from([None, [], "here", 3]))
    doc: dict[str, Any] = {"northing": 5735000.0, "easting": 620000.0, "yaw_deg": 10.0}
    odd = draw(st.sampled_from(["northing", "easting", "yaw_deg", "height", "radius_m", "run",
                                "extra", None, None]))  # fmt: skip
    values = {
        "northing": [SMALL.max_prior_coord, SMALL.max_prior_coord * 1.01, "1", True],
        "easting": [-SMALL.max_prior_coord, None, 1e300],
        "yaw_deg": [360.0, -360.5, 720.0, None],
        "height": [None, 0.0, SMALL.max_raw_coord, SMALL.max_raw_coord + 1.0, "0"],
        "radius_m": [
            None,
            0.0,
            -1.0,
            1e-9,
            SMALL.max_prior_radius_m,
            SMALL.max_prior_radius_m + 0.5,
            "5",
            True,
        ],
        "run": [None, "", "business/run", "x" * 256, "x" * 257, 3],
        "extra": [1],
    }
    if odd is not None:
        doc[odd] = draw(st.sampled_from(values[odd]))
    if draw(st.integers(0, 9)) == 0:
        del doc[draw(st.sampled_from(["northing", "easting", "yaw_deg"]))]
    return doc


def parses(parse: Any, doc: Any) -> bool:
    try:
        parse(json.dumps(doc).encode())
    except InputError:
        return False
    return True


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(clouds(top=True))
def test_generated_queries_are_schema_valid_iff_parsed(doc: Any) -> None:
    assert valid(CONTRACT.query_schema(), doc) == parses(CONTRACT.parse_query, doc)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.lists(clouds(top=False), max_size=SMALL.max_batch_queries + 1),
    st.none() | st.integers(-1, SMALL.max_top_n + 1),
)
def test_generated_batches_are_schema_valid_iff_parsed(queries: list[Any], top_n: Any) -> None:
    doc: dict[str, Any] = {"queries": queries}
    if top_n is not None:
        doc["top_n"] = top_n
    assert valid(CONTRACT.batch_schema(), doc) == parses(CONTRACT.parse_batch, doc)
