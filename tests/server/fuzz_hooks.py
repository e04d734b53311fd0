"""Schemathesis hooks of tests/server/test_fuzz.py (loaded through ``SCHEMATHESIS_HOOKS``).

OpenAPI cannot state four of the routes' rules, which their descriptions state
in words; a schema-valid case that breaks one is no finding:

- the query parameters of a binary body go together: ``kind`` and ``preprocess`` agree, no
  ``scale`` on a raw scan, a prior (``prior_northing``, ``prior_easting`` and
  ``prior_yaw_deg`` at least) only with a raw scan and not with ``verify=false``, and no
  ``prior_*`` with a JSON body (its prior is its ``prior`` object); a JSON body with a
  ``prior`` refuses ``verify: false``. :func:`filter_case` drops the positive cases that break
  them.
- a binary body is whole xyz triples of its dtype (4096 points in [-1, 1], or a raw scan):
  :func:`map_case` gives a positive case's binary body such points, as its parameters say.
- a reload names paths on the server's disk: only a positive reload without paths (the serving
  bundle read again) is run (:func:`filter_case`);
- the filter G refuses a raw scan that cropping and ground removal leave under 16 points (all
  points on one plane, say), and a raw scan's points within 0.1 m of the sensor are missing
  returns, dropped first (fewer than 16 left is refused): the 422 that says ``filter G:`` or
  ``missing returns`` for a scan of at least 16 points (the schema's minimum) is dropped by
  :func:`filter_failure`, and only from the check that schema-valid data is accepted; one of
  fewer points stands (the schema should refuse it).

Every other check, and every other failure, stands.
"""

from __future__ import annotations

import io
from typing import Any

import numpy as np
import schemathesis

#: The filter G's fewest points (``GConfig.min_points``; tests/localization/test_limits.py).
G_FEWEST = 16
PRIOR = ("northing", "easting", "yaw_deg", "height", "radius_m", "run")
BINARY = ("application/octet-stream", "application/x-npy")


def _positive(case: Any) -> bool:
    meta = case.meta
    return meta is not None and meta.generation.mode.is_positive


def _flag(value: Any) -> bool | None:
    """A boolean query parameter as the server reads it."""
    if isinstance(value, str):
        return {"true": True, "false": False}.get(value.lower())
    return value


def _raw(query: dict[str, Any]) -> bool:
    return _flag(query.get("preprocess")) is True or query.get("kind") in ("scan", "window")


def _parameters_agree(query: dict[str, Any], json_body: bool) -> bool:
    """Whether the query parameters meet the rules their descriptions state."""
    prior = {k for k in PRIOR if query.get(f"prior_{k}") is not None}
    if json_body:
        return not prior
    pre, kind = _flag(query.get("preprocess")), query.get("kind")
    if (kind == "submap" and pre is True) or (kind in ("scan", "window") and pre is False):
        return False
    raw = _raw(query)
    if raw and query.get("scale") is not None:
        return False
    if prior and (not raw or _flag(query.get("verify")) is False):
        return False
    return not prior or {"northing", "easting", "yaw_deg"} <= prior


@schemathesis.hook
def filter_case(context: Any, case: Any) -> bool:
    if not _positive(case):
        return True
    if case.operation.path == "/admin/reload":
        # Which paths hold a bundle or a model is the server's disk, no schema's: a reload
        # of the serving bundle (no paths) is the one a positive case can expect to pass.
        body = case.body if isinstance(case.body, dict) else {}
        return body.get("index") is None and body.get("checkpoint") is None
    if not case.operation.path.startswith("/localize"):
        return True
    query = dict(case.query or {})
    json_body = case.media_type == "application/json"
    if json_body and isinstance(case.body, dict):
        prior = case.body.get("prior")
        if isinstance(prior, dict) and case.body.get("verify") is False:
            return False
    return _parameters_agree(query, json_body)


def _cloud(raw: bool, rng: np.random.Generator) -> np.ndarray:
    """4096 points in [-1, 1], or a raw scan: walls on a ground plane, metres."""
    if not raw:
        return rng.uniform(-0.9, 0.9, (4096, 3))
    n = 2000
    xy = rng.uniform(-20, 20, (n, 2))
    z = np.where(np.arange(n) % 2, 0.0, rng.uniform(0.5, 3, n))
    return np.c_[xy, z]


@schemathesis.hook
def map_case(context: Any, case: Any) -> Any:
    if not _positive(case) or case.media_type not in BINARY:
        return case
    query = dict(case.query or {})
    rng = np.random.default_rng(len(query))
    if case.operation.path == "/localize/batch":
        raw = _flag(query.get("preprocess")) is True
        arr = np.stack([_cloud(raw, rng) for _ in range(2)]) if not raw else _cloud(raw, rng)[None]
    else:
        arr = _cloud(_raw(query), rng)
    if case.media_type == "application/x-npy":
        buf = io.BytesIO()
        np.save(buf, arr.astype(np.float32), allow_pickle=False)
        case.body = buf.getvalue()
    else:
        dtype = "<f8" if query.get("dtype") == "float64" else "<f4"
        case.body = arr.astype(dtype).tobytes()
    return case


def _fewest_points(body: Any) -> int | None:
    """The fewest points of a JSON body's clouds (None: not a JSON body of clouds)."""
    if not isinstance(body, dict):
        return None
    clouds = [body] if "points" in body else list(body.get("queries") or [])
    counts = [len(c["points"]) for c in clouds if isinstance(c, dict) and "points" in c]
    return min(counts) if counts else None


@schemathesis.hook
def filter_failure(context: Any, failure: Any, case: Any, response: Any) -> bool:
    """Keep every failure but a schema-valid raw scan of at least G's fewest points (the
    schema's minimum) that the filter G refused for its geometry, or that held fewer than 16
    points that are not missing returns (points at the sensor, which the schema cannot say)."""
    if getattr(failure, "code", None) != "ST202" or response.status_code != 422:
        return True
    fewest = _fewest_points(case.body)
    if fewest is None or fewest < G_FEWEST:
        return True  # a scan the schema lets through with fewer points than G needs
    try:
        detail = response.json().get("detail", "")
    except ValueError:
        return True
    return "filter G:" not in detail and "missing returns" not in detail
