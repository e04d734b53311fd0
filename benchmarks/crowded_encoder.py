"""The encoder beside a busy core: what a server's verification child does to an embedding.

On 2 cores under load, the server embeds while its verification child registers on the other
core. A forward pass on all of torch's threads (an OpenMP team of two) then waits at each of
its ~100 parallel regions' barriers for the team thread that has no core. With
``Encoder.crowded_by`` saying so, the clouds and the head run on the single-threaded cloud
workers instead. This script times both, in this process, for a single cloud and a batch of 2:
first on idle cores, then beside a child process that verifies the bundle's own submaps in a
loop on one thread (as the server's child does under load). CPU and wall ms a pass; the
environment is the server's (``GOMP_SPINCOUNT=20000`` unless set).

    python benchmarks/crowded_encoder.py --index runs/demo/map.index [--model DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

os.environ.setdefault("GOMP_SPINCOUNT", "20000")  # as `pnvlad serve` sets it, before torch

import numpy as np
from entry import run


def verify_forever(index: str) -> None:
    """The busy core: verify turned copies of the bundle's submaps against the bundle, one
    thread, until killed."""
    os.environ.pop("GOMP_SPINCOUNT", None)  # the server's child sleeps at barriers
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    from pnvlad_service.index.bundle import IndexBundle
    from pnvlad_service.localization.verify import verify as V

    bundle = IndexBundle.load(index)
    geo = bundle.geometry
    if geo is None:
        raise SystemExit(f"{index}: the bundle carries no geometry")
    cfg = V.VerifyConfig().crowded()
    cache = V.PreparedCache(128)
    rng = np.random.default_rng(0)
    n = geo.count
    while True:
        i = int(rng.integers(n))
        a = rng.uniform(0, 2 * np.pi)
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        query = V.QueryCloud(geo.metres(i) @ turn.T, "centroid", "measured")
        ids = [(i + k) % n for k in range(10)]
        V.verify(query, V.bundle_candidates(geo, ids), cfg, cache=cache)


def timed(enc, x: np.ndarray, repeats: int) -> tuple[float, float]:
    enc.embed(x)
    c, w = time.process_time(), time.perf_counter()
    for _ in range(repeats):
        enc.embed(x)
    return 1000 * (time.process_time() - c) / repeats, 1000 * (time.perf_counter() - w) / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--index", required=True, help="A bundle with geometry.")
    ap.add_argument("--model", help="Model directory (default: the bundle's).")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--busy", action="store_true", help=argparse.SUPPRESS)  # the child's role
    args = ap.parse_args()
    if args.busy:
        verify_forever(args.index)
        return
    from pnvlad_service.index.bundle import IndexBundle
    from pnvlad_service.localization.query.localizer import checked_model
    from pnvlad_service.models.runtimes import load_encoder

    model = args.model or checked_model(args.index).checkpoint
    bundle = IndexBundle.load(args.index)
    clouds = np.stack([bundle.geometry.metres(i) for i in range(2)])
    clouds = (clouds - clouds.mean(axis=1, keepdims=True)) / np.abs(clouds).max()
    clouds = clouds.astype(np.float32)
    enc = load_encoder(model)
    print(f"{'cores':>7} {'batch':>5} {'team (before)':>22} {'workers (crowded_by)':>22}")
    for label in ("idle", "beside"):
        child = None
        if label == "beside":
            child = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), "--index", args.index, "--busy"]
            )
            time.sleep(8)  # loaded and registering
        try:
            for b in (1, 2):
                enc.crowded_by = None
                team = timed(enc, clouds[:b], args.repeats)
                enc.crowded_by = lambda: True
                workers = timed(enc, clouds[:b], args.repeats)
                print(
                    f"{label:>7} {b:>5} {team[0]:>9.1f} CPU {team[1]:>6.1f} ms "
                    f"{workers[0]:>9.1f} CPU {workers[1]:>6.1f} ms",
                    flush=True,
                )
        finally:
            if child is not None:
                child.terminate()
                child.wait()
    enc.close()


if __name__ == "__main__":
    run(main)
