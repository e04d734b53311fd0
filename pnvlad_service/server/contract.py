"""The JSON request contract of ``POST /localize`` and ``POST /localize/batch``.

:func:`request_models` builds, from one :class:`~pnvlad_service.localization.query.limits.Limits`,
the pydantic models that validate JSON bodies (:meth:`Contract.parse_query`,
:meth:`Contract.parse_batch`: ``model_validate_json``, then each cloud made a
:class:`~pnvlad_service.localization.query.query.Query`, whose ``make`` checks a query's rules)
and whose ``model_json_schema()`` is the OpenAPI request schema. The schema of a cloud
is split into its two forms (4096 preprocessed points, or a raw scan with ``preprocess: true``)
with the counts and bounds of the same ``Limits``; tests/server/test_contract.py checks that a
body is schema-valid exactly when it is accepted.

Pydantic's errors are mapped to today's :class:`~pnvlad_service.errors.InputError` field
names and messages, the first one in the order a reader of the body meets them (unknown
fields, a missing field, ``top_n``, ``preprocess``, then the points in order).
"""

from __future__ import annotations

import copy
import functools
import json
from dataclasses import replace
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    WithJsonSchema,
    model_validator,
)

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.limits import MAX_RUN_CHARS, Limits, show_value
from pnvlad_service.localization.query.query import Query


class MalformedJSON(InputError):
    """The body is not JSON at all (400 rather than 422)."""

    problem_kind = "malformed-json"


#: One point: three numbers (validated as a tuple: fast, and a short point is reported as such).
Point = Annotated[
    tuple[float, float, float],
    WithJsonSchema({"type": "array", "minItems": 3, "maxItems": 3, "items": {"type": "number"}}),
]

PRIOR_DOC = (
    "Where the sensor is thought to be (the last fix moved on by odometry): the scan is then "
    "registered to the map entries within radius_m of it, with no retrieval, and the answer is "
    "its pose (mode 'prior'). Raw scans only; refused with verify=false."
)

POINTS_DOC = (
    "Exactly 4096 preprocessed points in the benchmark's normalised frame ([-1, 1]), or with "
    "preprocess=true a raw scan (sensor frame, metres) of any size up to the server's limit; "
    "its points within 0.1 m of the sensor are missing returns written as zeros (Ouster's "
    "drivers) and are dropped: at least 16 others must be left."
)


