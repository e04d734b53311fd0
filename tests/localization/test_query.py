"""The one query type: ``Query.make`` checks a query's rules once, and every way a query arrives
(the server's JSON bodies, its binary bodies with their query parameters, the library) is
refused by the same rule, naming its own field; the inline runner never suspends."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest

from pnvlad_service.errors import InputError
from pnvlad_service.localization.query.limits import MIN_RAW_POINTS, Limits
from pnvlad_service.localization.query.query import PRIOR_RAW, PRIOR_VERIFY, SCALE_RAW, Query
from pnvlad_service.localization.query.run import INLINE, run_inline
from pnvlad_service.server.bodies import JSON, OCTET, BinaryParams, read_query
from pnvlad_service.server.contract import Contract

LIMITS = Limits()
CONTRACT = Contract(LIMITS)
PRIOR = {"northing": 5735000.0, "easting": 620000.0, "yaw_deg": 10.0}


def scan(n: int = 600) -> np.ndarray:
    rng = np.random.default_rng(n)
    return np.c_[rng.uniform(-20, 20, (n, 2)), np.where(np.arange(n) % 2, 0.0, 2.0)]


def submap() -> np.ndarray:
    return np.random.default_rng(1).uniform(-0.9, 0.9, (4096, 3))


def refusal(fn: Any) -> tuple[str, str]:
    with pytest.raises(InputError) as err:
        fn()
    return err.value.detail, str(err.value.source)


def by_json(points: np.ndarray, **fields: Any) -> Query:
    return CONTRACT.parse_query(json.dumps({"points": points.tolist(), **fields}).encode())


def by_binary(points: np.ndarray, prior: dict[str, Any] | None = None, **params: Any) -> Query:
    body = np.ascontiguousarray(points, dtype="<f4").tobytes()
    return read_query(CONTRACT, OCTET, body, BinaryParams(prior=prior or {}, **params))


def by_library(points: np.ndarray, **kw: Any) -> Query:
    return Query.make(points, limits=LIMITS, **kw)


@pytest.mark.parametrize(
    ("rule", "points", "json_fields", "binary_params", "library", "message", "fields"),
    [
        ("a prior needs a raw scan", submap(), {"prior": PRIOR}, {"prior": PRIOR},
         {"prior": PRIOR}, PRIOR_RAW, ("prior", "prior_northing", "prior")),
        ("no verify=false with a prior", scan(),
         {"preprocess": True, "verify": False, "prior": PRIOR},
         {"preprocess": True, "verify": False, "prior": PRIOR},
         {"preprocess": True, "verify": False, "prior": PRIOR}, PRIOR_VERIFY,
         ("verify", "verify", "verify")),
        ("no scale on a raw scan", scan(), {"preprocess": True, "scale": 20.0},
         {"preprocess": True, "scale": 20.0}, {"preprocess": True, "scale": 20.0}, SCALE_RAW,
         ("scale", "scale", "scale")),
        ("G's fewest points", scan(MIN_RAW_POINTS - 1), {"preprocess": True},
         {"preprocess": True}, {"preprocess": True}, "between 16 and",
         ("points", "body", "points")),
        ("kind and preprocess agree", scan(), {"preprocess": True, "kind": "submap"},
         {"preprocess": True, "kind": "submap"}, {"preprocess": True, "kind": "submap"},
         "a submap query is 4096 preprocessed points", ("preprocess",) * 3),
    ],
)  # fmt: skip
def test_every_way_in_is_refused_by_the_same_rule(
    rule: str,
    points: np.ndarray,
    json_fields: dict,
    binary_params: dict,
    library: dict,
    message: str,
    fields: tuple[str, str, str],
) -> None:
    got = [
        refusal(lambda: by_json(points, **json_fields)),
        refusal(lambda: by_binary(points, **binary_params)),
        refusal(lambda: by_library(points, **library)),
    ]
    assert all(message in detail for detail, _ in got), (rule, got)
    assert tuple(field for _, field in got) == fields, (rule, got)


def test_the_three_ways_in_make_the_same_query() -> None:
    pts = scan()
    a = by_json(pts.astype(np.float32), preprocess=True, top_n=3, prior={**PRIOR, "run": "x/y"})
    b = by_binary(pts, preprocess=True, top_n=3, prior={**PRIOR, "run": "x/y"})
    c = by_library(pts.astype(np.float32), preprocess=True, top_n=3, prior={**PRIOR, "run": "x/y"})
    for q in (a, b, c):
        assert (q.kind, q.top_n, q.raw, q.scale, q.verify) == ("scan", 3, True, None, None)
        assert q.prior is not None and q.prior.run == "x/y" and q.prior.radius_m == 20.0
        assert np.array_equal(q.points, pts.astype(np.float32).astype(np.float64))
    assert by_library(scan(MIN_RAW_POINTS), preprocess=True).points.shape == (16, 3)
    assert by_json(submap()).kind == "submap" and by_json(submap()).top_n == 5
    with pytest.raises(InputError):  # JSON is not a binary body: its prior is in the body
        read_query(CONTRACT, JSON, b"{}", BinaryParams(prior=PRIOR))


def test_the_inline_runner_finishes_without_an_event_loop() -> None:
    async def steps() -> int:
        first = await INLINE.blocking(lambda x: x + 1, 1)
        from concurrent.futures import Future

        done: Future[int] = Future()
        done.set_result(40)
        return first + await INLINE.wait(done)

    assert run_inline(steps()) == 42

    async def suspends() -> None:
        import asyncio

        await asyncio.sleep(0)

    with pytest.raises(RuntimeError, match="suspended"):
        run_inline(suspends())
