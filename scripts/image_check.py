"""The HTTP checks of scripts/image_test.sh against a running container (standard library only).

Picks a query submap of a run that is not in the server's index, inside the dataset's test
regions (training never saw them): the one nearest the middle of the held-out run's part of
the regions, so the choice does not depend on the model. Its right answer is the indexed submap
nearest to it in UTM; the benchmark counts a top-1 match within ``--radius`` metres (25) as
right. Then:

- ``POST /localize`` without the token must answer 401 (application/problem+json);
- with ``Authorization: Bearer TOKEN`` it must answer 200 with a right top-1 match;
- every other held-out query in the test regions is sent too and counted (printed, not judged);
- with ``--raw``, the query's raw scan (``raw_scans/<timestamp>.bin``, KITTI layout) is sent with
  ``preprocess=true``: it must answer 200 (the filter G and verification ran in the image);
- with ``--reload PATH`` (the bundle's path in the container), ``POST /admin/reload``: 401
  without the token, 422 naming a bundle that is not there, 200 for PATH read again (the old
  and the new bundle the same), and the query's top-1 right again.

Exits 0 when every check passes, 1 otherwise.

    python3 scripts/image_check.py --url http://127.0.0.1:8000 --root city --dataset business \
        --held 2026-03-25-15-04-29 --token secret --raw --reload /data/index
"""

from __future__ import annotations

import argparse
import array
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


def _post(
    url: str,
    body: bytes,
    token: str | None,
    path: str = "/localize?top_n=3&dtype=float64",
    ctype: str = "application/octet-stream",
) -> tuple[int, str, bytes]:
    headers = {"Content-Type": ctype}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    req = urllib.request.Request(
        f"{url.rstrip('/')}{path}", data=body, headers=headers, method="POST"
    )
    try:
        with urllib.request.urlopen(req, timeout=60) as resp:
            return resp.status, resp.headers.get("Content-Type", ""), resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("Content-Type", ""), exc.read()
    except (urllib.error.URLError, OSError) as exc:
        return 0, "", f"cannot reach {url}: {exc}".encode()


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--url", required=True)
    ap.add_argument("--root", type=Path, required=True, help="benchmark tree root")
    ap.add_argument("--dataset", required=True)
    ap.add_argument("--held", required=True, help="the run left out of the index")
    ap.add_argument("--token", required=True, help="the server's PNVLAD_API_KEY")
    ap.add_argument("--radius", type=float, default=25.0)
    ap.add_argument("--raw", action="store_true", help="also send the query's raw scan")
    ap.add_argument("--reload", metavar="PATH", help="also reload the bundle at PATH")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)

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
    if args.raw:
        ok &= _raw_scan(args, ds / args.held / "raw_scans" / f"{query[0]}.bin", query)
    if args.reload:
        ok &= _reload(args, body, answer, query)
    return 0 if ok else 1


def _raw_scan(args: argparse.Namespace, path: Path, query: tuple[str, float, float]) -> bool:
    """The query's raw scan (float32 x, y, z, intensity) as float32 xyz, preprocess=true."""
    values = array.array("f")
    values.frombytes(path.read_bytes())
    xyz = array.array("f")
    for i in range(0, len(values), 4):
        xyz.extend(values[i : i + 3])
    status, _, raw = _post(args.url, xyz.tobytes(), args.token, "/localize?preprocess=true")
    if status != 200:
        print(f"  its raw scan ({len(xyz) // 3} points, preprocess=true): {status} {raw[:300]!r}"
              "  WRONG")  # fmt: skip
        return False
    answer = json.loads(raw)
    top = answer["matches"][0]
    off = math.hypot(top["northing"] - query[1], top["easting"] - query[2])
    print(
        f"  its raw scan ({len(xyz) // 3} points, preprocess=true): 200, verified "
        f"{answer['verified']}, top-1 {off:.1f} m from the truth (a single scan: information "
        f"only); preprocess {answer['timings_ms']['preprocess']:.1f} ms"
    )
    return True


def _reload(
    args: argparse.Namespace, body: bytes, before: dict, query: tuple[str, float, float]
) -> bool:
    """POST /admin/reload: refused without the token and for a missing bundle, then done."""
    ok = True
    js = "application/json"
    status, ctype, _ = _post(args.url, b"{}", None, "/admin/reload", js)
    good = status == 401 and ctype.startswith("application/problem+json")
    ok &= good
    print(f"  reload without the token: {status}  {'ok' if good else 'WRONG'}")
    missing = args.reload.rstrip("/") + "-missing"
    status, _, raw = _post(args.url, json.dumps({"index": missing}).encode(), args.token,
                           "/admin/reload", js)  # fmt: skip
    good = status == 422 and missing in json.loads(raw).get("detail", "")
    ok &= good
    print(f"  reload of {missing}: {status}, naming it  {'ok' if good else 'WRONG'}")
    status, _, raw = _post(args.url, json.dumps({"index": args.reload}).encode(), args.token,
                           "/admin/reload", js)  # fmt: skip
    if status != 200:
        print(f"  reload of {args.reload}: {status} {raw[:300]!r}  WRONG")
        return False
    done = json.loads(raw)
    same = done["current"]["index"] == before["index"]
    status, _, raw = _post(args.url, body, args.token)
    after = json.loads(raw) if status == 200 else {"matches": [{}], "index": None}
    top = after["matches"][0]
    right = (
        status == 200
        and math.hypot(top["northing"] - query[1], top["easting"] - query[2]) <= args.radius
    )
    ok &= same and right and after["index"] == done["current"]["index"]
    print(
        f"  reload of {args.reload}: 200 in {done['load_s']:.2f} s (encoder reused: "
        f"{done['encoder_reused']}), bundle {done['current']['index']['id']}"
        f"{' as before' if same else ' CHANGED'}; the query again: "
        f"{'RIGHT' if right else 'WRONG'}"
    )
    return ok


if __name__ == "__main__":
    sys.exit(main())
