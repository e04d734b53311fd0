"""The query parameters of the localisation routes (a binary body's: a JSON body says these in
itself), bounded by the contract's limits, as FastAPI dependencies that give a
:class:`~pnvlad_service.server.bodies.BinaryParams`. Their descriptions are the OpenAPI
document's."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

from fastapi import Query

from pnvlad_service.localization.query.limits import MAX_RUN_CHARS
from pnvlad_service.server.bodies import BinaryParams
from pnvlad_service.server.contract import Contract


def prior_params(contract: Contract) -> dict[str, Any]:
    """The ``prior_*`` query parameters of binary bodies, by the field they fill."""
    radius = contract.limits.max_prior_radius_m
    coord = contract.limits.max_prior_coord
    return {
        "northing": Query(
            None,
            ge=-coord,
            le=coord,
            description="Prior pose of the sensor (binary bodies), UTM metres: with "
            "prior_easting and prior_yaw_deg the scan is registered to the map entries near it, "
            "no retrieval (mode 'prior'; raw scans only).",
        ),
        "easting": Query(None, ge=-coord, le=coord, description="Prior pose: UTM metres."),
        "yaw_deg": Query(
            None,
            ge=-360.0,
            le=360.0,
            description="Prior pose: heading of the sensor's x axis, degrees from east.",
        ),
        "height": Query(
            None,
            ge=-contract.limits.max_raw_coord,
            le=contract.limits.max_raw_coord,
            description="Prior pose: metres (default: the map's).",
        ),
        "radius_m": Query(
            None,
            gt=0.0,
            le=radius,
            description=f"Prior pose: map entries within this many metres are registered to "
            f"(at most {radius:g}; default {contract.limits.default_prior_radius_m:g}).",
        ),
        "run": Query(
            None,
            min_length=1,
            max_length=MAX_RUN_CHARS,
            description="Prior pose: the map's drive (dataset/run) to register to when it has "
            "entries within the radius (the last answer's).",
        ),
    }


class _Params(NamedTuple):
    """The query parameters of binary bodies, as FastAPI declares them."""

    top_n: Any
    preprocess: Any
    verify: Any
    scale: Any
    kind: Any
    dtype: Any
    prior: dict[str, Any]


def _params(contract: Contract) -> _Params:
    """The routes' query parameters, bounded by ``contract``'s limits."""
    return _Params(
        top_n=Query(
            None,
            ge=1,
            le=contract.limits.max_top_n,
            description="Matches to return (binary bodies).",
        ),
        preprocess=Query(None, description="Raw scan: run the filter G first (binary bodies)."),
        verify=Query(
            None,
            description="Register the top candidates and re-rank them (binary bodies; default: "
            "when the index carries geometry).",
        ),
        scale=Query(
            None,
            gt=0,
            le=contract.limits.max_scale,
            description="Metres per unit of a preprocessed cloud, for a metric pose (binary "
            "bodies).",
        ),
        kind=Query(
            None,
            pattern="^(submap|scan|window)$",
            description="What the cloud is (binary bodies): 'submap' (4096 preprocessed points), "
            "'scan' (one raw scan, sensor frame, metres) or 'window' (raw scans accumulated over "
            "the last stretch of a drive, in the newest scan's frame); scan and window are raw "
            "(the filter G runs first). Default: 'scan' with preprocess=true, else 'submap'. A "
            "map of keyframes refuses windows (422).",
        ),
        dtype=Query(
            None,
            pattern="^(float32|float64)$",
            description="Element type of an application/octet-stream body (default float32; "
            "or the header X-Points-Dtype).",
        ),
        prior=prior_params(contract),
    )


def one_query(contract: Contract) -> Callable[..., BinaryParams]:
    """The dependency of ``POST /localize``'s query parameters."""
    q = _params(contract)

    def params(
        top_n: int | None = q.top_n,
        preprocess: bool | None = q.preprocess,
        dtype: str | None = q.dtype,
        verify: bool | None = q.verify,
        scale: float | None = q.scale,
        kind: str | None = q.kind,
        prior_northing: float | None = q.prior["northing"],
        prior_easting: float | None = q.prior["easting"],
        prior_yaw_deg: float | None = q.prior["yaw_deg"],
        prior_height: float | None = q.prior["height"],
        prior_radius_m: float | None = q.prior["radius_m"],
        prior_run: str | None = q.prior["run"],
    ) -> BinaryParams:
        prior = {
            "northing": prior_northing,
            "easting": prior_easting,
            "yaw_deg": prior_yaw_deg,
            "height": prior_height,
            "radius_m": prior_radius_m,
            "run": prior_run,
        }
        return BinaryParams(top_n, preprocess, verify, scale, kind, dtype, prior)

    return params


def batch(contract: Contract) -> Callable[..., BinaryParams]:
    """The dependency of ``POST /localize/batch``'s query parameters."""
    q = _params(contract)

    def params(
        top_n: int | None = q.top_n,
        preprocess: bool | None = q.preprocess,
        verify: bool | None = q.verify,
    ) -> BinaryParams:
        return BinaryParams(top_n, preprocess, verify)

    return params