class Contract:
    """The request models of one :class:`Limits` and the parsing of JSON bodies with them."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        self.query_model, self.batch_model = request_models(limits)

    def parse_query(self, body: bytes) -> Query:
        """``{"points": [[x, y, z], ...], "top_n": 5, "preprocess": false}`` -> :class:`Query`."""
        try:
            req = self.query_model.model_validate_json(_utf8(body))
        except ValidationError as exc:
            raise _query_error(exc.errors(), self.limits) from None
        return req._query

    def parse_batch(self, body: bytes) -> tuple[Query, ...]:
        """``{"queries": [{"points": ..., "preprocess": false}, ...], "top_n": 5}``."""
        try:
            req = self.batch_model.model_validate_json(_utf8(body))
        except ValidationError as exc:
            raise _batch_error(exc.errors(), self.limits) from None
        return tuple(replace(q._query, top_n=req.top_n, verify=req.verify) for q in req.queries)

    def query_schema(self) -> dict[str, Any]:
        """JSON Schema of the ``/localize`` JSON body (no ``$ref``: it sits in the OpenAPI)."""
        return inline_refs(self.query_model.model_json_schema())

    def batch_schema(self) -> dict[str, Any]:
        """JSON Schema of the ``/localize/batch`` JSON body."""
        return inline_refs(self.batch_model.model_json_schema())


def _utf8(body: bytes) -> bytes | str:
    """The body as the JSON parser takes it: UTF-8 bytes as they are (no copy); UTF-16 and
    UTF-32 (told by their first bytes, as ``json.loads`` tells them) and a UTF-8 BOM decoded."""
    encoding = json.detect_encoding(body)
    if encoding == "utf-8":
        return body
    try:
        return body.decode(encoding)
    except UnicodeDecodeError as exc:
        raise MalformedJSON(f"body is not valid JSON: {exc}", "body") from None


# --------------------------------------------------------------------------------------------
# The models
# --------------------------------------------------------------------------------------------


@functools.cache
def request_models(limits: Limits) -> tuple[type[BaseModel], type[BaseModel]]:
    """``(LocalizeRequest, BatchRequest)`` for ``limits`` (built once per ``Limits``)."""
    # Local names: pydantic resolves the fields' annotations in this function's namespace.
    Cloud = _cloud_model(limits)
    PriorIn = _prior_model(limits)

    class LocalizeRequest(Cloud):
        """One query cloud."""

        top_n: int = _top_n_field(limits)
        verify: bool | None = _verify_field()
        prior: PriorIn | None = Field(None, description=PRIOR_DOC)
        _query: Query = PrivateAttr()

        @model_validator(mode="after")
        def _make(self) -> LocalizeRequest:
            prior = None if self.prior is None else self.prior.model_dump()
            self._query = Query.make(
                np.asarray(self.points, dtype=np.float64),
                limits=limits,
                preprocess=self.preprocess,
                kind=self.kind,
                top_n=self.top_n if "top_n" in self.model_fields_set else None,
                verify=self.verify,
                scale=self.scale,
                prior=prior,
            )
            return self

    class BatchQuery(Cloud):
        """One cloud of a batch."""

        _query: Query = PrivateAttr()

        @model_validator(mode="after")
        def _make(self) -> BatchQuery:
            points = np.asarray(self.points, dtype=np.float64)
            self._query = Query.make(
                points, limits=limits, preprocess=self.preprocess, kind=self.kind, scale=self.scale
            )
            return self

    class BatchRequest(BaseModel):
        """Several clouds, embedded as one batch."""

        model_config = ConfigDict(extra="forbid", strict=True)

        queries: list[BatchQuery] = Field(..., min_length=1, max_length=limits.max_batch_queries)
        top_n: int = _top_n_field(limits)
        verify: bool | None = _verify_field()

    return LocalizeRequest, BatchRequest


def _cloud_model(limits: Limits) -> type[BaseModel]:
    """The fields of one cloud, which a ``/localize`` body and each query of a batch share
    (the models built on it check them by making the :class:`Query`); its schema is split into
    the cloud's two forms (:func:`cloud_variants`)."""

    def split(schema: dict[str, Any]) -> None:
        cloud_variants(schema, limits)

    class Cloud(BaseModel):
        model_config = ConfigDict(extra="forbid", strict=True, json_schema_extra=split)

        points: list[Point] = Field(..., min_length=1, description=POINTS_DOC)
        preprocess: bool = Field(False, description="Run the filter G on a raw scan first.")
        scale: float | None = Field(
            None,
            gt=0,
            le=limits.max_scale,
            description="Metres per unit of a preprocessed cloud (its frame sidecar's scale), "
            "for a metric pose; estimated from the candidates when absent. Not for raw scans.",
        )
        kind: Literal["submap", "scan", "window"] | None = Field(
            None,
            description="What the cloud is: 'submap' (4096 preprocessed points), 'scan' (one raw "
            "scan, sensor frame, metres) or 'window' (raw scans accumulated over the last "
            "stretch of a drive, in the newest scan's frame); 'scan' and 'window' need "
            "preprocess true. Default: 'scan' with preprocess, else 'submap'. A map of "
            "keyframes (single scans) refuses windows.",
        )

    return Cloud


def _top_n_field(limits: Limits) -> Any:
    return Field(
        limits.default_top_n,
        ge=1,
        le=limits.max_top_n,
        description=f"Matches to return (at most {limits.max_top_n}).",
    )


def _verify_field() -> Any:
    return Field(
        None,
        description="Register the top candidates and re-rank them (default: when the index "
        "carries geometry; true with an index without it is refused).",
    )


