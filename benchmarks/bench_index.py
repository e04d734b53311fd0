"""Index scale benchmark: build time, memory and search latency of FAISS index keys.

The database is N random unit vectors (float32, d = 256 by default); the queries are database
vectors plus Gaussian noise (a revisit of a mapped place), renormalised. For each N and key:
build (train + add) time, index size in memory (serialised bytes) and the process's peak RSS
growth, single-query search latency p50/p99 over --queries queries, and recall@1 against exact
search. Bounded: --queries (default 200) and the sizes given.

    python benchmarks/bench_index.py                          # 1e4, 1e5, 1e6 x Flat, HNSW32, IVF-PQ
    python benchmarks/bench_index.py --sizes 10000 100000 --keys Flat HNSW32

Geometry (--geometry N): writes a synthetic bundle of N submaps under --geometry-dir (random
descriptors in a Flat index, random float16 geometry rows written in chunks: N x 24,576 bytes,
24.6 GB for 1e6; checks the free disk first) and a twin bundle without the geometry (the same
index and metadata, hard-linked). Each bundle is then loaded in a fresh process, as a server
starts (IndexBundle.load, verify=True): start-up seconds and resident memory (VmRSS, RssAnon,
RssFile from /proc/self/status); then the cost of fetching 10 random candidates' points in
metres (BundleGeometry.metres_many), median and p99 over --geometry-queries queries, first with
the geometry file evicted from the page cache (posix_fadvise DONTNEED: cold), then the same
queries again (warm). The bundles are deleted afterwards unless --geometry-keep.

    python benchmarks/bench_index.py --geometry 1000000 --geometry-dir /work/bench_geo
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from entry import run


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def status_mb() -> dict[str, float]:
    """VmRSS, RssAnon and RssFile of this process, MB."""
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            key = line.split(":")[0]
            if key in ("VmRSS", "RssAnon", "RssFile"):
                out[key] = int(line.split()[1]) / 1024
    return out


def write_geometry_bundles(base: Path, n: int, dim: int) -> tuple[Path, Path]:
    """A Flat bundle of ``n`` random descriptors with random geometry rows under ``base``, and
    its twin without geometry (index and metadata hard-linked); both paths."""
    import faiss
    import numpy as np

    from pnvlad_service.index.bundle import Metadata, write_bundle
    from pnvlad_service.index.geometry import ROW_BYTES, GeometryWriter
    from pnvlad_service.index.manifest import MANIFEST_FILE, ModelRecord

    need = n * ROW_BYTES + n * dim * 4 + (2 << 30)
    free = shutil.disk_usage(base.parent if not base.exists() else base).free
    if free < need:
        sys.exit(f"{base}: {free / 1e9:.1f} GB free, the bundles need {need / 1e9:.1f} GB")
    base.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    index = faiss.IndexFlatL2(dim)
    for start in range(0, n, 100_000):
        index.add(unit(rng.standard_normal((min(100_000, n - start), dim), dtype=np.float32)))
    ts = 1_500_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000
    runs = np.array([f"run-{i // 10_000:03d}" for i in range(n)])
    meta = Metadata(
        submap_id=np.char.add("synth/", np.char.add(np.char.add(runs, "/"), ts.astype(str))),
        dataset=np.full(n, "synth"),
        run=runs,
        timestamp=ts,
        northing=5_735_000 + rng.uniform(0, 10_000, n),
        easting=620_000 + rng.uniform(0, 10_000, n),
        utm_zone=np.full(n, "30U"),
        path=np.char.add(
            np.char.add("synth/", runs), np.char.add("/pointcloud_20m/", ts.astype(str))
        ),
    )
    model = ModelRecord(None, "0" * 64, "0" * 64, {"output_dim": dim})

    def geometry(tmp: Path):
        w = GeometryWriter(tmp, n)
        chunk = 1024
        t0 = time.perf_counter()
        for start in range(0, n, chunk):
            k = min(chunk, n - start)
            rows = (rng.random((k, 4096, 3), dtype=np.float32) * 2 - 1).astype("<f2")
            origin = np.column_stack(
                [
                    meta.easting[start : start + k],
                    meta.northing[start : start + k],
                    np.full(k, 60.0),
                ]
            )
            w.append(rows, origin, rng.uniform(-5, 5, (k, 3)), rng.uniform(20, 60, k))
            if start // chunk % 100 == 0:
                print(
                    f"  geometry rows {start + k:,}/{n:,} ({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )
        return w.finish()

    with_geo = base / "with_geometry.index"
    without = base / "without_geometry.index"
    for p in (with_geo, without):
        if p.exists():
            shutil.rmtree(p)
    t0 = time.perf_counter()
    manifest = write_bundle(
        with_geo, index, meta, index_key="Flat", model=model, indexed=[], geometry=geometry
    )
    print(f"wrote {with_geo} in {time.perf_counter() - t0:.0f} s", flush=True)
    without.mkdir()
    for name in manifest.files:
        os.link(with_geo / name, without / name)
    doc = manifest.to_json()
    del doc["geometry"]
    (without / MANIFEST_FILE).write_text(json.dumps(doc, indent=2) + "\n")
    return with_geo, without


def load_and_fetch(bundle: Path, queries: int, k: int = 10) -> dict:
    """In this (fresh) process: load the bundle as a server does; with geometry, fetch ``k``
    random candidates' metres per query, cold (file evicted from the page cache) then warm."""
    import numpy as np

    from pnvlad_service.index.bundle import IndexBundle
    from pnvlad_service.index.geometry import POINTS_FILE

    geo_file = bundle / POINTS_FILE
    for f in bundle.iterdir():  # every file cold: what a start-up after a reboot reads
        fd = os.open(f, os.O_RDONLY)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        os.close(fd)
    before = status_mb()
    t0 = time.perf_counter()
    b = IndexBundle.load(bundle)
    load_s = time.perf_counter() - t0
    row = {
        "bundle": bundle.name,
        "count": b.count,
        "load_s": round(load_s, 3),
        "rss_before_mb": before,
        "rss_after_load_mb": status_mb(),
    }
    if b.geometry is None:
        return row
    g = b.geometry
    rng = np.random.default_rng(1)
    ids = rng.integers(0, g.count, (queries, k))
    fd = os.open(geo_file, os.O_RDONLY)
    os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    os.close(fd)
    for label in ("cold", "warm"):
        lat = []
        for q in ids:
            t = time.perf_counter()
            pts = g.metres_many(q)
            lat.append(time.perf_counter() - t)
            assert len(pts) == k and pts[0].shape == (4096, 3)
        p50, p99 = np.percentile(np.array(lat) * 1000, [50, 99])
        row[f"fetch{k}_{label}_p50_ms"] = round(float(p50), 3)
        row[f"fetch{k}_{label}_p99_ms"] = round(float(p99), 3)
        row[f"rss_after_{label}_mb"] = status_mb()
    row["bytes_per_submap"] = round(g.nbytes_per_submap(), 1)
    row["geometry_file_bytes"] = g.record.bytes
    return row


