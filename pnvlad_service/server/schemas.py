"""Response schemas, for the OpenAPI document and for clients.

The routes write the answers themselves (``Answer.to_json``); these models document them.
``Timings``, ``ModelOut`` and ``IndexOut`` are made from the localiser's dataclasses
(:mod:`pnvlad_service.localization.query.answers`), so the answer and its schema have one list of
fields. The request models live in :mod:`pnvlad_service.server.contract`, where they validate.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from pnvlad_service.localization.query import answers


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
    retrieval_rank: int = Field(..., description="Rank by descriptor distance (1 = nearest).")
    score: float | None = Field(
        None, description="Verification score (share of query points registered), or null."
    )
    kind: Literal["submap", "keyframe"] = Field(
        "submap", description="What the map entry is: a submap, or a keyframe (one scan)."
    )


class PoseOut(BaseModel):
    """The query's pose on the map from its best verified match."""

    northing: float = Field(..., description="UTM metres.")
    easting: float = Field(..., description="UTM metres.")
    height: float = Field(..., description="Metres, as the map's poses have it.")
    yaw_deg: float = Field(..., description="Heading of the query frame's x axis, from east.")
    transform: list[list[float]] = Field(..., description="4x4, query frame -> UTM.")
    fitness: float = Field(..., description="Share of query points within the inlier distance.")
    rmse_m: float = Field(..., description="RMS distance of those points, metres.")
    frame: str = Field(..., description="sensor (a raw scan) or centroid (a preprocessed cloud).")
    scale: str = Field(..., description="measured, or estimated from the candidates.")
    metres_per_unit: float | None = Field(
        None,
        description="The query's scale the pose was made with: the one given (or G's), or the "
        "one its registration found when estimated.",
    )
    constraint: float = Field(
        ...,
        description="How evenly the registration pins the translation: the smallest over the "
        "largest eigenvalue of its translational Hessian (near 0: free along a direction).",
    )
    covariance: list[list[float]] | None = Field(
        None,
        description="With a prior: 6x6 covariance of the pose, x (easting), y (northing), z "
        "(height) in metres, then rotations about x, y, z in radians (UTM axes, about the "
        "sensor; as ROS's PoseWithCovariance), from the point-to-plane residuals; null else.",
    )
    sigma_m: float | None = Field(
        None,
        description="With a prior: the largest horizontal standard deviation of the "
        "covariance, metres.",
    )


class VerificationOut(BaseModel):
    candidates: int = Field(..., description="Candidates offered for verification (K).")
    registered: int = Field(
        ..., description="Candidates registered: fewer than K when a sure match ended it early."
    )
    threshold: float = Field(..., description="Score a best match needs to count as verified.")
    best_score: float = Field(..., description="The best match's score.")
    confidence: float = Field(
        ...,
        description="What verified is decided on (0-1): the best score less a rival place's, "
        "scaled down when the alignment leaves the translation free along a direction.",
    )
    reason: str | None = Field(None, description="Why nothing could be verified, if so.")


class PriorOut(BaseModel):
    """A query with a prior pose: the prior as given and what registering near it found."""

    northing: float = Field(..., description="UTM metres, as given.")
    easting: float = Field(..., description="UTM metres, as given.")
    yaw_deg: float = Field(..., description="Heading of the sensor's x axis from east, as given.")
    height: float | None = Field(None, description="Metres, as given (null: the map's).")
    radius_m: float = Field(..., description="The map entries within this were searched.")
    run: str | None = Field(None, description="The map's drive asked for, as given.")
    submaps: int = Field(..., description="Map entries (of one drive) registered to.")
    fitness: float = Field(..., description="Share of the scan's points on the map after it.")
    uncertain: bool = Field(
        False,
        description="The scan fits the map there, but the pose is too uncertain along some "
        "direction to be verified (a street that leaves the shift along it free).",
    )
    constraint: float = Field(..., description="As the pose's.")
    sigma_m: float | None = Field(
        None, description="Largest horizontal standard deviation of the pose, metres."
    )
    correction_m: float | None = Field(
        None, description="How far the registration moved the sensor from the prior, metres."
    )
    correction_yaw_deg: float | None = Field(None, description="... and turned it, degrees.")
    registered: PoseOut | None = Field(
        None,
        description="The registration's pose and covariance when it is not verified (too "
        "uncertain along a direction, or fitting under the threshold): what a tracker weighs "
        "against its odometry; null else (a verified one is the answer's pose).",
    )