def _prior_model(limits: Limits) -> type[BaseModel]:
    """A prior pose's fields, bounded by ``limits``."""

    class PriorIn(BaseModel):
        """A prior pose of the sensor."""

        model_config = ConfigDict(extra="forbid", strict=True)

        northing: float = Field(
            ..., ge=-limits.max_prior_coord, le=limits.max_prior_coord, description="UTM metres."
        )
        easting: float = Field(
            ..., ge=-limits.max_prior_coord, le=limits.max_prior_coord, description="UTM metres."
        )
        yaw_deg: float = Field(
            ...,
            ge=-360.0,
            le=360.0,
            description="Heading of the sensor's x axis, degrees counter-clockwise from east.",
        )
        height: float | None = Field(
            None,
            ge=-limits.max_raw_coord,
            le=limits.max_raw_coord,
            description="Metres, as the map's poses have it (default: the map entry's there).",
        )
        radius_m: float | None = Field(
            None,
            gt=0.0,
            le=limits.max_prior_radius_m,
            description=f"Map entries within this of the prior are registered to (at most "
            f"{limits.max_prior_radius_m:g}; default {limits.default_prior_radius_m:g}).",
        )
        run: str | None = Field(
            None,
            min_length=1,
            max_length=MAX_RUN_CHARS,
            description="The map's drive (dataset/run, as a match's submap_id begins) to register "
            "to when it has entries within the radius: the last answer's, so that consecutive "
            "poses are in one drive's frame. Default (or a drive not there): the nearest entry's.",
        )

    return PriorIn


def cloud_variants(schema: dict[str, Any], limits: Limits) -> None:
    """Turn a cloud model's object schema, in place, into ``oneOf`` its two forms with the
    counts and bounds that ``Limits.check_points`` enforces: exactly ``points_per_cloud``
    points within ``bound`` (``preprocess`` false or absent), or ``min_raw_points`` to
    ``max_raw_points`` points within ``max_raw_coord`` (``preprocess: true``, required), each
    with the kinds it can be (``submap``; ``scan`` or ``window``)."""
    head = {k: schema.pop(k) for k in ("title", "description") if k in schema}
    pre, raw = copy.deepcopy(schema), copy.deepcopy(schema)
    for form, lo, hi, bound, flag in (
        (pre, limits.points_per_cloud, limits.points_per_cloud, limits.bound, False),
        (raw, limits.min_raw_points, limits.max_raw_points, limits.max_raw_coord, True),
    ):
        points = form["properties"]["points"]
        points.update(minItems=lo, maxItems=hi)
        points["items"] = copy.deepcopy(points["items"])
        points["items"]["items"].update(minimum=-bound, maximum=bound)
        form["properties"]["preprocess"]["enum"] = [flag]
        kinds = ["scan", "window"] if flag else ["submap"]  # what each form can be
        form["properties"]["kind"]["anyOf"][0]["enum"] = kinds
    del raw["properties"]["preprocess"]["default"]
    del raw["properties"]["scale"]  # a raw scan is in metres
    if "prior" in pre["properties"]:  # a prior is a sensor's pose: raw scans only
        pre["properties"]["prior"] = {"type": "null", "description": "Raw scans only."}
    raw["required"] = [*schema.get("required", []), "preprocess"]
    schema.clear()
    schema.update(head, oneOf=[pre, raw])


