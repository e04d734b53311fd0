"""The HTTP checks of scripts/image_test.sh against a running container (standard library only).

Picks a query submap of a run that is not in the server's index, inside the dataset's test
regions (training never saw them): the one nearest the middle of the held-out run's part of
the regions, so the choice does not depend on the model. Its right answer is the indexed submap
nearest to it in UTM; the benchmark counts a top-1 match within ``--radius`` metres (25) as
right. Then:

- ``POST /localize`` without the token must answer 401 (application/problem+json);
- with ``Authorization: Bearer TOKEN`` it must answer 200 with a right top-1 match;
- every other held-out query in the test regions is sent too and counted (printed, not judged).

Exits 0 when both checks pass, 1 otherwise.

    python3 scripts/image_check.py --url http://127.0.0.1:8000 --root city --dataset business \
        --held 2026-03-25-15-04-29 --token secret
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import urllib.error
import urllib.request
from pathlib import Path

CSV = "pointcloud_locations_20m.csv"  # the test layout: what `pnvlad index build` indexes
SUBMAPS = "pointcloud_20m"


def _submaps(root: Path, dataset: str, run: str) -> list[tuple[str, float, float]]:
    with open(root / dataset / run / CSV, newline="") as f:
        rows = csv.DictReader(f)
        return [(r["timestamp"], float(r["northing"]), float(r["easting"])) for r in rows]


def _inside(regions: dict, n: float, e: float) -> bool:
    if regions.get("all"):
        return True
    w = float(regions["half_size"])
    return any(cn - w < n < cn + w and ce - w < e < ce + w for cn, ce in regions["centres"])


def _post(url: str, body: bytes, token: str | None) -> tuple[int, str, bytes]:
    headers = {"Content-Type": "application/octet-stream"}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    req = urllib.request.Request(
        f"{url.rstrip('/')}/localize?top_n=3&dtype=float64",
        data=body,
        headers=headers,
        method="POST",
    )
    try:
        with urllib.request.urlopen(req, timeout=60) as resp:
            return resp.status, resp.headers.get("Content-Type", ""), resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("Content-Type", ""), exc.read()
    except (urllib.error.URLError, OSError) as exc:
        return 0, "", f"cannot reach {url}: {exc}".encode()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", required=True)
    ap.add_argument("--root", type=Path, required=True, help="benchmark tree root")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--held", required=True, help="the run left out of the index")
    ap.add_argument("--token", required=True, help="the server's PNVLAD_API_KEY")
    ap.add_argument("--radius", type=float, default=25.0)
    args = ap.parse_args(argv)

    ds = args.root / args.dataset
    regions = json.loads((ds / "test_regions.json").read_text())
    indexed = [
        (run.name, *s)
        for run in sorted(p for p in ds.iterdir() if (p / CSV).is_file() and p.name != args.held)
        for s in _submaps(args.root, args.dataset, run.name)
    ]
    queries = [s for s in _submaps(args.root, args.dataset, args.held) if _inside(regions, *s[1:])]
    if not queries or not indexed:
        print(f"no held-out queries or no indexed submaps under {ds}", file=sys.stderr)
        return 1

    def nearest(q: tuple[str, float, float]) -> tuple[tuple[str, str, float, float], float]:
        best = min(indexed, key=lambda s: math.hypot(s[2] - q[1], s[3] - q[2]))
        return best, math.hypot(best[2] - q[1], best[3] - q[2])

    # The held-out query nearest the centre of the held-out queries, with a right answer to find.
    cn = sum(q[1] for q in queries) / len(queries)
    ce = sum(q[2] for q in queries) / len(queries)
    answerable = [q for q in queries if nearest(q)[1] <= args.radius]
    query = min(answerable, key=lambda q: math.hypot(q[1] - cn, q[2] - ce))
    body = (ds / args.held / SUBMAPS / f"{query[0]}.bin").read_bytes()
    (want_run, want_ts, *_), want_off = nearest(query)
    print(
        f"query {args.dataset}/{args.held}/{query[0]} (held out of the index), true N "
        f"{query[1]:.1f} E {query[2]:.1f}; nearest indexed submap {want_run}/{want_ts}, "
        f"{want_off:.1f} m away"
    )

    ok = True
    status, ctype, raw = _post(args.url, body, None)
    good = status == 401 and ctype.startswith("application/problem+json")
    ok &= good
    print(f"  without the token: {status} {ctype.split(';')[0]}  {'ok' if good else 'WRONG'}")

    status, _, raw = _post(args.url, body, args.token)
    if status != 200:
        print(f"  with the token: {status} {raw[:300]!r}  WRONG")
        return 1
    answer = json.loads(raw)
    top = answer["matches"][0]
    off = math.hypot(top["northing"] - query[1], top["easting"] - query[2])
    right = off <= args.radius
    ok &= right
    nearest_too = top["run"] == want_run and str(top["timestamp"]) == want_ts
    print(
        f"  with the token: 200, top-1 {top['run']}/{top['timestamp']} (descriptor distance "
        f"{top['distance']:.3f}), {off:.1f} m from the truth: "
        f"{'RIGHT' if right else 'WRONG'} (within {args.radius:g} m"
        f"{', the nearest indexed submap' if nearest_too else ''}); embed "
        f"{answer['timings_ms']['embed']:.1f} ms, total {answer['timings_ms']['total']:.1f} ms"
    )

    hits = 0
    for q in queries:
        status, _, raw = _post(
            args.url, (ds / args.held / SUBMAPS / f"{q[0]}.bin").read_bytes(), args.token
        )
        if status == 200:
            m = json.loads(raw)["matches"][0]
            hits += math.hypot(m["northing"] - q[1], m["easting"] - q[2]) <= args.radius
    print(
        f"  all {len(queries)} held-out queries in the test regions: {hits} right by their top-1"
        " (information only)"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