#: ``Timings.to_json``: milliseconds per stage.
Timings = _json_model(answers.Timings, "Timings", "Milliseconds spent per stage.")
ModelOut = _json_model(answers.ModelInfo, "ModelOut", arch=None)
IndexOut = _json_model(answers.IndexInfo, "IndexOut")


_QUERY_KIND = Field(
    "submap", description="What the query was asked as: a submap, a raw scan or a window."
)
_MAP_KIND = Field("submap", description="What the map's entries are: submaps or keyframes.")
_MODE = Field(
    "search",
    description="search: the cloud was embedded, searched for and verified; prior: it was "
    "registered to the map near the prior pose it gave (no embedding).",
)
_PRIOR = Field(None, description="With a prior pose: that registration; null else.")
_NO_RETURNS = Field(
    0,
    ge=0,
    description="Points of a raw scan within 0.1 m of the sensor, dropped before the filter G: "
    "missing returns that a driver wrote as zeros (Ouster's). 0 for a preprocessed submap.",
)


class LocalizeResponse(BaseModel):
    matches: list[MatchOut]
    query_kind: Literal["submap", "scan", "window"] = _QUERY_KIND
    map_kind: Literal["submap", "keyframe"] = _MAP_KIND
    mode: Literal["search", "prior"] = _MODE
    verified: bool | None = Field(
        None,
        description="Whether the best match is verified (with a prior: whether the scan "
        "registered to the map near it); null when verification was off.",
    )
    pose: PoseOut | None = None
    verification: VerificationOut | None = None
    prior: PriorOut | None = _PRIOR
    no_returns: int = _NO_RETURNS
    timings_ms: Timings
    batch_size: int = Field(..., description="Clouds embedded together with this one.")
    model: ModelOut
    index: IndexOut


class BatchItem(BaseModel):
    matches: list[MatchOut]
    query_kind: Literal["submap", "scan", "window"] = _QUERY_KIND
    map_kind: Literal["submap", "keyframe"] = _MAP_KIND
    mode: Literal["search", "prior"] = _MODE
    verified: bool | None = None
    pose: PoseOut | None = None
    verification: VerificationOut | None = None
    prior: PriorOut | None = _PRIOR
    no_returns: int = _NO_RETURNS
    timings_ms: Timings
    batch_size: int


class BatchResponse(BaseModel):
    results: list[BatchItem]
    timings_ms: Timings
    model: ModelOut
    index: IndexOut


class Health(BaseModel):
    status: str


class Ready(BaseModel):
    """``/readyz``: ready, what embeds (``onnxruntime 1.22.0, 2 threads`` or ``torch ...``) and
    the bundle in service."""

    status: str
    runtime: str
    index: dict[str, Any]


class ReloadRequest(BaseModel):
    """``POST /admin/reload``: the bundle to serve next (default: the serving bundle's path,
    read again) and its model (default: the serving model). Paths on the server."""

    model_config = ConfigDict(extra="forbid")

    index: str | None = Field(None, description="Index bundle directory on the server.")
    checkpoint: str | None = Field(
        None, description="Model directory on the server (default: the serving model)."
    )


class ReloadResponse(BaseModel):
    """What a reload swapped: the bundle and model before and after."""

    previous: dict[str, Any]
    current: dict[str, Any]
    index_path: str
    encoder_reused: bool
    load_s: float
    drain_s: float
    runtime: str


class PriorInfo(BaseModel):
    """How a query with a prior pose is registered here (the settings, or the bundle's map)."""

    aligned_map: bool = Field(
        description="The bundle records its map as aligned (pnvlad map align: its drives "
        "agree), so that by default a prior registers to the nearest entries of any drive."
    )
    same_run: bool = Field(description="Registered to the entries of one drive at a time.")
    max_submaps: int = Field(description="Nearest entries laid together and registered to.")
    retry_submaps: int = Field(
        description="Entries a fit under min_fitness is tried against once more (0: never)."
    )
    min_fitness: float
    max_sigma_m: float | None


class Info(BaseModel):
    manifest: dict[str, Any]
    utm_zone: str | None = Field(
        None,
        description="The UTM zone of the map's coordinates (e.g. '30U', '17 south'), which every "
        "match carries; null when the map was built without one (pnvlad index build "
        "--utm-zone, or data prepare --utm-zone, gives it).",
        examples=["30U"],
    )
    model: dict[str, Any]
    runtime: str
    limits: dict[str, Any]
    prior: PriorInfo