def inline_refs(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with every ``{"$ref": "#/$defs/X"}`` replaced by ``X`` and no ``$defs``."""
    defs = schema.get("$defs", {})

    def walk(node: Any) -> Any:
        if isinstance(node, dict):
            ref = node.get("$ref")
            if isinstance(ref, str) and ref.startswith("#/$defs/"):
                return walk(defs[ref.removeprefix("#/$defs/")])
            return {k: walk(v) for k, v in node.items() if k != "$defs"}
        if isinstance(node, list):
            return [walk(v) for v in node]
        return node

    return walk(schema)


# --------------------------------------------------------------------------------------------
# Pydantic's errors as today's InputError
# --------------------------------------------------------------------------------------------

Loc = tuple[Any, ...]


def _cloud_rank(err: dict[str, Any], loc: Loc) -> tuple[Any, ...]:
    """Where an error about one cloud comes in reading order (``loc`` relative to the cloud):
    the object itself, unknown fields, a missing ``points``, ``top_n``, ``preprocess``, the
    points in order (a point's shape before its coordinates), the values' checks last."""
    kind = err["type"]
    if not loc:
        return (7,) if kind == "value_error" else (1,)
    if kind == "extra_forbidden" and len(loc) == 1:
        return (2,)
    if loc[0] == "points":
        if len(loc) == 1:
            return (3,) if kind == "missing" else (6, -1, 0, 0)
        if len(loc) == 2:
            return (6, loc[1], 0, 0)
        return (6, loc[1], int(kind == "float_type"), loc[2])
    ranks = {
        "top_n": (4,),
        "preprocess": (5,),
        "verify": (5, 1),
        "scale": (5, 2),
        "kind": (5, 3),
        "prior": (5, 4),
    }
    return ranks.get(loc[0], (8,))


def _cloud_error(
    err: dict[str, Any],
    loc: Loc,
    errors: list[dict[str, Any]],
    where: str,
    prefix: str,
    allowed: list[str],
    limits: Limits,
) -> InputError:
    """The :class:`InputError` of the first error ``err`` of one cloud (``loc`` relative to it;
    ``errors``: the errors of its fields); ``where`` names the cloud's object, ``prefix`` its
    fields, ``allowed`` its field names."""
    kind, value = err["type"], err.get("input")
    if not loc and kind == "value_error":
        inner = err["ctx"]["error"]
        if isinstance(inner, InputError):
            return InputError(inner.detail, f"{prefix}{inner.source}")
        return InputError(str(inner), where)
    if not loc:
        return InputError(f"expected a JSON object, got {type(value).__name__}", where)
    if loc[0] == "prior":
        return _prior_error(err, loc, limits)
    if kind == "extra_forbidden":
        extra = sorted(str(e["loc"][-1]) for e in errors if e["type"] == "extra_forbidden")
        return InputError(f"unknown fields {extra}; allowed: {allowed}", where)
    if loc == ("points",):
        if kind == "missing":
            return InputError("field required", f"{prefix}points")
        if kind == "too_short":
            return InputError("expected at least one point, got an empty list", f"{prefix}points")
        return InputError(
            f"expected a list of [x, y, z] points, got {type(value).__name__}", f"{prefix}points"
        )
    if loc[0] == "points":
        i = loc[1]
        field = f"{prefix}points[{i}]"
        if kind == "float_type":
            return InputError(f"point {i} has a non-numeric coordinate {value!r}", field)
        what = f"{len(value)} values" if isinstance(value, list) else type(value).__name__
        return InputError(f"point {i} must be [x, y, z], got {what}", field)
    if loc in (("preprocess",), ("verify",)):
        return InputError(f"expected true or false, got {show_value(value)}", loc[0])
    if loc[0] == "kind":
        return InputError(
            f"must be one of ['submap', 'scan', 'window'], got {show_value(value)}",
            f"{prefix}kind",
        )
    if loc == ("scale",):
        try:
            limits.check_scale(value)
        except InputError as exc:
            return InputError(exc.detail, f"{prefix}scale")
        return InputError(f"invalid scale {show_value(value)}", f"{prefix}scale")
    return InputError(err.get("msg", "invalid value"), ".".join(map(str, loc)))


def _prior_error(err: dict[str, Any], loc: Loc, limits: Limits) -> InputError:
    """A ``prior`` field's error as the library's check words it."""
    kind, value = err["type"], err.get("input")
    if len(loc) == 1:
        return InputError(
            f"expected an object {{northing, easting, yaw_deg, height?, radius_m?, run?}}, got "
            f"{show_value(value)}",
            "prior",
        )
    name = str(loc[1])
    field = f"prior.{name}"
    if kind == "extra_forbidden":
        return InputError(
            "unknown field; allowed: ['easting', 'height', 'northing', 'radius_m', 'run', "
            "'yaw_deg']",
            field,
        )
    if kind == "missing":
        return InputError("field required: a prior is northing, easting and yaw_deg (height "
                          "optional)", field)  # fmt: skip
    if name == "radius_m":
        try:
            limits.check_radius(value, field)
        except InputError as exc:
            return exc
    if name == "run":
        try:
            limits.check_prior(0.0, 0.0, 0.0, run=value)
        except InputError as exc:
            return exc
    probe = {"northing": 0.0, "easting": 0.0, "yaw_deg": 0.0, name: value}
    try:
        limits.check_prior(**probe)
    except InputError as exc:
        return exc
    return InputError(err.get("msg", "invalid value"), field)


def _json_error(errors: list[dict[str, Any]]) -> MalformedJSON | None:
    for e in errors:
        if e["type"] == "json_invalid":
            reason = e.get("ctx", {}).get("error") or e.get("msg", "")
            return MalformedJSON(f"body is not valid JSON: {reason}", "body")
    return None


def _top_n_error(value: Any, limits: Limits) -> InputError:
    try:
        limits.check_top_n(value)
    except InputError as exc:
        return exc
    return InputError(f"invalid top_n {show_value(value)}", "top_n")  # pragma: no cover


def _query_error(errors: list[dict[str, Any]], limits: Limits) -> InputError:
    """The first of a ``/localize`` body's errors as an :class:`InputError`."""
    bad = _json_error(errors)
    if bad is not None:
        return bad
    err = min(errors, key=lambda e: _cloud_rank(e, tuple(e["loc"])))
    loc = tuple(err["loc"])
    if loc == ("top_n",):
        return _top_n_error(err.get("input"), limits)
    top = [e for e in errors if len(e["loc"]) == 1]
    allowed = ["kind", "points", "preprocess", "prior", "scale", "top_n", "verify"]
    return _cloud_error(err, loc, top, "body", "", allowed, limits)


def _batch_rank(err: dict[str, Any]) -> tuple[Any, ...]:
    loc, kind = tuple(err["loc"]), err["type"]
    if not loc:
        return (1,)
    if kind == "extra_forbidden" and len(loc) == 1:
        return (2,)
    if loc[0] == "queries":
        if len(loc) == 1:
            return (3,) if kind == "missing" else (5,)
        return (6, loc[1], *_cloud_rank(err, loc[2:]))
    return {"top_n": (4,), "verify": (4, 1)}.get(loc[0], (8,))


def _batch_error(errors: list[dict[str, Any]], limits: Limits) -> InputError:
    """The first of a ``/localize/batch`` body's errors as an :class:`InputError`."""
    bad = _json_error(errors)
    if bad is not None:
        return bad
    err = min(errors, key=_batch_rank)
    loc, kind, value = tuple(err["loc"]), err["type"], err.get("input")
    rank = _batch_rank(err)
    if rank == (1,):
        return InputError(f"expected a JSON object, got {type(value).__name__}", "body")
    if rank == (2,):
        extra = sorted(str(e["loc"][0]) for e in errors if len(e["loc"]) == 1 and e["type"] == kind)
        return InputError(
            f"unknown fields {extra}; allowed: ['queries', 'top_n', 'verify']", "body"
        )
    if rank == (3,):
        return InputError("field required", "queries")
    if rank == (4,):
        return _top_n_error(value, limits)
    if rank == (4, 1):
        return InputError(f"expected true or false, got {show_value(value)}", "verify")
    if rank == (5,):
        n = len(value) if isinstance(value, list) else type(value).__name__
        return InputError(
            f"expected a list of 1 to {limits.max_batch_queries} queries, got {n}", "queries"
        )
    if rank[0] == 6:
        i = loc[1]
        same = [e for e in errors if tuple(e["loc"][:2]) == ("queries", i) and len(e["loc"]) == 3]
        allowed = ["kind", "points", "preprocess", "scale"]
        return _cloud_error(err, loc[2:], same, f"queries[{i}]", f"queries[{i}].", allowed, limits)
    return InputError(err.get("msg", "invalid value"), ".".join(map(str, loc)))