def geometry_benchmark(args: argparse.Namespace) -> None:
    base = Path(args.geometry_dir)
    with_geo, without = write_geometry_bundles(base, args.geometry, args.dim)
    rows = []
    try:
        for bundle in (without, with_geo, without, with_geo):  # each twice: the spread
            out = subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--geometry-load",
                    str(bundle),
                    "--geometry-queries",
                    str(args.geometry_queries),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(json.dumps(row), flush=True)
    finally:
        if not args.geometry_keep:
            shutil.rmtree(base / with_geo.name, ignore_errors=True)
            shutil.rmtree(base / without.name, ignore_errors=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument(
        "--keys",
        nargs="+",
        default=["Flat", "HNSW32", "IVF-PQ"],
        help="FAISS keys; 'IVF-PQ' means IVF{ivf_lists(N)},PQ32",
    )
    ap.add_argument("--dim", type=int, default=256)
    ap.add_argument("--queries", type=int, default=200)
    ap.add_argument("--noise", type=float, default=0.3, help="Query noise norm (unit vectors).")
    ap.add_argument("--threads", type=int, default=None, help="FAISS OpenMP threads.")
    ap.add_argument("--json", type=str, default=None, help="Also write the rows here.")
    ap.add_argument(
        "--geometry",
        type=int,
        default=None,
        metavar="N",
        help="Geometry benchmark with a synthetic bundle of N submaps instead.",
    )
    ap.add_argument("--geometry-dir", default="/work/bench_geo", help="Where it is written.")
    ap.add_argument("--geometry-queries", type=int, default=1000)
    ap.add_argument("--geometry-keep", action="store_true", help="Keep the bundles.")
    ap.add_argument("--geometry-load", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.geometry_load:
        print(json.dumps(load_and_fetch(Path(args.geometry_load), args.geometry_queries)))
        return
    if args.geometry:
        geometry_benchmark(args)
        return

    import faiss

    from pnvlad_service.index.keys import (
        apply_search_params,
        default_search_params,
        ivf_lists,
        make_index,
    )

    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    rows = []
    print(
        f"{'N':>9} {'key':<18} {'build s':>8} {'index MB':>9} {'RSS+ MB':>8} "
        f"{'p50 ms':>8} {'p99 ms':>8} {'recall@1':>8}"
    )
    for n in args.sizes:
        rng = np.random.default_rng(n)
        xb = unit(rng.standard_normal((n, args.dim), dtype=np.float32))
        pick = rng.choice(n, args.queries, replace=False)
        noise = rng.standard_normal((args.queries, args.dim), dtype=np.float32)
        xq = unit(xb[pick] + args.noise * noise / np.sqrt(args.dim))
        exact = faiss.IndexFlatL2(args.dim)
        exact.add(xb)
        _, gt = exact.search(xq, 1)
        del exact
        for key in args.keys:
            real = f"IVF{ivf_lists(n)},PQ32" if key == "IVF-PQ" else key
            rss0 = rss_mb()
            t0 = time.perf_counter()
            index = make_index(xb, real)  # what `pnvlad index build` does
            build = time.perf_counter() - t0
            apply_search_params(index, default_search_params(real))
            size_mb = len(faiss.serialize_index(index)) / 2**20
            rss_grow = rss_mb() - rss0
            lat = []
            found = np.empty(args.queries, dtype=np.int64)
            for i in range(args.queries):
                t = time.perf_counter()
                _, ids = index.search(xq[i : i + 1], 1)
                lat.append(time.perf_counter() - t)
                found[i] = ids[0, 0]
            p50, p99 = np.percentile(np.array(lat) * 1000, [50, 99])
            recall = float((found == gt[:, 0]).mean())
            row = {
                "n": n,
                "key": real,
                "build_s": round(build, 2),
                "index_mb": round(size_mb, 1),
                "rss_growth_mb": round(rss_grow, 1),
                "p50_ms": round(float(p50), 3),
                "p99_ms": round(float(p99), 3),
                "recall_at_1": recall,
                "params": default_search_params(real),
            }
            rows.append(row)
            print(
                f"{n:>9} {real:<18} {build:>8.2f} {size_mb:>9.1f} {rss_grow:>8.1f} "
                f"{p50:>8.3f} {p99:>8.3f} {recall:>8.3f}",
                flush=True,
            )
            del index
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MB; faiss threads {faiss.omp_get_max_threads()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    run(main)
